/* Trilinear interpolation of a voxel map's corner embeddings, forward and backward, one pass over the points.
 *
 * The CPU fast path of voxfusion.core.map.field's interpolation (built and loaded by core/native/__init__.py); the
 * PyTorch operators in field.py (local_coords, trilinear_weights, _WeightedCornerSum) are the reference it is
 * tested against, and what every other device runs. Plain C99, no PyTorch headers: it compiles in about a second.
 *
 * Shapes (all arrays contiguous, row-major):
 *   emb          [V, D] float32   corner embeddings
 *   vertex_ids   [M, 8] int64     each voxel's corner rows in emb, corner c = 4 dx + 2 dy + dz
 *   voxel_coords [M, 3] int64     each voxel's integer coordinates (its low corner is coords * voxel_size)
 *   points       [K, 3] float32   world points, metres
 *   voxel_idx    [K]    int64     each point's voxel, 0 <= voxel_idx < M (checked by the forward pass)
 *
 * The arithmetic follows field.py operator for operator (local coordinate clamped to [0, 1], weights
 * w[4 dx + 2 dy + dz] = (x_dx y_dy) z_dz, the clamp's gradient zero outside [0, 1]); the embedding sums are
 * accumulated corner by corner, so they round like PyTorch's to within float32 rounding, not to the bit.
 * Compiled with -ffp-contract=off: no fused multiply-adds that PyTorch's kernels would not make either.
 */
#include <stdint.h>

static void corner_weights(const float l[3], float w[8]) {
    const float x1 = l[0], y1 = l[1], z1 = l[2];
    const float x0 = 1.0f - x1, y0 = 1.0f - y1, z0 = 1.0f - z1;
    const float w00 = x0 * y0, w01 = x0 * y1, w10 = x1 * y0, w11 = x1 * y1;
    w[0] = w00 * z0; w[1] = w00 * z1; w[2] = w01 * z0; w[3] = w01 * z1;
    w[4] = w10 * z0; w[5] = w10 * z1; w[6] = w11 * z0; w[7] = w11 * z1;
}

/* Features out [K, D] and, for the backward pass, each point's clamped local coordinate loc [K, 3] and which
 * of its axes were inside [0, 1] before clamping (bit a of inside [K]). Returns 0, or -1 (and writes nothing)
 * when a voxel index is outside [0, n_voxels). */
int vf_interpolate_forward(const float *emb, int64_t dim, const int64_t *vertex_ids, const int64_t *voxel_coords,
                           int64_t n_voxels, const float *points, const int64_t *voxel_idx, int64_t n_points,
                           float voxel_size, float *out, float *loc, uint8_t *inside) {
    for (int64_t k = 0; k < n_points; ++k)
        if (voxel_idx[k] < 0 || voxel_idx[k] >= n_voxels) return -1;
    for (int64_t k = 0; k < n_points; ++k) {
        const int64_t m = voxel_idx[k];
        float l[3], w[8];
        uint8_t flags = 0;
        for (int a = 0; a < 3; ++a) {
            const float origin = (float)voxel_coords[3 * m + a] * voxel_size;
            const float r = (points[3 * k + a] - origin) / voxel_size;
            if (r >= 0.0f && r <= 1.0f) flags |= (uint8_t)(1u << a);
            l[a] = r < 0.0f ? 0.0f : (r > 1.0f ? 1.0f : r); /* NaN stays NaN, as torch.clamp */
            loc[3 * k + a] = l[a];
        }
        inside[k] = flags;
        corner_weights(l, w);
        float *o = out + k * dim;
        for (int64_t d = 0; d < dim; ++d) o[d] = 0.0f;
        for (int c = 0; c < 8; ++c) {
            const float *row = emb + vertex_ids[8 * m + c] * dim;
            const float wc = w[c];
            for (int64_t d = 0; d < dim; ++d) o[d] += wc * row[d];
        }
    }
    return 0;
}

/* Given grad_out [K, D] (the gradient with respect to the features): adds the embeddings' gradient into
 * grad_emb [V, D] (when not NULL; points in order, so the sums are deterministic) and writes the points'
 * gradient grad_points [K, 3] (when not NULL). The indices are the forward pass's, already checked. */
void vf_interpolate_backward(const float *emb, int64_t dim, const int64_t *vertex_ids, const int64_t *voxel_idx,
                             int64_t n_points, float voxel_size, const float *loc, const uint8_t *inside,
                             const float *grad_out, float *grad_emb, float *grad_points) {
    for (int64_t k = 0; k < n_points; ++k) {
        const int64_t m = voxel_idx[k];
        const float *l = loc + 3 * k;
        const float *g = grad_out + k * dim;
        float w[8];
        corner_weights(l, w);
        if (grad_emb) {
            for (int c = 0; c < 8; ++c) {
                float *row = grad_emb + vertex_ids[8 * m + c] * dim;
                const float wc = w[c];
                for (int64_t d = 0; d < dim; ++d) row[d] += wc * g[d];
            }
        }
        if (grad_points) {
            float gw[8]; /* d loss / d weight: each corner's embedding dotted with grad_out */
            for (int c = 0; c < 8; ++c) {
                const float *row = emb + vertex_ids[8 * m + c] * dim;
                float s = 0.0f;
                for (int64_t d = 0; d < dim; ++d) s += row[d] * g[d];
                gw[c] = s;
            }
            const float x1 = l[0], y1 = l[1], z1 = l[2];
            const float x0 = 1.0f - x1, y0 = 1.0f - y1, z0 = 1.0f - z1;
            float gz_sum[4], gz_diff[4];
            for (int p = 0; p < 4; ++p) {
                gz_sum[p] = gw[2 * p] * z0 + gw[2 * p + 1] * z1;
                gz_diff[p] = gw[2 * p + 1] - gw[2 * p];
            }
            const float dl[3] = {
                (gz_sum[2] - gz_sum[0]) * y0 + (gz_sum[3] - gz_sum[1]) * y1,
                (gz_sum[1] - gz_sum[0]) * x0 + (gz_sum[3] - gz_sum[2]) * x1,
                (gz_diff[0] * y0 + gz_diff[1] * y1) * x0 + (gz_diff[2] * y0 + gz_diff[3] * y1) * x1,
            };
            for (int a = 0; a < 3; ++a)
                grad_points[3 * k + a] = (inside[k] >> a) & 1u ? dl[a] / voxel_size : 0.0f;
        }
    }
}
