/* project.cl — stage 1: world to camera, cull, EWA 2D covariance, conic, radii, depth.
 *
 * One work-item per (camera, Gaussian) pair cg = c * N + g. Culled pairs get radii 0 and an
 * empty tile rectangle, so no later stage touches them.
 *
 * Build parameters: REAL_DOUBLE, TILE, ANTIALIASED (0/1), TILE_COUNTS (0/1: write tiles), the
 * radius knobs of common.h, and CLS_POCL_CPU (inline sqrt, ceil, floor, min, max: common.h).
 */

__kernel void project(const int C, const int N,
                      __global const REAL *means,     /* [N, 3] */
                      __global const REAL *quats,     /* [N, 4] wxyz */
                      __global const REAL *scales,    /* [N, 3] */
                      __global const REAL *opacities, /* [N] */
                      __global const REAL *viewmats,  /* [C, 4, 4] world to camera */
                      __global const REAL *Ks,        /* [C, 3, 3] */
                      const int width, const int height,
                      const REAL near_plane, const REAL far_plane,
                      const REAL eps2d, const REAL radius_clip,
                      const int tiles_x, const int tiles_y,
                      __global REAL *means2d,  /* [C, N, 2] */
                      __global REAL *conics,   /* [C, N, 3] */
                      __global REAL *depths,   /* [C, N] */
                      __global int *radii,     /* [C, N, 2] */
                      __global REAL *opac_cg,  /* [C, N] opacity used in compositing */
                      __global int *rects,     /* [C, N, 4] tile rectangle x0 y0 x1 y1 */
                      __global REAL *extents,  /* [C, N, 2] |dx|, |dy| beyond which alpha < ALPHA_MIN */
                      __global int *tiles)     /* [C, N] tiles in the rectangle (TILE_COUNTS): the host
                                                * sums these (4 bytes a pair) instead of the rectangles */
{
    const int cg = get_global_id(0);
    if (cg >= C * N) return; /* no barrier in this kernel */
    const int c = cg / N, g = cg - c * N;
    __global const REAL *vm = viewmats + 16 * c;
    __global const REAL *K = Ks + 9 * c;

    /* A culled pair's outputs are zeros, written here rather than by a host fill of every
     * array before the launch: the first touch of fresh memory then happens on the device's
     * cores, once (a visible pair's values overwrite these in the same cache lines). */
    radii[2 * cg] = 0;
    radii[2 * cg + 1] = 0;
    rects[4 * cg] = rects[4 * cg + 1] = rects[4 * cg + 2] = rects[4 * cg + 3] = 0;
    means2d[2 * cg] = means2d[2 * cg + 1] = 0;
    conics[3 * cg] = conics[3 * cg + 1] = conics[3 * cg + 2] = 0;
    opac_cg[cg] = 0;
    extents[2 * cg] = extents[2 * cg + 1] = 0;
#if TILE_COUNTS
    tiles[cg] = 0;
#endif

    const REAL3 m = (REAL3)(means[3 * g], means[3 * g + 1], means[3 * g + 2]);
    const REAL3 p = (REAL3)(vm[0] * m.x + vm[1] * m.y + vm[2] * m.z + vm[3],
                            vm[4] * m.x + vm[5] * m.y + vm[6] * m.z + vm[7],
                            vm[8] * m.x + vm[9] * m.y + vm[10] * m.z + vm[11]);
    depths[cg] = p.z;
    if (!(p.z >= near_plane && p.z <= far_plane)) return;
    const REAL Rv[9] = {vm[0], vm[1], vm[2], vm[4], vm[5], vm[6], vm[8], vm[9], vm[10]};
    const REAL s0 = scales[3 * g], s1 = scales[3 * g + 1], s2 = scales[3 * g + 2];
    const REAL rz = 1 / p.z;
    const REAL2 xy = (REAL2)(K[0] * p.x * rz + K[2], K[4] * p.y * rz + K[5]);

    /* Off screen by more than any radius its scales allow: culled before the EWA. Of a surround
     * rig's pairs about half lie in front of a camera, and more than half of those beside its
     * image (scene B: 26 % of all pairs, against 21 % visible). A mean on the image needs no
     * bound (it cannot be culled this way), so one camera's view pays four comparisons. */
    if (p.z > 0 && !(xy.x >= 0 && xy.x < width && xy.y >= 0 && xy.y < height)) {
        const REAL2 rb = radius_bounds(p, Rv, s0 * s0 + s1 * s1 + s2 * s2, eps2d, K,
                                       frustum_limits(K, width, height));
        if (xy.x + rb.x <= 0 || xy.x - rb.x >= width || xy.y + rb.y <= 0 || xy.y - rb.y >= height) return;
    }

    /* World covariance M M^T with M = R S. */
    REAL Rq[9];
    quat_to_rotmat((REAL4)(quats[4 * g], quats[4 * g + 1], quats[4 * g + 2], quats[4 * g + 3]), Rq);
    REAL M[9] = {Rq[0] * s0, Rq[1] * s1, Rq[2] * s2,
                 Rq[3] * s0, Rq[4] * s1, Rq[5] * s2,
                 Rq[6] * s0, Rq[7] * s1, Rq[8] * s2};
    const Ewa e = ewa_splat(p, Rv, M, K, width, height);
    REAL a = e.a, d = e.d;
    const REAL b = e.b;
    const REAL det_orig = a * d - b * b;
    a += eps2d;
    d += eps2d;
    const REAL det = a * d - b * b;
    if (!(det > 0)) return;
    const REAL inv_det = 1 / det;

    REAL op = opacities[g];
#if ANTIALIASED
    op *= CLS_SQRT(CLS_FMAX((REAL)0, det_orig * inv_det));
#endif
#if OPACITY_AWARE_RADIUS
    /* gsplat's rule: beyond sqrt(2 ln(o / ALPHA_MIN)) sigmas the sample falls below
     * ALPHA_MIN and would be skipped anyway; never more than RADIUS_SIGMA. */
    if (!(op >= (REAL)ALPHA_MIN)) return;
    const REAL cut = log(op / (REAL)ALPHA_MIN); /* (also the compositing extents' below) */
    const REAL extent = CLS_FMIN((REAL)RADIUS_SIGMA, CLS_SQRT(2 * cut));
#else
    const REAL extent = (REAL)RADIUS_SIGMA;
#endif
    /* Radii are capped so a near-plane giant cannot overflow int; any cap above the image
     * size culls and bins identically. */
    const REAL rcap = (REAL)(1 << 30);
    const REAL rxf = CLS_FMIN(rcap, CLS_CEIL(extent * CLS_SQRT(a)));
    const REAL ryf = CLS_FMIN(rcap, CLS_CEIL(extent * CLS_SQRT(d)));
    if (rxf <= radius_clip && ryf <= radius_clip) return;

    if (xy.x + rxf <= 0 || xy.x - rxf >= width || xy.y + ryf <= 0 || xy.y - ryf >= height) return;
    const int2 rad = (int2)((int)rxf, (int)ryf);
    const int4 rect = tile_rect(xy, rad, tiles_x, tiles_y);
    if (rect.z <= rect.x || rect.w <= rect.y) return;

    radii[2 * cg] = rad.x;
    radii[2 * cg + 1] = rad.y;
    means2d[2 * cg] = xy.x;
    means2d[2 * cg + 1] = xy.y;
    conics[3 * cg] = d * inv_det;
    conics[3 * cg + 1] = -b * inv_det;
    conics[3 * cg + 2] = a * inv_det;
    opac_cg[cg] = op;
    /* alpha >= ALPHA_MIN needs sigma <= cut = log(o / ALPHA_MIN), and over a pixel row sigma
     * is at least dy^2 / (2 cov_yy) (likewise for columns): compositing skips a sample
     * beyond these extents without evaluating it. Computed here from the covariance, where
     * it is accurate even for needles whose conic has lost its determinant to rounding. */
#if !OPACITY_AWARE_RADIUS
    const REAL cut = log(op / (REAL)ALPHA_MIN);
#endif
    extents[2 * cg] = cut >= 0 ? CLS_SQRT(2 * cut * a) : (REAL)-1;
    extents[2 * cg + 1] = cut >= 0 ? CLS_SQRT(2 * cut * d) : (REAL)-1;
    rects[4 * cg] = rect.x;
    rects[4 * cg + 1] = rect.y;
    rects[4 * cg + 2] = rect.z;
    rects[4 * cg + 3] = rect.w;
#if TILE_COUNTS
    tiles[cg] = (rect.z - rect.x) * (rect.w - rect.y); /* <= tiles_x * tiles_y */
#endif
}
