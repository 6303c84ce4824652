/* The depth filter's neighbourhood support: for each pixel, how many neighbours in its window agree with its depth.
 *
 * The CPU fast path of voxfusion.core.depth_filter.depth_support (built and loaded by core/native/__init__.py); the
 * PyTorch operators there are the reference it is tested against (the same counts) and what every other device
 * runs. Plain C99.
 *
 * Input: ld [H, W] float32, the log depth (NaN where invalid: it agrees with nothing), as the reference computes
 * it; r = window_px / 2; tol = log1p(rel_tol) as float32. Output: count [H, W] uint8 (zeroed here), the neighbours
 * (y + dy, x + dx), |dy|, |dx| <= r, inside the image with |ld - ld'| <= tol: the reference's float32 operators.
 */
#include <math.h>
#include <stdint.h>

void vf_depth_support(const float *ld, int64_t h, int64_t w, int64_t r, float tol, uint8_t *count) {
    for (int64_t i = 0; i < h * w; ++i) count[i] = 0;
    /* each unordered pair of offsets once, as the reference: pixel a at (y, x), its neighbour b at (y + dy, x + dx),
     * a row segment at a time so that the inner loop vectorises (a NaN agrees with nothing) */
    for (int64_t dy = 0; dy <= r; ++dy) {
        for (int64_t dx = -r; dx <= r; ++dx) {
            if (dy == 0 && dx <= 0) continue;
            if (dy >= h || (dx < 0 ? -dx : dx) >= w) continue;
            const int64_t x0 = dx < 0 ? -dx : 0, x1 = dx > 0 ? w - dx : w;
            for (int64_t y = 0; y + dy < h; ++y) {
                const float *la = ld + y * w, *lb = ld + (y + dy) * w + dx;
                uint8_t *ca = count + y * w, *cb = count + (y + dy) * w + dx;
                for (int64_t x = x0; x < x1; ++x) {
                    const uint8_t agree = fabsf(la[x] - lb[x]) <= tol;
                    ca[x] += agree;
                    cb[x] += agree;
                }
            }
        }
    }
}
