/* raster.c: exact first hits of a pinhole camera's pixel-centre rays on triangle meshes (ddsgen/raster.py).
 *
 * What it computes. The ray of pixel (u, v) leaves the camera centre along d = ((u - cx) / fx,
 * (v - cy) / fy, 1), so its parameter t at a hit is the depth z. For every triangle of every mesh
 * (vertices in the camera frame; a triangle reaching behind the camera is first clipped to the
 * half-space in front of it), the pixels whose centres fall in the triangle's projected bounding box are
 * tested with the Moller-Trumbore ray-triangle test in double precision; a hit nearer than the
 * pixel's current depth (the analytic planes' depths, or an earlier triangle's) replaces it:
 * a z-buffer whose samples are exact ray casts, not interpolated depths. Per pixel it writes
 * the depth, the owner (index of the mesh in the caller's list), the face index in that mesh,
 * Embree's barycentrics (P = (1 - b0 - b1) V0 + b0 V1 + b1 V2) and the unit geometric normal
 * turned towards the camera. Per mesh it counts the pixels the mesh covers when alone
 * (a pixel is counted once per mesh, whatever its depth), which a BOP visible fraction needs.
 *
 * Why not Embree for these rays: embreex casts one ray per call from a Python loop over
 * numpy rows, about 130 ns per ray on these machines; a pinhole camera's primary rays are a
 * raster, and walking each triangle's few pixels costs a fraction of that. Results are
 * independent of any thread count (one thread; triangles in a fixed order, ties keep the
 * first). Built with the system compiler like the matcher's kernels (ddsgen/ckernel.py).
 */

#include <math.h>
#include <stdint.h>
#include <stdlib.h>

/* Parts of triangles nearer than this to the camera plane (m) are clipped off before projecting (as in
 * ddsgen/raycast_planes.py). */
#define NEAR_CLIP_M 1e-4

/* One face's corners (double) and its edges from p0. */
typedef struct {
    double p0[3], p1[3], p2[3], e1[3], e2[3];
} Triangle;

static inline Triangle load_triangle(const float *vertices, const int32_t *faces, int64_t f)
{
    Triangle tri;
    for (int k = 0; k < 3; k++) {
        tri.p0[k] = vertices[3 * (int64_t)faces[3 * f] + k];
        tri.p1[k] = vertices[3 * (int64_t)faces[3 * f + 1] + k];
        tri.p2[k] = vertices[3 * (int64_t)faces[3 * f + 2] + k];
    }
    for (int k = 0; k < 3; k++) tri.e1[k] = tri.p1[k] - tri.p0[k], tri.e2[k] = tri.p2[k] - tri.p0[k];
    return tri;
}

/* Moller-Trumbore: whether the ray o + t d (d not normalised) meets the triangle at t > 0; then its t and
 * barycentrics (b0, b1) with P = (1 - b0 - b1) p0 + b0 p1 + b1 p2 (Embree's u, v). Inlined: called per pixel
 * (a call through pointers cost the raster ~15 %). */
static inline __attribute__((always_inline)) int ray_hits_triangle(const Triangle *tri, const double *o,
                                                                    const double *d, double *t, double *b0,
                                                                    double *b1)
{
    const double *e1 = tri->e1, *e2 = tri->e2;
    double pvec[3] = {d[1] * e2[2] - d[2] * e2[1], d[2] * e2[0] - d[0] * e2[2], d[0] * e2[1] - d[1] * e2[0]};
    double det = e1[0] * pvec[0] + e1[1] * pvec[1] + e1[2] * pvec[2];
    if (det == 0.0) return 0; /* the ray lies in the triangle's plane */
    double inv = 1.0 / det;
    double s[3] = {o[0] - tri->p0[0], o[1] - tri->p0[1], o[2] - tri->p0[2]};
    *b0 = (s[0] * pvec[0] + s[1] * pvec[1] + s[2] * pvec[2]) * inv;
    if (*b0 < 0.0 || *b0 > 1.0) return 0;
    double q[3] = {s[1] * e1[2] - s[2] * e1[1], s[2] * e1[0] - s[0] * e1[2], s[0] * e1[1] - s[1] * e1[0]};
    *b1 = (d[0] * q[0] + d[1] * q[1] + d[2] * q[2]) * inv;
    if (*b1 < 0.0 || *b0 + *b1 > 1.0) return 0;
    *t = (e2[0] * q[0] + e2[1] * q[1] + e2[2] * q[2]) * inv;
    return *t > 0.0;
}

