/* zncc.c: the CPU kernels of ddsgen's block matcher (ddsgen/sensor/matcher/).
 *
 * What they compute. The observed IR image O is compared with the projector's reference
 * pattern R along image rows (epipolar lines): for a disparity d, the block x block window of O
 * at (v, u) against the window of R at (v, u - d), scored by zero-mean normalised
 * cross-correlation,
 *     ZNCC = (sum O R - sum O sum R / n) / sqrt(var_O + floor) / sqrt(var_R + floor),  n = block^2,
 * where the variance floor keeps flat windows finite. Five entry points, called through ctypes
 * from kernel.py / autograd.py (plain C11 + GCC vector extensions + OpenMP over rows):
 *   ddsgen_observed_stats     the mirrored, padded O and its per-pixel window sum and 1 / std;
 *   ddsgen_zncc_search        stage 1: ZNCC at every integer disparity, streaming (no cost
 *                             volume); per pixel the best score, the second peak (confidence)
 *                             and the disparities of both;
 *   ddsgen_refine             stage 2: ZNCC of the sub-pixel candidates d_t = K + (t - T) / S
 *                             against the reference phases, then the soft-argmax
 *                             d = sum_t softmax(beta ZNCC)_t d_t; in backward mode also the
 *                             gradients w.r.t. the cross-correlations, O's statistics and beta;
 *   ddsgen_window_cross_grad  the backward of the window cross-correlations w.r.t. O;
 *   ddsgen_confirm_by_unique_neighbour  the confirmed-match rule of the validity (a unique
 *                             match within the window agrees with a peak), stopping at the
 *                             first agreeing neighbour.
 * The torch twin of the first four is torch_path.py + windows.py, of the last
 * matcher._confirmed_by_a_unique_neighbour; tests/test_matcher.py checks that both give the same
 * disparities, gradients and confirmations. Every pixel is computed in a fixed order, so
 * results depend neither on the thread count nor on the row-band split.
 *
 * Built on first use with the system compiler (cc -O3 -march=native -fopenmp), cached in
 * ddsgen's cache folder under a hash of this file, the compiler, the flags and the CPU.
 */

#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <math.h>

typedef float v8 __attribute__((vector_size(32)));
typedef float v8u __attribute__((vector_size(32), aligned(4)));
#define LOADU(p) (*(const v8u *)(p))
#define NEG_BIG (-1e30f)
#define ROW_BLOCK 32

typedef int32_t vi8 __attribute__((vector_size(32)));
typedef uint8_t vu8 __attribute__((vector_size(8)));

static inline v8 vsel8(vi8 mask, v8 a, v8 b) { /* mask ? a : b, lane-wise */
    return (v8)((mask & (vi8)a) | (~mask & (vi8)b));
}

static inline v8 vmax8(v8 a, v8 b) { return vsel8(a > b, a, b); }

/* Horizontal max and sum by halving (3 steps instead of an 8-long dependency chain). */
static inline float hmax8(v8 m) {
    m = vmax8(m, __builtin_shuffle(m, (vi8){4, 5, 6, 7, 0, 1, 2, 3}));
    m = vmax8(m, __builtin_shuffle(m, (vi8){2, 3, 0, 1, 6, 7, 4, 5}));
    m = vmax8(m, __builtin_shuffle(m, (vi8){1, 0, 3, 2, 5, 4, 7, 6}));
    return m[0];
}

static inline float clip01(float x) { return x < 0.0f ? 0.0f : (x > 1.0f ? 1.0f : x); }

/* The matcher's uniqueness test on clipped scores, as matcher/__init__.py computes it in float32. */
static inline int unique_match(float best, float second, float min_confidence) {
    const float conf = clip01(clip01(best) - clip01(second));
    return conf >= min_confidence && conf > 0.0f;
}

/* The integer search's vectors: SL candidates each. */
#define SL 16
typedef float vs __attribute__((vector_size(4 * SL)));
typedef float vsu __attribute__((vector_size(4 * SL), aligned(4)));
typedef int32_t vis __attribute__((vector_size(4 * SL)));
#define LOADS(p) (*(const vsu *)(p))
#define LANE_INDEX {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15}

static inline vs vselS(vis mask, vs a, vs b) { /* mask ? a : b, lane-wise */
    return (vs)((mask & (vis)a) | (~mask & (vis)b));
}

static inline vis vselI(vis mask, vis a, vis b) { return (mask & a) | (~mask & b); }

static inline vs vmaxS(vs a, vs b) { return vselS(a > b, a, b); }

static inline vs vminS(vs a, vs b) { return vselS(a < b, a, b); }

