/* A mapping iteration's compositing and loss terms, forward and backward, one loop over the rays.
 *
 * The CPU fast path of voxfusion.core.losses.band_losses (built and loaded by core/native/__init__.py). The
 * reference, tested against it and run everywhere else, is PyTorch's: core/render/volume.py composite() and
 * core/losses.py compute_losses(); the formulas are written out in core/losses.py (_BandLosses). Plain C99.
 *
 * Shapes (contiguous, row-major), N rays of S samples:
 *   sdf [N, S] float32 (any value where mask is 0), rgb [N, S, 3] float32 or NULL (no colour term),
 *   t [N, S] float32 ascending, mask [N, S] uint8 (bool), dn [N] float32 (metres per unit t),
 *   depth_gt [N] float32 (t-units; <= 0 or not finite: no observation), color_gt [N, 3] float32 or NULL,
 *   color_valid [N] uint8 or NULL (every ray's colour is real).
 * Per-sample arithmetic is float32 as PyTorch's; the sums over rays are accumulated in double (PyTorch sums
 * float32 in another order), so terms and gradients agree with the reference to float32 rounding.
 */
#include <math.h>
#include <stdint.h>

#define MAX_SAMPLES 64 /* samples per ray; the caller falls back to PyTorch beyond it */

typedef struct {
    double color_sum, depth_sum, free_sum, band_sum; /* sums of per-ray values */
    double n_color, n_depth, n_free, n_band;         /* rays that count for each term */
} Sums;

static float sigmoidf(float x) { return 1.0f / (1.0f + expf(-x)); }

static float signf(float x) { return (float)((x > 0.0f) - (x < 0.0f)); }

/* One ray's compositing: the masked SDF sdf0, the bell s_pos s_neg and its two sigmoids, the kept samples
 * (inside the map, not behind the first surface plus the truncation), the weights a (normalised), the weight
 * sum w_sum and its clamped value w_norm; depth and colour (color NULL without rgb). Returns hit. */
static int composite_ray(const float *sdf, const float *rgb, const float *t, const uint8_t *mask, float dn,
                         int64_t S, float tr, float b, float *sdf0, float *s_pos, float *s_neg, uint8_t *kept,
                         float *a, float *w_sum, float *w_norm, float *depth, float *color) {
    int hit = 0, surface = 0;
    float t_cross = 0.0f;
    for (int64_t s = 0; s < S; ++s) {
        sdf0[s] = mask[s] ? sdf[s] : 0.0f;
        hit |= mask[s] != 0;
    }
    for (int64_t s = 0; s + 1 < S; ++s) {
        if (sdf0[s] > 0.0f && sdf0[s + 1] <= 0.0f && mask[s] && mask[s + 1]) {
            surface = 1;
            t_cross = t[s];
            break;
        }
    }
    const float limit = t_cross + tr / (dn > 1e-12f ? dn : 1e-12f);
    float sum = 0.0f;
    for (int64_t s = 0; s < S; ++s) {
        s_pos[s] = sigmoidf(sdf0[s] / b);
        s_neg[s] = sigmoidf(-sdf0[s] / b);
        kept[s] = mask[s] && (!surface || t[s] <= limit);
        a[s] = kept[s] ? s_pos[s] * s_neg[s] : 0.0f;
        sum += a[s];
    }
    *w_sum = sum;
    *w_norm = sum > 1e-20f ? sum : 1e-20f;
    float d = 0.0f, c[3] = {0.0f, 0.0f, 0.0f};
    for (int64_t s = 0; s < S; ++s) {
        a[s] /= *w_norm;
        d += a[s] * t[s];
        if (rgb && mask[s])
            for (int k = 0; k < 3; ++k) c[k] += a[s] * rgb[3 * s + k];
    }
    *depth = d;
    if (color)
        for (int k = 0; k < 3; ++k) color[k] = c[k];
    return hit;
}

static int depth_valid(int hit, float gt) { return hit && gt > 0.0f && isfinite(gt); }

/* terms[0..4] = total, colour, depth, free space, SDF; counts[0..3] = the rays of the colour, depth, free-space
 * and SDF terms (what the backward pass divides by). Returns 0, or -1 when S > MAX_SAMPLES. */