/* The projection of triangle (p0, p1, p2)'s part at z >= NEAR_CLIP_M (clipped against that plane) into
 * a camera at (eye_x, 0, 0) with the camera's orientation and intrinsics: a convex polygon of 0, 3 or 4
 * points (pu, pv) in order. Returns the number of points. */
static int clipped_projection(const double *p0, const double *p1, const double *p2, double eye_x, double fx,
                              double fy, double cx, double cy, double *pu, double *pv)
{
    const double *corner[3] = {p0, p1, p2};
    int n = 0;
    for (int k = 0; k < 3; k++) {
        const double *x = corner[k], *y = corner[(k + 1) % 3];
        double kept[2][3];
        int n_kept = 0;
        if (x[2] >= NEAR_CLIP_M) {
            kept[n_kept][0] = x[0], kept[n_kept][1] = x[1], kept[n_kept][2] = x[2];
            n_kept++;
        }
        if ((x[2] >= NEAR_CLIP_M) != (y[2] >= NEAR_CLIP_M)) { /* the edge crosses the plane */
            double w = (NEAR_CLIP_M - x[2]) / (y[2] - x[2]);
            kept[n_kept][0] = x[0] + w * (y[0] - x[0]);
            kept[n_kept][1] = x[1] + w * (y[1] - x[1]);
            kept[n_kept][2] = NEAR_CLIP_M;
            n_kept++;
        }
        for (int j = 0; j < n_kept; j++, n++) {
            pu[n] = fx * (kept[j][0] - eye_x) / kept[j][2] + cx;
            pv[n] = fy * kept[j][1] / kept[j][2] + cy;
        }
    }
    return n;
}

/* The u-range [*lo, *hi] of a convex polygon (n points pu, pv) within the strip va <= v <= vb: the extremes
 * lie on its edges clipped to the strip. Returns 0 when the strip misses it. */
static int strip_span(const double *pu, const double *pv, int n, double va, double vb, double *lo, double *hi)
{
    *lo = INFINITY, *hi = -INFINITY;
    for (int k = 0; k < n; k++) {
        double u0 = pu[k], v0 = pv[k], u1 = pu[(k + 1) % n], v1 = pv[(k + 1) % n];
        double t0 = 0.0, t1 = 1.0;
        if (v0 == v1) {
            if (v0 < va || v0 > vb) continue;
        } else {
            double ta = (va - v0) / (v1 - v0), tb = (vb - v0) / (v1 - v0);
            t0 = fmax(0.0, fmin(ta, tb)), t1 = fmin(1.0, fmax(ta, tb));
            if (t0 > t1) continue;
        }
        double ua = u0 + t0 * (u1 - u0), ub = u0 + t1 * (u1 - u0);
        *lo = fmin(*lo, fmin(ua, ub)), *hi = fmax(*hi, fmax(ua, ub));
    }
    return *lo <= *hi;
}

/* The v extent [*v_lo, *v_hi] of a polygon of n points. */
static void polygon_v_range(const double *pv, int n, double *v_lo, double *v_hi)
{
    *v_lo = INFINITY, *v_hi = -INFINITY;
    for (int k = 0; k < n; k++) *v_lo = fmin(*v_lo, pv[k]), *v_hi = fmax(*v_hi, pv[k]);
}

