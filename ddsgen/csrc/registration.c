/* registration.c: the registration maps of ddsgen/sensor/registration.py, one pass over the pixels each.
 *
 * The numpy functions there are the definition and the path without a compiler; these give the same maps bit
 * for bit (tests/test_registration.py): every value is computed with the same IEEE operations in the same order
 * (float32 where numpy works in float32; built with -ffp-contract=off, so no fused multiply-adds).
 * Called through ctypes from ddsgen/sensor/registration_kernel.py.
 */

#include <math.h>
#include <stddef.h>
#include <stdint.h>

/* registration_index: for each output pixel, the flat IR index of the pixel whose depth it shows, -1 where the
 * IR camera does not see its surface point. points, normals (H*W, 3), hit (H*W), ir_depth, ir_hit (H*W) as in
 * the numpy function; out (H*W) int64. Per pixel, in float32 as numpy:
 *   x = px + b_r, z = hit ? pz : 1, column = rint(fx x / z + c)                     (c = cx - shift)
 *   tolerance = fmin(z z |nx| / (2fx |n . (x, py, z)|), cap z) + rel z + abs
 *   seen = hit, 0 <= column < W, ir_hit[row, column], |ir_depth[row, column] - z| <= tolerance. */
void ddsgen_registration_index(const float *points, const float *normals, const uint8_t *hit, const float *ir_depth,
                               const uint8_t *ir_hit, int64_t height, int64_t width, float b_r, float fx, float c,
                               float cap, float rel, float abs_m, int64_t *out)
{
    const float two_fx = 2.0f * fx; /* exact, and equal to numpy's float32(2 fx) */
    for (int64_t row = 0; row < height; row++) {
        for (int64_t col = 0; col < width; col++) {
            const int64_t p = row * width + col;
            out[p] = -1;
            if (!hit[p]) continue;
            const float *P = points + 3 * p, *n = normals + 3 * p;
            const float x = P[0] + b_r, y = P[1], z = P[2];
            const float u = rintf(fx * x / z + c);
            if (!(u >= 0.0f && u < (float)width)) continue; /* numpy: outside, or nan */
            const int64_t q = row * width + (int64_t)u;
            if (!ir_hit[q]) continue;
            const float facing = fabsf(n[0] * x + n[1] * y + n[2] * z);
            const float half_pixel = z * z * fabsf(n[0]) / (two_fx * facing);
            const float tolerance = fminf(half_pixel, cap * z) + rel * z + abs_m;
            if (fabsf(ir_depth[q] - z) <= tolerance) out[p] = q;
        }
    }
}

/* In place on `lines` lines of `length` entries, entry j of line i at flat[i * stride_line + j * stride_entry]
 * (IR flat indices, -1 = empty): a run of at most max_run empty entries between two written ones of its line
 * takes the nearer one's source (depth: flat IR depth; ties take the first); with `one_row`, only where the two
 * sources are neighbours in one IR row of `width` pixels. With `seen` (the ray-cast index, same layout as flat),
 * only entries whose `seen` is -1 or a `valid` IR pixel are written. Runs are bounded by written entries, so
 * filling one never changes another. */
static void fill_short_runs(int64_t *flat, int64_t lines, int64_t length, int64_t stride_line, int64_t stride_entry,
                            const float *depth, int64_t max_run, int one_row, int64_t width, const int64_t *seen,
                            const uint8_t *valid)
{
    for (int64_t i = 0; i < lines; i++) {
        int64_t *line = flat + i * stride_line;
        int64_t j = 0;
        while (j < length) {
            if (line[j * stride_entry] >= 0) {
                j++;
                continue;
            }
            int64_t end = j; /* the run j .. end - 1 */
            while (end < length && line[end * stride_entry] < 0) end++;
            if (j > 0 && end < length && end - j <= max_run) {
                const int64_t a = line[(j - 1) * stride_entry], b = line[end * stride_entry];
                const int64_t step = b > a ? b - a : a - b;
                if (!one_row || (step == 1 && a / width == b / width)) {
                    const int64_t chosen = depth[a] <= depth[b] ? a : b;
                    for (int64_t k = j; k < end; k++) {
                        const int64_t e = i * stride_line + k * stride_entry;
                        if (!seen || seen[e] < 0 || valid[seen[e]]) flat[e] = chosen;
                    }
                }
            }
            j = end;
        }
    }
}

