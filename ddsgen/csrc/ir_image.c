/* The IR camera image in C: ddsgen.sensor.ir.render_ir's forward without gradients, one pass per pixel
 * instead of some thirty whole-image torch passes (about 10 ms of a 640 x 480 frame).
 *
 * Every operation is the torch definition's float32 operation, in its order (compiled without FMA
 * contraction), with correctly rounded square roots: with those on both sides the two give the same image bit
 * for bit (tests/test_ir_kernel.py); torch's own float32 sqrt is 1 ulp off for ~0.6 % of values. The bilinear
 * sampling stays torch's grid_sample between the two passes: its CPU kernel contracts multiply-adds in a
 * way that depends on the CPU capability torch dispatches to.
 */
#include <math.h>
#include <stdint.h>

static inline float at_least(float x, float floor_value) { return x > floor_value ? x : floor_value; }

static inline float clamp01(float x) {
    x = at_least(x, 0.0f);
    return x < 1.0f ? x : 1.0f;
}

/* base ** n for 1 <= n <= 8 by repeated squaring, in the order of ddsgen.sensor.ir._power. */
static inline float power_by_squaring(float base, int n) {
    float out = 0.0f, square = base;
    int have = 0;
    while (n) {
        if (n & 1) {
            out = have ? out * square : square;
            have = 1;
        }
        n >>= 1;
        if (n) square = square * square;
    }
    return out;
}

/* Pass 1: grid_sample's coordinates (n, 2) of the pattern texel each camera point sees.
 * points (n, 3) camera frame (m); projector at (+baseline, 0, 0) with the camera's intrinsics
 * (projector_coordinates); then PatternField.sample's (u_p - origin_u) * sx * 2 / ws - 1 (and v). */
void ddsgen_ir_grid(const float *points, int64_t n, float fx, float fy, float cx, float cy, float baseline,
                    float origin_u, float origin_v, float sx, float sy, float ws, float hs, float *grid) {
    for (int64_t i = 0; i < n; ++i) {
        const float x = points[3 * i], y = points[3 * i + 1], z = at_least(points[3 * i + 2], 1e-6f);
        const float u = fx * (x - baseline) / z + cx;
        const float v = fy * y / z + cy;
        grid[2 * i] = (u - origin_u) * sx * 2.0f / ws - 1.0f;
        grid[2 * i + 1] = (v - origin_v) * sy * 2.0f / hs - 1.0f;
    }
}

/* Pass 2: the signal and the noisy, clipped (and rounded) IR counts of an (height, width) image.
 * points, normals (height, width, 3); albedo, lit, pattern (height, width) (pattern in grid_sample's
 * 8-bit units); speckle, read (height, noise_stride), their first width columns used.
 * falloff_n, vignetting_n: whole exponents 0..8 (0: off). electrons_per_count 0: read noise only. */
void ddsgen_ir_image(const float *points, const float *normals, const float *albedo, const float *lit,
                     const float *pattern, const float *speckle, const float *read, int64_t noise_stride,
                     int64_t height, int64_t width, float pattern_unit, float baseline, float emitted, float ambient,
                     float speckle_scale, float read_mean, float read_std, float read_std_squared,
                     float electrons_per_count, int falloff_n, int vignetting_n, float ir_max, int quantise,
                     float *ir, float *signal) {
    for (int64_t r = 0; r < height; ++r) {
        for (int64_t c = 0; c < width; ++c) {
            const int64_t i = r * width + c, j = r * noise_stride + c;
            const float x = points[3 * i], y = points[3 * i + 1], z_raw = points[3 * i + 2];
            const float nx = normals[3 * i], ny = normals[3 * i + 1], nz = normals[3 * i + 2];
            const float dots = pattern[i] * pattern_unit;
            const float to_projector_x = baseline - x;
            const float yy_zz = y * y + z_raw * z_raw;
            const float distance_sq = at_least(to_projector_x * to_projector_x + yy_zz, 1e-12f);
            const float distance = sqrtf(distance_sq);
            const float cos_incidence = at_least((nx * to_projector_x - ny * y - nz * z_raw) / distance, 0.0f);
            float s = albedo[i] * emitted * dots * cos_incidence / (distance_sq * 1e6f) * lit[i];
            const float z = at_least(z_raw, 1e-6f);
            if (falloff_n) s = s * power_by_squaring(clamp01(z / distance), falloff_n);
            if (vignetting_n) {
                const float camera_distance = at_least(sqrtf(x * x + yy_zz), 1e-6f);
                s = s * power_by_squaring(clamp01(z / camera_distance), vignetting_n);
            }
            signal[i] = s;
            const float light = s * (speckle[j] * speckle_scale) + ambient;
            float noise_std = read_std;
            if (electrons_per_count > 0.0f)
                noise_std = sqrtf(read_std_squared + at_least(light, 0.0f) / electrons_per_count);
            float counts = light + read_mean + noise_std * read[j];
            counts = at_least(counts, 0.0f);
            counts = counts < ir_max ? counts : ir_max;
            ir[i] = quantise ? rintf(counts) + 0.0f : counts;
        }
    }
}
