/* project.cl — stage 1: world to camera, cull, EWA 2D covariance, conic, radii, depth.
 *
 * One work-item per (camera, Gaussian) pair cg = c * N + g. Culled pairs get radii 0 and an
 * empty tile rectangle, so no later stage touches them.
 *
 * Build parameters: REAL_DOUBLE, TILE, ANTIALIASED (0/1), and the radius knobs of common.h.
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
                      __global REAL *extents)  /* [C, N, 2] |dx|, |dy| beyond which alpha < ALPHA_MIN */
{
    const int cg = get_global_id(0);
    if (cg >= C * N) return; /* no barrier in this kernel */
    const int c = cg / N, g = cg - c * N;
    __global const REAL *vm = viewmats + 16 * c;
    __global const REAL *K = Ks + 9 * c;

    radii[2 * cg] = 0;
    radii[2 * cg + 1] = 0;
    rects[4 * cg] = rects[4 * cg + 1] = rects[4 * cg + 2] = rects[4 * cg + 3] = 0;

    const REAL3 m = (REAL3)(means[3 * g], means[3 * g + 1], means[3 * g + 2]);
    const REAL3 p = (REAL3)(vm[0] * m.x + vm[1] * m.y + vm[2] * m.z + vm[3],
                            vm[4] * m.x + vm[5] * m.y + vm[6] * m.z + vm[7],
                            vm[8] * m.x + vm[9] * m.y + vm[10] * m.z + vm[11]);
    depths[cg] = p.z;
    if (!(p.z >= near_plane && p.z <= far_plane)) return;

    /* World covariance M M^T with M = R S. */
    REAL Rq[9];
    quat_to_rotmat((REAL4)(quats[4 * g], quats[4 * g + 1], quats[4 * g + 2], quats[4 * g + 3]), Rq);
    const REAL s0 = scales[3 * g], s1 = scales[3 * g + 1], s2 = scales[3 * g + 2];
    REAL M[9] = {Rq[0] * s0, Rq[1] * s1, Rq[2] * s2,
                 Rq[3] * s0, Rq[4] * s1, Rq[5] * s2,
                 Rq[6] * s0, Rq[7] * s1, Rq[8] * s2};
    /* Camera-frame M: Rv M, so the camera covariance is (Rv M)(Rv M)^T. Forming the product
     * before squaring keeps needle Gaussians symmetric positive semi-definite. */
    REAL V[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            V[3 * i + j] = vm[4 * i] * M[j] + vm[4 * i + 1] * M[3 + j] + vm[4 * i + 2] * M[6 + j];

    const REAL fx = K[0], fy = K[4], cx = K[2], cy = K[5];
    const REAL tan_fovx = (REAL)0.5 * width / fx, tan_fovy = (REAL)0.5 * height / fy;
    const REAL lim_xp = (width - cx) / fx + (REAL)CLS_FRUSTUM_MARGIN * tan_fovx;
    const REAL lim_xn = cx / fx + (REAL)CLS_FRUSTUM_MARGIN * tan_fovx;
    const REAL lim_yp = (height - cy) / fy + (REAL)CLS_FRUSTUM_MARGIN * tan_fovy;
    const REAL lim_yn = cy / fy + (REAL)CLS_FRUSTUM_MARGIN * tan_fovy;
    const REAL rz = 1 / p.z;
    const REAL tx = p.z * fmin(lim_xp, fmax(-lim_xn, p.x * rz));
    const REAL ty = p.z * fmin(lim_yp, fmax(-lim_yn, p.y * rz));
    /* J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]]; T = J V is 2x3. */
    const REAL j00 = fx * rz, j02 = -fx * tx * rz * rz, j11 = fy * rz, j12 = -fy * ty * rz * rz;
    REAL T0[3], T1[3];
    for (int j = 0; j < 3; ++j) {
        T0[j] = j00 * V[j] + j02 * V[6 + j];
        T1[j] = j11 * V[3 + j] + j12 * V[6 + j];
    }
    REAL a = T0[0] * T0[0] + T0[1] * T0[1] + T0[2] * T0[2];
    const REAL b = T0[0] * T1[0] + T0[1] * T1[1] + T0[2] * T1[2];
    REAL d = T1[0] * T1[0] + T1[1] * T1[1] + T1[2] * T1[2];
    const REAL det_orig = a * d - b * b;
    a += eps2d;
    d += eps2d;
    const REAL det = a * d - b * b;
    if (!(det > 0)) return;
    const REAL inv_det = 1 / det;

    REAL op = opacities[g];
#if ANTIALIASED
    op *= sqrt(fmax((REAL)0, det_orig * inv_det));
#endif
#if OPACITY_AWARE_RADIUS
    /* Beyond this many sigmas the sample falls below ALPHA_MIN and would be skipped anyway. */
    if (!(op >= (REAL)ALPHA_MIN)) return;
    const REAL extent = sqrt(2 * log(op / (REAL)ALPHA_MIN));
#else
    const REAL extent = (REAL)RADIUS_SIGMA;
#endif
    /* Radii are capped so a near-plane giant cannot overflow int; any cap above the image
     * size culls and bins identically. */
    const REAL rcap = (REAL)(1 << 30);
    const REAL rxf = fmin(ceil(extent * sqrt(a)), rcap), ryf = fmin(ceil(extent * sqrt(d)), rcap);
    if (rxf <= radius_clip && ryf <= radius_clip) return;

    const REAL2 xy = (REAL2)(fx * p.x * rz + cx, fy * p.y * rz + cy);
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
    const REAL cut = log(op / (REAL)ALPHA_MIN);
    extents[2 * cg] = cut >= 0 ? sqrt(2 * cut * a) : (REAL)-1;
    extents[2 * cg + 1] = cut >= 0 ? sqrt(2 * cut * d) : (REAL)-1;
    rects[4 * cg] = rect.x;
    rects[4 * cg + 1] = rect.y;
    rects[4 * cg + 2] = rect.z;
    rects[4 * cg + 3] = rect.w;
}