/* Horizontal max / min by halving (4 steps instead of a 16-long dependency chain). Exact for the finite scores
 * here; of equal lanes of opposite zero sign either may come out (the outputs compare them as equal). */
#define HALVES(x, op)                                                                                         \
    x = op(x, __builtin_shuffle(x, (vis){8, 9, 10, 11, 12, 13, 14, 15, 0, 1, 2, 3, 4, 5, 6, 7}));            \
    x = op(x, __builtin_shuffle(x, (vis){4, 5, 6, 7, 0, 1, 2, 3, 12, 13, 14, 15, 8, 9, 10, 11}));            \
    x = op(x, __builtin_shuffle(x, (vis){2, 3, 0, 1, 6, 7, 4, 5, 10, 11, 8, 9, 14, 15, 12, 13}));            \
    x = op(x, __builtin_shuffle(x, (vis){1, 0, 3, 2, 5, 4, 7, 6, 9, 8, 11, 10, 13, 12, 15, 14}))

static inline vis vminI(vis a, vis b) { return vselI(a < b, a, b); }

static inline float hmaxS(vs x) {
    HALVES(x, vmaxS);
    return x[0];
}

static inline int hminS(vis x) {
    HALVES(x, vminI);
    return x[0];
}

/* Stage 1, integer-disparity search (no gradient needed here).
 *
 * For every output pixel (v, u) and candidate c = 0..D-1 (integer disparity k = k_hi - c):
 *   cross(v, u, c) = sum_{i<b, j<b} O[v+i][u+j] * R[v+i][u+j + r0 + c]
 *   score          = (cross - OS[v][u] * RS[v][u+r0+c] / n) * invO[v][u] * invR[v][u+r0+c] + PEN[v][u+r0+c]
 * O is the row/column padded observed image, R the row padded reference (phase 0, unknown
 * values zeroed), PEN is 0 where the reference window is known and -1e30 where it is not.
 * Window sums are running sums (vertical ones restarted every ROW_BLOCK rows, so the result
 * is independent of the thread count). Outputs per pixel: best score, the best score at least 2 candidates away from the
 * best (the "second peak"), the best candidate index (-1 if every candidate is excluded) and
 * the second peak's candidate index where its score exceeds second_floor and the match fails the
 * uniqueness test (clipped best - second < min_confidence; -1 elsewhere: the confirmed-match rule
 * needs no other, and the search for it costs; ties in either go to the lowest index).
 * Candidates go 16 to a vector (SL lanes: one AVX-512 register, two AVX2 ones; each lane's arithmetic is the
 * same whatever the width, so the width changes the speed only). Arrays R, RS, invR, PEN must have SL - 1
 * readable columns beyond candidate D - 1 (kernel.py: SEARCH_LANES).
 */
