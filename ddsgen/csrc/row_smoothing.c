/* The device's smoothing along the rows in C: ddsgen.sensor.row_smoothing.smooth_along_rows's forward without
 * gradients, one pass instead of a dozen whole-image torch passes. The same float32 operations in the same order
 * (compiled without FMA contraction): the same disparities bit for bit (tests/test_row_smoothing.py). */
#include <math.h>
#include <stdint.h>

/* disparity (height, width) px; valid (height, width) 0/1. centre_weight = float32(1 - 2 w), side_weight =
 * float32(w); same_surface_px: neighbours further apart are another surface; quantum_px 0: no rounding. */
void ddsgen_smooth_along_rows(const float *disparity, const uint8_t *valid, int64_t height, int64_t width,
                              float centre_weight, float side_weight, float same_surface_px, float quantum_px,
                              float *out) {
    for (int64_t r = 0; r < height; ++r) {
        const float *d = disparity + r * width;
        const uint8_t *v = valid + r * width;
        float *o = out + r * width;
        for (int64_t c = 0; c < width; ++c) {
            float value = d[c];
            if (v[c]) {
                float left = value, right = value;
                if (c > 0 && v[c - 1] && fabsf(value - d[c - 1]) <= same_surface_px) left = d[c - 1];
                if (c + 1 < width && v[c + 1] && fabsf(d[c + 1] - value) <= same_surface_px) right = d[c + 1];
                value = centre_weight * value + side_weight * (left + right);
            }
            if (quantum_px != 0.0f) value = (rintf(value / quantum_px) + 0.0f) * quantum_px;
            o[c] = value;
        }
    }
}