int vf_band_losses_forward(const float *sdf, const float *rgb, const float *t, const uint8_t *mask, const float *dn,
                           const float *depth_gt, const float *color_gt, const uint8_t *color_valid, int64_t N,
                           int64_t S, float tr, float b, const double *weights, double *terms, double *counts) {
    if (S > MAX_SAMPLES) return -1;
    Sums sums = {0};
    float sdf0[MAX_SAMPLES], s_pos[MAX_SAMPLES], s_neg[MAX_SAMPLES], a[MAX_SAMPLES];
    uint8_t kept[MAX_SAMPLES];
    for (int64_t r = 0; r < N; ++r) {
        const float *rgb_r = rgb ? rgb + r * S * 3 : 0;
        float w_sum, w_norm, depth, color[3];
        const int hit = composite_ray(sdf + r * S, rgb_r, t + r * S, mask + r * S, dn[r], S, tr, b, sdf0, s_pos,
                                      s_neg, kept, a, &w_sum, &w_norm, &depth, rgb ? color : 0);
        if (rgb && hit && (!color_valid || color_valid[r])) {
            float err = 0.0f;
            for (int k = 0; k < 3; ++k) err += fabsf(color[k] - color_gt[3 * r + k]);
            sums.color_sum += err / 3.0f;
            sums.n_color += 1.0;
        }
        const int valid = depth_valid(hit, depth_gt[r]);
        if (valid) {
            sums.depth_sum += fabsf(depth - depth_gt[r]);
            sums.n_depth += 1.0;
        }
        const float d_gt = valid ? depth_gt[r] : 0.0f;
        float free_sum = 0.0f, band_sum = 0.0f;
        int n_free = 0, n_band = 0;
        for (int64_t s = 0; s < S; ++s) {
            if (!(mask[r * S + s] && valid)) continue;
            const float dist = (d_gt - t[r * S + s]) * dn[r];
            if (dist > tr) {
                const float e = (sdf0[s] - tr) / tr;
                free_sum += e * e;
                ++n_free;
            }
            if (fabsf(dist) <= tr) {
                const float e = (sdf0[s] - dist) / tr;
                band_sum += e * e;
                ++n_band;
            }
        }
        if (n_free) { sums.free_sum += free_sum / (float)n_free; sums.n_free += 1.0; }
        if (n_band) { sums.band_sum += band_sum / (float)n_band; sums.n_band += 1.0; }
    }
    terms[1] = sums.n_color > 0 ? sums.color_sum / sums.n_color : 0.0;
    terms[2] = sums.n_depth > 0 ? sums.depth_sum / sums.n_depth : 0.0;
    terms[3] = sums.n_free > 0 ? sums.free_sum / sums.n_free : 0.0;
    terms[4] = sums.n_band > 0 ? sums.band_sum / sums.n_band : 0.0;
    terms[0] = weights[0] * terms[1] + weights[1] * terms[2] + weights[2] * terms[3] + weights[3] * terms[4];
    counts[0] = sums.n_color; counts[1] = sums.n_depth; counts[2] = sums.n_free; counts[3] = sums.n_band;
    return 0;
}

/* Gradients grad_sdf [N, S] and grad_rgb [N, S, 3] (when not NULL) of sum_x coef[x] term_x, coef = the gradient
 * reaching the colour, depth, free-space and SDF terms; counts as the forward pass returned them. */
int vf_band_losses_backward(const float *sdf, const float *rgb, const float *t, const uint8_t *mask, const float *dn,
                            const float *depth_gt, const float *color_gt, const uint8_t *color_valid, int64_t N,
                            int64_t S, float tr, float b, const double *coef, const double *counts, float *grad_sdf,
                            float *grad_rgb) {
    if (S > MAX_SAMPLES) return -1;
    const float k_color = (float)(coef[0] / (3.0 * (counts[0] > 1 ? counts[0] : 1.0)));
    const float k_depth = (float)(coef[1] / (counts[1] > 1 ? counts[1] : 1.0));
    const float k_free = (float)(2.0 * coef[2] / ((counts[2] > 1 ? counts[2] : 1.0) * tr));
    const float k_band = (float)(2.0 * coef[3] / ((counts[3] > 1 ? counts[3] : 1.0) * tr));
    float sdf0[MAX_SAMPLES], s_pos[MAX_SAMPLES], s_neg[MAX_SAMPLES], a[MAX_SAMPLES], g_a[MAX_SAMPLES];
    uint8_t kept[MAX_SAMPLES];
    for (int64_t r = 0; r < N; ++r) {
        const float *rgb_r = rgb ? rgb + r * S * 3 : 0;
        const uint8_t *m = mask + r * S;
        const float *t_r = t + r * S;
        float w_sum, w_norm, depth, color[3];
        const int hit = composite_ray(sdf + r * S, rgb_r, t_r, m, dn[r], S, tr, b, sdf0, s_pos, s_neg, kept, a,
                                      &w_sum, &w_norm, &depth, rgb ? color : 0);
        const int valid = depth_valid(hit, depth_gt[r]);
        const float g_depth = valid ? k_depth * signf(depth - depth_gt[r]) : 0.0f;
        float g_color[3] = {0.0f, 0.0f, 0.0f};
        if (rgb && hit && (!color_valid || color_valid[r]))
            for (int k = 0; k < 3; ++k) g_color[k] = k_color * signf(color[k] - color_gt[3 * r + k]);
        float g_sum = 0.0f;
        for (int64_t s = 0; s < S; ++s) {
            float g = g_depth * t_r[s];
            if (rgb && m[s])
                for (int k = 0; k < 3; ++k) g += g_color[k] * rgb_r[3 * s + k];
            g_a[s] = g;
            g_sum += g * a[s];
        }
        if (!(w_sum >= 1e-20f)) g_sum = 0.0f; /* clamp's gradient: none where the sum was clamped */
        const float d_gt = valid ? depth_gt[r] : 0.0f;
        int n_free = 0, n_band = 0;
        for (int64_t s = 0; s < S; ++s) {
            if (!(m[s] && valid)) continue;
            const float dist = (d_gt - t_r[s]) * dn[r];
            n_free += dist > tr;
            n_band += fabsf(dist) <= tr;
        }
        for (int64_t s = 0; s < S; ++s) {
            float g = 0.0f;
            if (kept[s]) {
                const float g_w = (g_a[s] - g_sum) / w_norm;
                g = g_w * (s_pos[s] * s_neg[s]) * (s_neg[s] - s_pos[s]) / b;
            }
            if (m[s] && valid) {
                const float dist = (d_gt - t_r[s]) * dn[r];
                if (dist > tr) g += (sdf0[s] - tr) / tr * (k_free / (float)n_free);
                if (fabsf(dist) <= tr) g += (sdf0[s] - dist) / tr * (k_band / (float)n_band);
            }
            grad_sdf[r * S + s] = g;
            if (grad_rgb)
                for (int k = 0; k < 3; ++k) grad_rgb[(r * S + s) * 3 + k] = m[s] ? g_color[k] * a[s] : 0.0f;
        }
    }
    return 0;
}