void ddsgen_raster_hits(const float *vertices, const int32_t *faces, const int64_t *face_start,
                        const int32_t *mesh_owner, int n_meshes, int width, int height,
                        double fx, double fy, double cx, double cy,
                        float *depth, int32_t *owner, int32_t *triangle, float *barycentric,
                        float *normal, int64_t *coverage, int32_t *stamp)
{
    /* vertices: (V, 3) float32, every mesh's, camera frame; faces: (F, 3) int32 rows of `vertices`;
     * face_start: (n_meshes + 1,) first face of each mesh; mesh_owner: (n_meshes,) owner index to write;
     * depth (H*W,) in/out (inf = nothing yet), owner / triangle (H*W,) int32 in/out, barycentric (H*W, 2),
     * normal (H*W, 3) out where this kernel wins; coverage (n_meshes,) out; stamp (H*W,) int32 scratch set
     * to -1 by the caller. */
    const double origin[3] = {0.0, 0.0, 0.0};
    for (int m = 0; m < n_meshes; m++) {
        int64_t covered = 0;
        for (int64_t f = face_start[m]; f < face_start[m + 1]; f++) {
            Triangle tri = load_triangle(vertices, faces, f);
            const double *p0 = tri.p0, *e1 = tri.e1, *e2 = tri.e2;
            double n[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                           e1[0] * e2[1] - e1[1] * e2[0]};
            double n_len = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
            if (!(n_len > 0.0)) continue; /* degenerate: no ray hits it */
            /* Towards the camera: the camera centre (the origin) is on the side n . (0 - P0) > 0. */
            double facing = (n[0] * p0[0] + n[1] * p0[1] + n[2] * p0[2]) > 0.0 ? -1.0 : 1.0;
            float nx = (float)(facing * n[0] / n_len), ny = (float)(facing * n[1] / n_len),
                  nz = (float)(facing * n[2] / n_len);
            /* The pixel centres inside the projection of the part at z >= NEAR_CLIP_M, row by row. Hits
             * nearer than NEAR_CLIP_M outside it are lost: 0.1 mm from the camera, far below any sensor's
             * range. */
            double pu[4], pv[4], v_lo, v_hi;
            int n_points = clipped_projection(tri.p0, tri.p1, tri.p2, 0.0, fx, fy, cx, cy, pu, pv);
            if (n_points < 3) continue; /* wholly behind the plane */
            polygon_v_range(pv, n_points, &v_lo, &v_hi);
            /* Margins far above rounding: the exact test below decides, the spans only limit the work. */
            int row0 = (int)fmax(ceil(v_lo - 1e-6), 0.0), row1 = (int)fmin(floor(v_hi + 1e-6), height - 1.0);
            for (int row = row0; row <= row1; row++) {
                double u_lo, u_hi;
                if (!strip_span(pu, pv, n_points, row - 1e-6, row + 1e-6, &u_lo, &u_hi)) continue;
                int col0 = (int)fmax(ceil(u_lo - 1e-6), 0.0), col1 = (int)fmin(floor(u_hi + 1e-6), width - 1.0);
                double dy = (row - cy) / fy;
                for (int col = col0; col <= col1; col++) {
                    double d[3] = {(col - cx) / fx, dy, 1.0}, t, b0, b1;
                    if (!ray_hits_triangle(&tri, origin, d, &t, &b0, &b1)) continue;
                    int64_t pixel = (int64_t)row * width + col;
                    if (stamp[pixel] != m) {
                        stamp[pixel] = m;
                        covered++;
                    }
                    float tf = (float)t;
                    if (!(tf < depth[pixel])) continue; /* ties keep the earlier surface */
                    depth[pixel] = tf;
                    owner[pixel] = mesh_owner[m];
                    triangle[pixel] = (int32_t)(f - face_start[m]);
                    barycentric[2 * pixel] = (float)b0;
                    barycentric[2 * pixel + 1] = (float)b1;
                    normal[3 * pixel] = nx;
                    normal[3 * pixel + 1] = ny;
                    normal[3 * pixel + 2] = nz;
                }
            }
        }
        coverage[m] = covered;
    }
}

/* Whether the segment P -> S (P the projector at (projector_x, 0, 0)) crosses the triangle strictly between P
 * and just before S (ray parameter in (0, 1 - 1e-6), as Embree's capped occlusion ray). */
static int segment_crosses(const Triangle *tri, double projector_x, const float *s)
{
    double o[3] = {projector_x, 0.0, 0.0}, d[3] = {s[0] - projector_x, s[1], s[2]}, t, b0, b1;
    return ray_hits_triangle(tri, o, d, &t, &b0, &b1) && t < 1.0 - 1e-6;
}

/* Largest grid of projector-image cells, per start point: bounds the memory when the points project far apart. */
#define CELLS_PER_POINT 4