void ddsgen_zncc_search(const float *restrict O, int Wo,
                        const float *restrict R, int Wr,
                        const float *restrict OS, const float *restrict invO,
                        const float *restrict RS, const float *restrict invR,
                        const float *restrict PEN, int Ws,
                        int H, int W, int b, int r0, int D,
                        float *restrict best_out, float *restrict second_out,
                        int32_t *restrict arg_out, int32_t *restrict arg2_out, float second_floor,
                        float min_confidence, int n_threads)
{
    const float inv_n = 1.0f / (float)(b * b);
    const int Wv = W + b - 1;
    const int nb = (D + SL - 1) / SL;
    const int Dp = nb * SL;
#pragma omp parallel num_threads(n_threads)
    {
        vs *V = (vs *)aligned_alloc(sizeof(vs), sizeof(vs) * (size_t)Wv * nb);
        vs *S = (vs *)aligned_alloc(sizeof(vs), sizeof(vs) * (size_t)nb);
        vs *SC = (vs *)aligned_alloc(sizeof(vs), sizeof(vs) * (size_t)nb);
        vs *TAIL = (vs *)aligned_alloc(sizeof(vs), sizeof(vs) * (size_t)nb);
        float *tail = (float *)TAIL;
        for (int c = 0; c < Dp; c++) tail[c] = c < D ? 0.0f : NEG_BIG;
        /* Rows are processed in fixed blocks of ROW_BLOCK: the vertical window sums are
           computed in full at a block's first row and then updated incrementally, so the
           result depends on neither the thread count nor the caller's band split. */
#pragma omp for schedule(dynamic, 1)
        for (int blk = 0; blk < (H + ROW_BLOCK - 1) / ROW_BLOCK; blk++)
        for (int v = blk * ROW_BLOCK; v < H && v < (blk + 1) * ROW_BLOCK; v++) {
            if (v == blk * ROW_BLOCK) {
                for (int x = 0; x < Wv; x++) {
                    vs *Vx = V + (size_t)x * nb;
                    for (int q = 0; q < nb; q++) Vx[q] = (vs){0};
                    for (int i = 0; i < b; i++) {
                        const float oi = O[(size_t)(v + i) * Wo + x];
                        const float *ri = R + (size_t)(v + i) * Wr + r0 + x;
                        for (int q = 0; q < nb; q++) Vx[q] += oi * LOADS(ri + SL * q);
                    }
                }
            } else {
                const float *onew = O + (size_t)(v + b - 1) * Wo, *oold = O + (size_t)(v - 1) * Wo;
                const float *rnew = R + (size_t)(v + b - 1) * Wr + r0, *rold = R + (size_t)(v - 1) * Wr + r0;
                for (int x = 0; x < Wv; x++) {
                    vs *Vx = V + (size_t)x * nb;
                    const float on = onew[x], oo = oold[x];
                    for (int q = 0; q < nb; q++)
                        Vx[q] += on * LOADS(rnew + x + SL * q) - oo * LOADS(rold + x + SL * q);
                }
            }
            /* horizontal running window sums */
            for (int q = 0; q < nb; q++) {
                vs acc = V[q];
                for (int j = 1; j < b; j++) acc += V[(size_t)j * nb + q];
                S[q] = acc;
            }
            for (int u = 0; u < W; u++) {
                const float os = OS[(size_t)v * W + u] * inv_n;
                const float io = invO[(size_t)v * W + u];
                const size_t base = (size_t)v * Ws + u + r0;
                vs m = NEG_BIG - (vs){0};
                vs m2 = NEG_BIG - (vs){0}; /* per lane, the second-best score (of candidates c = lane mod SL) */
                vis mi = {0};
                vis ci = LANE_INDEX;
                for (int q = 0; q < nb; q++) {
                    vs sc = (S[q] - os * LOADS(RS + base + SL * q)) * (io * LOADS(invR + base + SL * q))
                            + LOADS(PEN + base + SL * q) + TAIL[q];
                    SC[q] = sc;
                    m2 = vmaxS(m2, vminS(m, sc));
                    vis gt = sc > m;
                    m = vselS(gt, sc, m);
                    mi = (gt & ci) | (~gt & mi);
                    ci += SL;
                }
                /* the maximum, and the lowest index among the lanes holding it */
                const float best = hmaxS(m);
                int arg = hminS(vselI(m == best, mi, INT32_MAX - (vis){0}));
                if (!(best > 0.5f * NEG_BIG)) arg = -1;
                float second = -2.0f;
                int arg2 = -1;
                if (arg >= 0) {
                    /* The best score at least 2 candidates from the best peak. A lane holds at most one of the
                       peak's three candidates (SL > 3): where it is the lane's best, the lane's second best is
                       the lane's best without it; elsewhere the lane's best is. (No second pass over SC.) */
                    const vis beside_peak = (mi >= arg - 1) & (mi <= arg + 1);
                    const float s2 = hmaxS(vselS(beside_peak, m2, m));
                    if (s2 > second) second = s2;
                    /* Its index only where the confirmed-match rule may ask for it: a peak above
                       second_floor at a match failing the uniqueness test (clipped scores, as in Python);
                       the lowest index among ties. */
                    if (s2 > second_floor && !unique_match(best, s2, min_confidence)) {
                        vis lowest = INT32_MAX - (vis){0};
                        vis cq = LANE_INDEX;
                        for (int q = 0; q < nb; q++, cq += SL) {
                            const vis near_peak = (cq >= arg - 1) & (cq <= arg + 1);
                            lowest = vminI(lowest, vselI((SC[q] == s2) & ~near_peak, cq, INT32_MAX - (vis){0}));
                        }
                        arg2 = hminS(lowest);
                    }
                }
                best_out[(size_t)v * W + u] = arg >= 0 ? best : -2.0f;
                second_out[(size_t)v * W + u] = second;
                arg_out[(size_t)v * W + u] = arg;
                arg2_out[(size_t)v * W + u] = arg2;
                if (u + 1 < W) {
                    const vs *add = V + (size_t)(u + b) * nb;
                    const vs *sub = V + (size_t)u * nb;
                    for (int q = 0; q < nb; q++) S[q] += add[q] - sub[q];
                }
            }
        }
        free(V);
        free(S);
        free(SC);
        free(TAIL);
    }
}


/* Vector exp for x <= 0 (Cephes expf: range reduction by ln 2, degree-6 polynomial, exponent
 * bits; relative error ~1e-7). Inputs below -87 give 2^-126 (callers only use x >= -87 as
 * weights next to exp(0) = 1, where that is far below float resolution). */