/* forward_registration_index: each valid IR pixel (depth > 0) goes to column rint((u + shift) - f b_r / Z) of
 * its row ((u + shift) in double, f b_r / Z in float32, as numpy mixes a Python float, int64 columns and float32
 * depths); of several on one output pixel the nearest wins, of equal depths the first in row-major order. Then
 * the row fill (gap_px, sources neighbours in one IR row) and, with `seen` (H*W, the ray-cast index; NULL for
 * none), the column fill (fill_rows) where `seen` is -1 or a valid IR pixel. out (H*W) int64. */
void ddsgen_forward_registration_index(const uint8_t *valid, const float *depth, int64_t height, int64_t width,
                                       double shift_px, float focal_offset, int64_t gap_px, int64_t fill_rows,
                                       const int64_t *seen, int64_t *out)
{
    const int64_t n = height * width;
    for (int64_t p = 0; p < n; p++) out[p] = -1;
    for (int64_t p = 0; p < n; p++) { /* row-major: a later source replaces only a strictly nearer depth */
        const float z = depth[p];
        if (!valid[p] || !(z > 0.0f)) continue;
        const int64_t row = p / width, col = p % width;
        const double target = rint(((double)col + shift_px) - (double)(focal_offset / z));
        if (!(target >= 0.0 && target < (double)width)) continue;
        const int64_t key = row * width + (int64_t)target;
        if (out[key] < 0 || z < depth[out[key]]) out[key] = p;
    }
    if (gap_px > 0) fill_short_runs(out, height, width, width, 1, depth, gap_px, 1, width, NULL, NULL);
    if (fill_rows > 0 && seen) fill_short_runs(out, width, height, 1, width, depth, fill_rows, 0, width, seen, valid);
}

/* dense_splat_index: a registration index after the device's dense splat, composed (registration.py
 * splat_fill_index, then index read through it). A pixel p is valid where index[p] >= 0 and valid[index[p]];
 * a pixel that is not takes the index of its lower-right, else lower, else right neighbour, the first of them
 * that is valid (the later writers of the 2x2 splat win); -1 where none is. index, out (H*W) int64 (distinct
 * arrays); valid (H*W) uint8, the IR image's validity. */
void ddsgen_dense_splat_index(const int64_t *index, const uint8_t *valid, int64_t height, int64_t width,
                              int64_t *out)
{
    static const int64_t dy[3] = {1, 1, 0}, dx[3] = {1, 0, 1}; /* highest priority first */
    for (int64_t row = 0; row < height; row++) {
        for (int64_t col = 0; col < width; col++) {
            const int64_t p = row * width + col;
            if (index[p] >= 0 && valid[index[p]]) {
                out[p] = index[p];
                continue;
            }
            out[p] = -1;
            for (int k = 0; k < 3; k++) {
                const int64_t r = row + dy[k], c = col + dx[k];
                if (r >= height || c >= width) continue;
                const int64_t q = index[r * width + c];
                if (q >= 0 && valid[q]) {
                    out[p] = q;
                    break;
                }
            }
        }
    }
}

/* Several images registered through one index (ddsgen.sensor.registration.register_images without gradients):
 * out[k][p] = images[k][index[p]], zero bytes where index[p] is -1. images[k], out[k] hold n elements of
 * sizes[k] bytes (1, 4 or 8); index (n) int64. One pass over the index instead of two torch passes per image. */
void ddsgen_register_images(const int64_t *index, int64_t n, int64_t count, const void *const *images,
                            const int64_t *sizes, void *const *out)
{
    for (int64_t k = 0; k < count; k++) {
        const int64_t size = sizes[k];
        if (size == 4) {
            const uint32_t *src = (const uint32_t *)images[k];
            uint32_t *dst = (uint32_t *)out[k];
            for (int64_t p = 0; p < n; p++) dst[p] = index[p] >= 0 ? src[index[p]] : 0u;
        } else if (size == 1) {
            const uint8_t *src = (const uint8_t *)images[k];
            uint8_t *dst = (uint8_t *)out[k];
            for (int64_t p = 0; p < n; p++) dst[p] = index[p] >= 0 ? src[index[p]] : 0u;
        } else {
            const uint64_t *src = (const uint64_t *)images[k];
            uint64_t *dst = (uint64_t *)out[k];
            for (int64_t p = 0; p < n; p++) dst[p] = index[p] >= 0 ? src[index[p]] : 0u;
        }
    }
}