int ddsgen_raster_shadow(const float *vertices, const int32_t *faces, int64_t n_faces, const float *all_starts,
                         const int64_t *rays, int64_t n_starts, double projector_x, double fx, double fy, double cx,
                         double cy, uint8_t *blocked, int64_t *scratch)
{
    /* Which segments S -> projector cross a triangle. vertices (V, 3) float32 and faces (F, 3) int32 as
     * above; the segments start at all_starts[rays[i]] (all_starts (M, 3) float32, rays (N,) int64 indices
     * into it; NULL: the first N), every z >= NEAR_CLIP_M (the caller tests the others itself);
     * blocked (M,) uint8 set to 1 at rays[i] where a triangle blocks segment i (never cleared). scratch:
     * int64, 2 N + 1 + CELLS_PER_POINT N + 2.
     *
     * Every point of a segment S -> P lies on one projector ray, so the segment can only meet a triangle
     * whose projection into the projector's image (a camera at P with the camera's orientation and
     * intrinsics) contains S's projection. The points are bucketed by projector-image cell (counting
     * sort); each triangle tests only the points in the cells its projected box covers. Exact: the box is
     * conservative, the test is the segment's own. Returns 0, or -1 when a start is nearer than
     * NEAR_CLIP_M, -2 when out of memory. */
    if (n_starts == 0) return 0;
    double *uv = malloc(sizeof(double) * 2 * (size_t)n_starts); /* each start's projector-image point */
    if (!uv) return -2;
    double u_min = INFINITY, u_max = -INFINITY, v_min = INFINITY, v_max = -INFINITY;
#define RAY(i) (rays ? rays[i] : (i))
    for (int64_t i = 0; i < n_starts; i++) {
        const float *s = all_starts + 3 * RAY(i);
        if (!(s[2] >= NEAR_CLIP_M)) {
            free(uv);
            return -1;
        }
        double u = fx * (s[0] - projector_x) / s[2] + cx, v = fy * s[1] / s[2] + cy;
        uv[2 * i] = u, uv[2 * i + 1] = v;
        u_min = fmin(u_min, u), u_max = fmax(u_max, u), v_min = fmin(v_min, v), v_max = fmax(v_max, v);
    }
    /* Cell size: 1 px, coarser when the points spread over more than CELLS_PER_POINT N cells. */
    double cell = 1.0;
    while ((floor((u_max - u_min) / cell) + 1.0) * (floor((v_max - v_min) / cell) + 1.0) >
           (double)CELLS_PER_POINT * (double)n_starts)
        cell *= 2.0;
    int64_t grid_w = (int64_t)floor((u_max - u_min) / cell) + 1, grid_h = (int64_t)floor((v_max - v_min) / cell) + 1;
    int64_t *cell_of = scratch, *order = scratch + n_starts, *first = scratch + 2 * n_starts;
    int64_t n_cells = grid_w * grid_h;
    for (int64_t c = 0; c <= n_cells; c++) first[c] = 0;
    for (int64_t i = 0; i < n_starts; i++) {
        const double u = uv[2 * i], v = uv[2 * i + 1];
        int64_t gu = (int64_t)floor((u - u_min) / cell), gv = (int64_t)floor((v - v_min) / cell);
        cell_of[i] = gv * grid_w + gu;
        first[cell_of[i] + 1]++;
    }
    for (int64_t c = 0; c < n_cells; c++) first[c + 1] += first[c];
    for (int64_t i = 0; i < n_starts; i++) order[first[cell_of[i]]++] = i; /* first[c] is now cell c's end */
    for (int64_t c = n_cells; c > 0; c--) first[c] = first[c - 1];
    first[0] = 0;
    for (int64_t f = 0; f < n_faces; f++) {
        Triangle tri = load_triangle(vertices, faces, f);
        double pu[4], pv[4], v_lo, v_hi;
        int n_points = clipped_projection(tri.p0, tri.p1, tri.p2, projector_x, fx, fy, cx, cy, pu, pv);
        if (n_points < 3) continue;
        polygon_v_range(pv, n_points, &v_lo, &v_hi);
        /* Cell rows, then per row the cells whose points can project into the polygon (margins far above
         * rounding; the segment test decides). */
        double h0 = floor((v_lo - 1e-6 - v_min) / cell), h1 = floor((v_hi + 1e-6 - v_min) / cell);
        if (h1 < 0.0 || h0 > (double)(grid_h - 1)) continue;
        int64_t gv0 = h0 < 0.0 ? 0 : (int64_t)h0, gv1 = h1 > grid_h - 1 ? grid_h - 1 : (int64_t)h1;
        for (int64_t gv = gv0; gv <= gv1; gv++) {
            double u_lo, u_hi;
            double va = v_min + gv * cell - 1e-6, vb = v_min + (gv + 1) * cell + 1e-6;
            if (!strip_span(pu, pv, n_points, va, vb, &u_lo, &u_hi)) continue;
            double g0 = floor((u_lo - 1e-6 - u_min) / cell), g1 = floor((u_hi + 1e-6 - u_min) / cell);
            if (g1 < 0.0 || g0 > (double)(grid_w - 1)) continue;
            int64_t gu0 = g0 < 0.0 ? 0 : (int64_t)g0, gu1 = g1 > grid_w - 1 ? grid_w - 1 : (int64_t)g1;
            for (int64_t gu = gu0; gu <= gu1; gu++) {
                int64_t cell_index = gv * grid_w + gu;
                for (int64_t j = first[cell_index]; j < first[cell_index + 1]; j++) {
                    int64_t i = RAY(order[j]);
                    if (!blocked[i] && segment_crosses(&tri, projector_x, all_starts + 3 * i)) blocked[i] = 1;
                }
            }
        }
    }
    free(uv);
    return 0;
#undef RAY
}