static inline v8 vexp8(v8 x) {
    const v8 lo = {-87.0f, -87.0f, -87.0f, -87.0f, -87.0f, -87.0f, -87.0f, -87.0f};
    x = vmax8(x, lo);
    v8 t = x * 1.44269504088896341f + 0.5f;
    vi8 n = __builtin_convertvector(t, vi8);  /* truncation; floor for negative t below */
    v8 nf = __builtin_convertvector(n, v8);
    vi8 gt = nf > t;
    n += gt;  /* gt is -1 where nf > t */
    nf = __builtin_convertvector(n, v8);
    v8 r = x - nf * 0.693359375f - nf * -2.12194440e-4f;
    v8 y = 1.9875691500e-4f * r + 1.3981999507e-3f;
    y = y * r + 8.3334519073e-3f;
    y = y * r + 4.1665795894e-2f;
    y = y * r + 1.6666665459e-1f;
    y = y * r + 5.0000001201e-1f;
    y = y * (r * r) + r + 1.0f;
    vi8 scale = (n + 127) << 23;
    return y * (v8)scale;
}

/* Observed-image window statistics. X is the (H, W) normalised observed image; writes the
 * mirrored (no edge repeat) padded image Opad (H + b - 1, W + b - 1), and per output pixel the
 * window sums OSUM = sum Opad, OINV = 1 / sqrt(max(sum Opad^2 - OSUM^2 / n, 0) + floor) over
 * b x b windows (sums in double: running along each padded row, then direct over the b rows,
 * so every value is computed in a fixed order, whatever the thread count). RS, RS2 are
 * scratch of (H + b - 1) x W doubles. */
static inline int mirror(int i, int n) { return i < 0 ? -i : (i >= n ? 2 * n - 2 - i : i); }

void ddsgen_observed_stats(const float *restrict X, int H, int W, int b, float floor_, float *restrict Opad,
                           float *restrict OSUM, float *restrict OINV, double *restrict RS,
                           double *restrict RS2, int n_threads)
{
    const int h = b / 2, Hp = H + b - 1, Wp = W + b - 1;
    const float nf = (float)(b * b);
#pragma omp parallel num_threads(n_threads)
    {
#pragma omp for schedule(static)
        for (int y = 0; y < Hp; y++) {
            const float *restrict x = X + (size_t)mirror(y - h, H) * W;
            float *restrict o = Opad + (size_t)y * Wp;
            for (int c = 0; c < Wp; c++) o[c] = x[mirror(c - h, W)];
            double s = 0.0, s2 = 0.0;
            for (int j = 0; j < b; j++) {
                s += (double)o[j];
                s2 += (double)(o[j] * o[j]);
            }
            double *restrict rs = RS + (size_t)y * W, *restrict rs2 = RS2 + (size_t)y * W;
            rs[0] = s;
            rs2[0] = s2;
            for (int u = 1; u < W; u++) {
                const float a = o[u + b - 1], d = o[u - 1];
                s += (double)a - (double)d;
                s2 += (double)(a * a) - (double)(d * d);
                rs[u] = s;
                rs2[u] = s2;
            }
        }
#pragma omp for schedule(static)
        for (int v = 0; v < H; v++) {
            for (int u = 0; u < W; u++) {
                double s = 0.0, s2 = 0.0;
                for (int i = 0; i < b; i++) {
                    s += RS[(size_t)(v + i) * W + u];
                    s2 += RS2[(size_t)(v + i) * W + u];
                }
                const float os = (float)s, os2 = (float)s2;
                float var = os2 - os * os / nf;
                var = var > 0.0f ? var : 0.0f;
                OSUM[(size_t)v * W + u] = os;
                OINV[(size_t)v * W + u] = 1.0f / sqrtf(var + floor_);
            }
        }
    }
}

/* One window column's share of the sub-pixel candidates' cross-correlations:
 * out[q] = sum_{i<b} O[v+i][x] * FX[v+i][XB - c XCS + q XVS .. + 7], q < nq, where c = x + col_shift - k
 * is the reference column that observed column x meets at integer disparity k (FX: the candidates of
 * reference column c start at XB - c XCS, vector q of them XVS floats further; row stride WX). Even
 * and odd rows go to separate sums (independent dependency chains: an FMA's latency, not its
 * throughput, would otherwise bound the loop), added at the end. */
