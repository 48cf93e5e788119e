/* The matcher's validity in C: from the integer search's peaks to the confidence, the valid map and the kept
 * integer disparity (ddsgen.sensor.matcher.match's step between the two kernels and matcher._validity), in two
 * passes instead of some twenty whole-image torch passes. Only additions, subtractions, comparisons and
 * maxima of float32 values, as in the torch definition: the same maps bit for bit (tests/test_matcher.py). */
#include <stdint.h>

static inline float clamp01(float x) {
    x = x > 0.0f ? x : 0.0f; /* torch's clamp on the CPU: +0 for -0 */
    return x < 1.0f ? x : 1.0f;
}

/* best, second (H, W): the search's peak ZNCCs (unclipped); arg (H, W) int64, arg2 (H, W) int32: their candidate
 * indices, -1 for none (disparity k_hi - index). min_confidence, confirmed_zncc: as matcher.match takes them
 * (confirmed_zncc >= 1: no confirmed matches). seeds: scratch of (H + 2h) x (W + 2h) int32.
 * Out: best_out, second_out clipped to [0, 1]; confidence; valid (0/1); k_int int64 (k_lo where nothing was
 * found, the second peak's where only that one was confirmed); k_second int32 (-1 for none). */
void ddsgen_match_validity(const float *best, const float *second, const int64_t *arg, const int32_t *arg2,
                           int64_t height, int64_t width, int64_t k_hi, int64_t k_lo, int block,
                           float min_confidence, float confirmed_zncc, int32_t *seeds, float *best_out,
                           float *second_out, float *confidence, uint8_t *valid, int64_t *k_int, int32_t *k_second) {
    const int64_t h = block / 2, padded_width = width + 2 * h, n = height * width;
    const int confirming = confirmed_zncc < 1.0f;
    const int32_t sentinel = -(1 << 20); /* far from every disparity */
    if (confirming)
        for (int64_t i = 0; i < (height + 2 * h) * padded_width; i++) seeds[i] = sentinel;
    /* Pass 1: the uniqueness test, and the unique matches' disparities as seeds. */
    for (int64_t v = 0; v < height; v++) {
        for (int64_t u = 0; u < width; u++) {
            const int64_t i = v * width + u;
            const int found = arg[i] >= 0;
            k_int[i] = found ? k_hi - arg[i] : k_lo;
            k_second[i] = arg2[i] >= 0 ? (int32_t)(k_hi - arg2[i]) : -1;
            best_out[i] = clamp01(best[i]);
            second_out[i] = clamp01(second[i]);
            const int matchable = found && u >= h && u < width - h;
            confidence[i] = matchable ? clamp01(best_out[i] - second_out[i]) : 0.0f;
            const int unique = matchable && confidence[i] >= min_confidence && confidence[i] > 0.0f;
            if (confirming && unique) seeds[(v + h) * padded_width + u + h] = (int32_t)k_int[i];
            /* valid[i] holds "a candidate for confirmation" until pass 2 */
            valid[i] = confirming && matchable && !unique && best_out[i] > confirmed_zncc;
        }
    }
    /* Pass 2: a candidate whose best (else second) peak a unique neighbour in its window agrees with (+-1 px). */
    for (int64_t v = 0; v < height; v++) {
        for (int64_t u = 0; u < width; u++) {
            const int64_t i = v * width + u;
            if (valid[i]) {
                const int32_t own_best = (int32_t)k_int[i], own_second = k_second[i];
                int by_best = 0, by_second = 0;
                for (int64_t dy = 0; dy < block && !by_best; dy++) {
                    const int32_t *row = seeds + (v + dy) * padded_width + u;
                    for (int64_t dx = 0; dx < block; dx++) {
                        const int32_t to_best = row[dx] - own_best, to_second = row[dx] - own_second;
                        if (to_best >= -1 && to_best <= 1) {
                            by_best = 1;
                            break;
                        }
                        if (to_second >= -1 && to_second <= 1) by_second = 1;
                    }
                }
                by_second = by_second && !by_best && own_second >= 0 && second_out[i] > confirmed_zncc;
                if (by_second) k_int[i] = own_second;
                if (by_best || by_second) {
                    const float peak = by_second ? second_out[i] : best_out[i];
                    const float margin = clamp01(min_confidence + peak - confirmed_zncc);
                    confidence[i] = confidence[i] > margin ? confidence[i] : margin;
                }
            }
            valid[i] = confidence[i] >= min_confidence && confidence[i] > 0.0f;
        }
    }
}
