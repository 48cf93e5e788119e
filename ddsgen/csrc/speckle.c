/* The speckle field's Gamma quantiles in C (ddsgen.sensor.speckle.speckle_field): linear interpolation of each
 * normal score in the table of Gamma quantiles on its uniform grid of scores, one pass instead of nine numpy passes.
 * The same float32 operations in the same order (compiled without FMA contraction): the same factors bit for bit
 * (tests/test_speckle.py). */
#include <stdint.h>

/* normal (n) scores; table (size) quantiles at scores -z_max + k / scale; out (n) quantiles. */
void ddsgen_gamma_quantiles(const float *normal, int64_t n, float z_max, float scale, const float *table,
                            int64_t size, float *out)
{
    for (int64_t i = 0; i < n; i++) {
        float position = normal[i];
        position = position > -z_max ? position : -z_max; /* np.clip: max with the low end, then min with the high */
        position = position < z_max ? position : z_max;
        position = position + z_max;
        position = position * scale;
        int32_t index = (int32_t)position;
        if (index > size - 2) index = (int32_t)(size - 2);
        const float frac = position - (float)index;
        const float low = table[index];
        out[i] = low + (table[index + 1] - low) * frac;
    }
}