static inline __attribute__((always_inline)) void column_cross(
    const float *restrict O, int Wo, const float *restrict FX, size_t WX, ptrdiff_t XB, int XCS, int XVS, int v,
    int x, int c, int b, v8 *restrict out, const int nq)
{
    v8 even[8], odd[8];
    for (int q = 0; q < nq; q++) even[q] = odd[q] = (v8){0, 0, 0, 0, 0, 0, 0, 0};
    const float *o = O + (size_t)v * Wo + x;
    const float *f = FX + (size_t)v * WX + XB - (ptrdiff_t)c * XCS;
    int i = 0;
    for (; i + 2 <= b; i += 2) {
        const float o0 = o[(size_t)i * Wo], o1 = o[(size_t)(i + 1) * Wo];
        const float *f0 = f + (size_t)i * WX, *f1 = f0 + WX;
        for (int q = 0; q < nq; q++) {
            even[q] += o0 * LOADU(f0 + (ptrdiff_t)q * XVS);
            odd[q] += o1 * LOADU(f1 + (ptrdiff_t)q * XVS);
        }
    }
    if (i < b) {
        const float oi = o[(size_t)i * Wo];
        const float *fi = f + (size_t)i * WX;
        for (int q = 0; q < nq; q++) even[q] += oi * LOADU(fi + (ptrdiff_t)q * XVS);
    }
    for (int q = 0; q < nq; q++) out[q] = even[q] + odd[q];
}

static inline float hsum8(v8 x) {
    x += __builtin_shuffle(x, (vi8){4, 5, 6, 7, 0, 1, 2, 3});
    x += __builtin_shuffle(x, (vi8){2, 3, 0, 1, 6, 7, 4, 5});
    x += __builtin_shuffle(x, (vi8){1, 0, 3, 2, 5, 4, 7, 6});
    return x[0];
}

typedef struct {
    const float *O; int Wo; const float *FX; size_t WX; ptrdiff_t XB; int XCS; int XVS; int S; int C; int CP;
    const int32_t *K; int col_shift; int v0; int W; int b;
    const float *CSUM; const float *CINV; const uint8_t *CUNK; size_t WS; ptrdiff_t SB;
    const float *OSUM; const float *OINV; float beta; float d_lo; float d_hi;
    float *disp; const float *GD; float *G; float *dOSUM; float *dOINV; float *dBETA;
    v8 OFF[8]; vi8 PADL[8];  /* candidate offsets (t - T) / S; -1 in lanes t >= C */
} refine_args;

/* One row v of ddsgen_refine, with constant nq = CP / 8 (accumulators in registers).
 *
 * A window's cross-correlations are the sum of its b columns' (column_cross). Those depend on the
 * observed column and on k only, so along a run of pixels with the same k each new pixel adds one
 * column, and only a change of k recomputes the window's b columns (k changes at 6-20 % of the
 * pixels of a rendered frame; the work per pixel falls about 3-fold). The columns are kept in a ring
 * (column x at slot x mod b) and always added in window order, so a pixel's result depends on
 * (v, u, k) alone, never on its neighbours. */