/* ---- per-pixel attributes of the primary hits (ddsgen.raycast.cast), one pass each -----------------------
 * Owner indices are rows of per-owner tables whose last row stands for "no hit" (owner -1), as numpy's
 * np.take(table, owner) reads them. */

/* out (n, cols) = rows of table (n_rows, cols) at index (n); index -1 reads the last row. */
void ddsgen_take_rows(const float *table, int64_t n_rows, int64_t cols, const int32_t *index, int64_t n,
                      float *out)
{
    for (int64_t i = 0; i < n; i++) {
        const float *row = table + (index[i] >= 0 ? index[i] : n_rows - 1) * cols;
        for (int64_t c = 0; c < cols; c++) out[i * cols + c] = row[c];
    }
}

/* From each pixel's owner (-1: no hit) and ray parameter t along directions (n, 3) with z = 1: hit, depth
 * (t, 0 without a hit), points = directions * depth, the owner's instance id and albedo; triangle set to 0
 * where the owner is a polygon. ids, albedos, is_polygon: (n_owners + 1,), the last entry for no hit. */
void ddsgen_hit_attributes(const int32_t *owner, const float *best_t, const float *directions, int64_t n,
                           const uint16_t *ids, const float *albedos, const uint8_t *is_polygon, int64_t n_entries,
                           uint8_t *hit, float *depth, float *points, int32_t *triangle, uint16_t *instance,
                           float *albedo)
{
    for (int64_t i = 0; i < n; i++) {
        const int64_t k = owner[i] >= 0 ? owner[i] : n_entries - 1;
        const float d = owner[i] >= 0 ? best_t[i] : 0.0f;
        hit[i] = owner[i] >= 0;
        depth[i] = d;
        for (int c = 0; c < 3; c++) points[3 * i + c] = directions[3 * i + c] * d;
        if (is_polygon[k]) triangle[i] = 0;
        instance[i] = ids[k];
        albedo[i] = albedos[k];
    }
}

/* A planar polygon's primary hits written into the z-buffer (ddsgen.raycast_planes.primary_depth_band and the
 * update ddsgen.raycast.cast makes with it), rows v0 .. v0 + rows - 1 of a width-wide image: at pixel (u, v) the
 * ray parameter offset / (row_term[v - v0] + col_term[u]) (float32, the numpy definition's order), kept where
 * lo[v - v0] <= u <= hi[v - v0], it is > 0 and nearer than best_t; there owner becomes `index`. */
void ddsgen_plane_zbuffer(float offset, const float *row_term, const float *col_term, const double *lo,
                          const double *hi, int64_t v0, int64_t rows, int64_t width, int32_t index, float *best_t,
                          int32_t *owner)
{
    for (int64_t r = 0; r < rows; r++) {
        float *t = best_t + (v0 + r) * width;
        int32_t *o = owner + (v0 + r) * width;
        for (int64_t u = 0; u < width; u++) {
            const float band = offset / (row_term[r] + col_term[u]);
            if ((double)u >= lo[r] && (double)u <= hi[r] && band > 0.0f && band < t[u]) {
                t[u] = band;
                o[u] = index;
            }
        }
    }
}