static inline __attribute__((always_inline)) void refine_row(const refine_args *A, int v, const int nq)
{
    const v8 m3 = {-3.0f, -3.0f, -3.0f, -3.0f, -3.0f, -3.0f, -3.0f, -3.0f};
    const v8 zero = {0, 0, 0, 0, 0, 0, 0, 0};
    const v8 vlow = {-3.4e38f, -3.4e38f, -3.4e38f, -3.4e38f, -3.4e38f, -3.4e38f, -3.4e38f, -3.4e38f};
    const int b = A->b;
    const float nf = (float)(b * b), beta = A->beta;
    v8 ring[b][8];
    int ring_k = INT32_MIN;  /* the ring holds columns u .. u + b - 2 at ring_k (before pixel u); none yet */
    for (int u = 0, first = 0; u < A->W; u++, first = first + 1 == b ? 0 : first + 1) {  /* first = u mod b */
        const size_t p = (size_t)v * A->W + u;
        const int k = A->K[p];
        const int c0 = u + A->col_shift - k;
        v8 cr[8], z[8], e[8];
        vi8 ex[8];
        if (k != ring_k) {  /* disparities are >= 0: the first pixel always fills the ring */
            for (int j = 0, slot = first; j < b - 1; j++, slot = slot + 1 == b ? 0 : slot + 1)
                column_cross(A->O, A->Wo, A->FX, A->WX, A->XB, A->XCS, A->XVS, v, u + j, c0 + j, b, ring[slot], nq);
            ring_k = k;
        }
        const int last = first == 0 ? b - 1 : first - 1;  /* (u + b - 1) mod b: the slot of column u - 1 */
        column_cross(A->O, A->Wo, A->FX, A->WX, A->XB, A->XCS, A->XVS, v, u + b - 1, c0 + b - 1, b, ring[last], nq);
        {
            v8 even[8], odd[8];
            for (int q = 0; q < nq; q++) even[q] = odd[q] = zero;
            int slot = first, j = 0;
            for (; j + 2 <= b; j += 2) {
                const int next = slot + 1 == b ? 0 : slot + 1;
                for (int q = 0; q < nq; q++) {
                    even[q] += ring[slot][q];
                    odd[q] += ring[next][q];
                }
                slot = next + 1 == b ? 0 : next + 1;
            }
            if (j < b)
                for (int q = 0; q < nq; q++) even[q] += ring[slot][q];
            for (int q = 0; q < nq; q++) cr[q] = even[q] + odd[q];
        }
        const float a = A->OSUM[p] / nf, io = A->OINV[p];
        const size_t s = (size_t)v * A->WS + (size_t)(A->SB - (ptrdiff_t)c0 * A->S);
        const float *cs = A->CSUM + s, *ci = A->CINV + s;  /* read 8 nq floats: arrays have slack */
        const uint8_t *cu = A->CUNK + s;
        const float kf = (float)k;
        v8 mv = vlow;
        for (int q = 0; q < nq; q++) {
            const v8 dt = kf + A->OFF[q];
            vi8 x = (dt < A->d_lo) | (dt > A->d_hi) | A->PADL[q];
            vu8 unk;
            memcpy(&unk, cu + 8 * q, 8);
            x |= __builtin_convertvector(unk, vi8) != 0;
            const v8 zz = vsel8(x, m3, ((cr[q] - a * LOADU(cs + 8 * q)) * io) * LOADU(ci + 8 * q));
            z[q] = zz;
            ex[q] = x;
            e[q] = vsel8(A->PADL[q], vlow, beta * zz);
            mv = vmax8(mv, e[q]);
        }
        const float m = hmax8(mv);
        v8 se_v = zero, so_v = zero;
        for (int q = 0; q < nq; q++) {
            e[q] = vsel8(A->PADL[q], zero, vexp8(e[q] - m));
            se_v += e[q];
            so_v += e[q] * A->OFF[q];
        }
        const float se = hsum8(se_v), delta = hsum8(so_v) / se;
        if (!A->GD) {
            A->disp[p] = kf + delta;
            continue;
        }
        const float g = A->GD[p];
        v8 *gp = (v8 *)(A->G + ((size_t)(v - A->v0) * A->W + u) * A->CP);
        v8 db = zero, dos = zero, doi = zero;
        for (int q = 0; q < nq; q++) {
            const v8 dl = g * (e[q] / se) * (A->OFF[q] - delta);
            db += dl * z[q];
            const v8 dz = vsel8(ex[q], zero, dl * beta);
            const v8 c_i = LOADU(ci + 8 * q), c_s = LOADU(cs + 8 * q);
            const v8 gt = vsel8(ex[q], zero, dz * io * c_i);  /* (garbage lanes: excluded) */
            gp[q] = gt;
            dos -= vsel8(ex[q], zero, gt * c_s / nf);
            doi += vsel8(ex[q], zero, dz * (cr[q] - a * c_s) * c_i);
        }
        A->dOSUM[p] = hsum8(dos);
        A->dOINV[p] = hsum8(doi);
        A->dBETA[p] = hsum8(db);
    }
}

/* Sub-pixel refinement, fused (no cost volume is written). For each pixel (v, u) of rows
 * [v0, v1) with integer disparity k = K[v][u] and candidates t = 0..C-1 (d_t = k + (t - T)/S,
 * T = (C - 1) / 2), window start column c0 = u + col_shift - k:
 *   cross_t = sum_{i<b, j<b} O[v+i][u+j] * F[v+i][c0 + j][t],
 *             F[y][c][8q + l] = FX[y][XB - c XCS + q XVS + l]
 *   z_t     = ((cross_t - OSUM/n * CSUM_t) * OINV) * CINV_t, or -3 if excluded (CUNK, or d_t
 *             outside [d_lo, d_hi])
 *   d       = k + sum_t e_t (t - T)/S / sum_t e_t,  e_t = exp(beta z_t - max beta z)
 * Candidate t of column c is phase (t - T) mod S, shifted by floor((t - T) / S) columns; FX
 * holds the S phases interleaved in reversed column order (XCS = S, XVS = 8: the C candidates
 * of a column are contiguous), or for S < 8 the first 8 candidates of every column (XCS = 8,
 * XVS = 64 / S: vector q of column c is vector 0 of column c - 8q / S), so that vectors are
 * 32-byte aligned; no per-candidate copy exists. CP (a multiple of 8, at most 64) values are
 * read per column. CSUM, CINV, CUNK (row stride WS) are the phases' window
 * statistics in the same layout: candidate t of window start column c is [v][SB - c S + t].
 * All arrays have zero (CUNK: 1) elements around the phases for the reads that fall outside. Forward (GD == NULL): writes disp[v][u]. Backward (GD given): recomputes
 * the same and writes, for dL/dd = GD[v][u], the gradients w.r.t. cross_t into
 * G[(v - v0)][u][t] (band-local, CP per pixel, 0 in padding lanes), w.r.t. OSUM, OINV into
 * dOSUM, dOINV and the pixel's contribution to dL/dbeta into dBETA (all H x W). Every pixel is
 * computed on its own, in a fixed order: results depend neither on the thread count nor on the
 * band split. */
void ddsgen_refine(const float *restrict O, int Wo, const float *restrict FX, int64_t WX, int64_t XB, int XCS, int XVS,
                   int C, int CP,
                   const int32_t *restrict K, int col_shift, int v0, int v1, int W, int b,
                   const float *restrict CSUM, const float *restrict CINV, const uint8_t *restrict CUNK, int64_t WS,
                   int64_t SB,
                   const float *restrict OSUM, const float *restrict OINV, float beta, int S,
                   float d_lo, float d_hi, float *restrict disp,
                   const float *restrict GD, float *restrict G, float *restrict dOSUM,
                   float *restrict dOINV, float *restrict dBETA, int n_threads)
{
    refine_args A = {O, Wo, FX, (size_t)WX, (ptrdiff_t)XB, XCS, XVS, S, C, CP, K, col_shift, v0, W, b, CSUM, CINV, CUNK,
                     (size_t)WS, (ptrdiff_t)SB, OSUM, OINV, beta, d_lo, d_hi, disp, GD, G, dOSUM, dOINV, dBETA};
    const int T = (C - 1) / 2;
    for (int t = 0; t < 64; t++) {
        A.OFF[t / 8][t % 8] = (float)(t - T) / (float)S;
        A.PADL[t / 8][t % 8] = t < C ? 0 : -1;
    }
    const int nq = CP / 8;
#pragma omp parallel for schedule(dynamic, 4) num_threads(n_threads)
    for (int v = v0; v < v1; v++) {
        switch (nq) {  /* constant trip counts: the accumulators stay in registers */
        case 1: refine_row(&A, v, 1); break;
        case 2: refine_row(&A, v, 2); break;
        case 3: refine_row(&A, v, 3); break;
        case 4: refine_row(&A, v, 4); break;
        case 5: refine_row(&A, v, 5); break;
        case 6: refine_row(&A, v, 6); break;
        case 7: refine_row(&A, v, 7); break;
        default: refine_row(&A, v, 8); break;
        }
    }
}

/* acc[q] = sum_t g[t] * ft[toff[t] + 8q .. 8q + 7], q < nbq; NR candidates side by side
 * into separate sums (independent dependency chains). */
static inline __attribute__((always_inline)) void cross_grad(
    const float *restrict g, const float *restrict ft, const ptrdiff_t *restrict toff, int C, v8 *restrict out,
    const int nbq, const int NR)
{
    v8 acc[4][8];
    for (int r = 0; r < NR; r++)
        for (int q = 0; q < nbq; q++) acc[r][q] = (v8){0, 0, 0, 0, 0, 0, 0, 0};
    int t = 0;
    for (; t + NR <= C; t += NR)
        for (int r = 0; r < NR; r++) {
            const float gt = g[t + r];
            const float *restrict f = ft + toff[t + r];
            for (int q = 0; q < nbq; q++) acc[r][q] += gt * LOADU(f + 8 * q);
        }
    for (; t < C; t++) {
        const float gt = g[t];
        const float *restrict f = ft + toff[t];
        for (int q = 0; q < nbq; q++) acc[0][q] += gt * LOADU(f + 8 * q);
    }
    for (int q = 0; q < nbq; q++) {
        v8 s = acc[0][q];
        for (int r = 1; r < NR; r++) s += acc[r][q];
        out[q] = s;
    }
}

/* Backward of the window cross-correlation w.r.t. O, for the band of rows [v0, v1): adds
 *   dO[y][u+j] += sum_t G[v - v0][u][t] * FT[t][y][c0 + j]   (G: CG floats per pixel)   for v = y - i in [v0, v1), all u, j
 * (c0 = u + col_shift - K[v][u]), where FT[t][y][c] = P[s][y][PL + c - q] for candidate t - T
 * = q S + s (0 <= s < S): P holds the S phases (S x Hp x WP) with PL zero columns on the left,
 * and is readable 7 columns beyond the last window column of every shift. Each row y is owned by one thread (no races,
 * deterministic). Bands are called in order and each dO element receives its terms in order
 * of (v, u) whatever the band split, so the result is bit-identical for any split. */
void ddsgen_window_cross_grad(const float *restrict G, int CG, const float *restrict P, int WP, int PL, int Hp,
                              int S, int C, const int32_t *restrict K, int col_shift, int v0, int v1, int W,
                              int b, float *restrict dO, int Wo, int n_threads)
{
    const int nbq = (b + 7) / 8;
    const int T = (C - 1) / 2;
    ptrdiff_t toff[64];  /* element offset of candidate t from P[0][y][c0] */
    for (int t = 0; t < C && t < 64; t++) {
        const int tt = t - T;
        const int q = tt >= 0 ? tt / S : -((-tt + S - 1) / S);
        const int s = tt - q * S;
        toff[t] = (ptrdiff_t)s * Hp * WP + PL - q;
    }
#pragma omp parallel num_threads(n_threads)
    {
        v8 acc[8];
#pragma omp for schedule(dynamic, 4)
        for (int y = v0; y < v1 + b - 1; y++) {
            float *restrict drow = dO + (size_t)y * Wo;
            for (int i = b - 1; i >= 0; i--) {  /* v ascending, as across bands: every dO */
                const int v = y - i;                /* element sums its terms in the same order */
                if (v < v0 || v >= v1) continue;
                for (int u = 0; u < W; u++) {
                    const float *restrict g = G + ((size_t)(v - v0) * W + u) * CG;
                    const int c0 = u + col_shift - K[(size_t)v * W + u];
                    const float *restrict ft = P + (size_t)y * WP + c0;
                    switch (nbq) {  /* constant trip counts: the accumulators stay in registers */
                    case 1: cross_grad(g, ft, toff, C, acc, 1, 4); break;
                    case 2: cross_grad(g, ft, toff, C, acc, 2, 4); break;
                    case 3: cross_grad(g, ft, toff, C, acc, 3, 2); break;
                    case 4: cross_grad(g, ft, toff, C, acc, 4, 2); break;
                    case 5: cross_grad(g, ft, toff, C, acc, 5, 1); break;
                    case 6: cross_grad(g, ft, toff, C, acc, 6, 1); break;
                    case 7: cross_grad(g, ft, toff, C, acc, 7, 1); break;
                    default: cross_grad(g, ft, toff, C, acc, 8, 1); break;
                    }
                    const float *restrict sv = (const float *)acc;
                    float *restrict d = drow + u;
                    for (int j = 0; j < b; j++) d[j] += sv[j];  /* scalar: store-forwarding friendly */
                }
            }
        }
    }
}

/* ---- confirmed matches: a unique neighbour within the window agrees with a peak -------------------------
 *
 * For each candidate pixel i at (ys[i], xs[i]) and each of its n_peaks peak disparities own[j * n + i]:
 * out[j * n + i] = 1 when some pixel of the block x block window centred on it holds a unique match whose
 * integer disparity is within 1 px of that peak. seeds is the (H + 2h) x Ws grid (Ws = W + 2h, h = block / 2)
 * of the unique matches' disparities, padded by h and holding a sentinel far from every disparity elsewhere,
 * so the window of pixel (y, x) is rows y .. y + 2h, columns x .. x + 2h of it. The scan stops at the first
 * agreeing neighbour (the torch twin, matcher._confirmed_by_a_unique_neighbour, gathers all block^2). */
void ddsgen_confirm_by_unique_neighbour(const int32_t *restrict seeds, int Ws, const int64_t *restrict ys,
                                        const int64_t *restrict xs, int64_t n, const int32_t *restrict own,
                                        int n_peaks, int block, uint8_t *restrict out, int n_threads) {
#pragma omp parallel for schedule(static) num_threads(n_threads)
    for (int64_t i = 0; i < n; i++) {
        const int32_t *corner = seeds + ys[i] * (int64_t)Ws + xs[i];
        for (int j = 0; j < n_peaks; j++) {
            const int32_t peak = own[(int64_t)j * n + i];
            uint8_t found = 0;
            for (int dy = 0; dy < block && !found; dy++) {
                const int32_t *row = corner + (int64_t)dy * Ws;
                for (int dx = 0; dx < block; dx++) {
                    const int32_t diff = row[dx] - peak;
                    if (diff >= -1 && diff <= 1) {
                        found = 1;
                        break;
                    }
                }
            }
            out[(int64_t)j * n + i] = found;
        }
    }
}
