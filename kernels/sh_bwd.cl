/* sh_bwd.cl — backward of sh_colors: to the SH coefficients and, through the view
 * direction, to the means.
 *
 * One work-item per Gaussian, looping over cameras in order, so the sum over cameras is
 * fixed and no atomics are needed. The colour clamp max(x + 0.5, 0) passes no gradient where
 * it is active. With DIR_GRAD each pair's gradient of its unnormalised view direction is
 * stored too: the host turns it into the view matrices' gradient through the camera centre.
 *
 * Build parameters: REAL_DOUBLE, SH_DEGREE, SH_COEFFS, MEANS_GRAD, DIR_GRAD.
 */

/* v_d += sum_i v_b[i] d b_i / d d for the basis of common.h, at the unit direction d. */
inline REAL3 sh_basis_vjp(REAL3 d, const REAL *vb) {
    REAL3 g = (REAL3)(0, 0, 0);
#if SH_DEGREE >= 1
    const REAL C1 = (REAL)0.48860251190292;
    g += (REAL3)(-C1 * vb[3], -C1 * vb[1], C1 * vb[2]);
#endif
#if SH_DEGREE >= 2
    const REAL C2 = (REAL)1.092548430592079, C4 = (REAL)0.5462742152960395, C11 = (REAL)0.9461746957575601;
    const REAL x = d.x, y = d.y, z = d.z;
    g += vb[4] * (REAL3)(2 * C4 * y, 2 * C4 * x, 0);
    g += vb[5] * (REAL3)(0, -C2 * z, -C2 * y);
    g += vb[6] * (REAL3)(0, 0, 2 * C11 * z);
    g += vb[7] * (REAL3)(-C2 * z, 0, -C2 * x);
    g += vb[8] * (REAL3)(2 * C4 * x, -2 * C4 * y, 0);
#endif
#if SH_DEGREE >= 3
    const REAL C5 = (REAL)2.285228997322329, C6 = (REAL)0.4570457994644658, C7 = (REAL)1.445305721320277;
    const REAL C8 = (REAL)1.865881662950577, C9 = (REAL)1.119528997770346, C10 = (REAL)0.5900435899266435;
    const REAL t0 = -C5 * z * z + C6;
    g += vb[9] * (REAL3)(-6 * C10 * x * y, -3 * C10 * (x * x - y * y), 0);
    g += vb[10] * (REAL3)(2 * C7 * z * y, 2 * C7 * z * x, 2 * C7 * x * y);
    g += vb[11] * (REAL3)(0, t0, -2 * C5 * z * y);
    g += vb[12] * (REAL3)(0, 0, 3 * C8 * z * z - C9);
    g += vb[13] * (REAL3)(t0, 0, -2 * C5 * z * x);
    g += vb[14] * (REAL3)(2 * C7 * z * x, -2 * C7 * z * y, C7 * (x * x - y * y));
    g += vb[15] * (REAL3)(-3 * C10 * (x * x - y * y), 6 * C10 * x * y, 0);
#endif
#if SH_DEGREE >= 4
    {
        const REAL K1 = (REAL)0.6258357354491763, K2 = (REAL)1.770130769779931;
        const REAL K3 = (REAL)3.31161143515146, K4 = (REAL)0.47308734787878;
        const REAL K5 = (REAL)4.683325804901025, K6 = (REAL)2.007139630671868;
        const REAL K7 = (REAL)1.984313483298443, K8 = (REAL)1.006230589874905;
        const REAL x2 = x * x, y2 = y * y, z2 = z * z;
        const REAL c1 = x2 - y2, s1 = 2 * x * y;
        const REAL c2 = x * c1 - y * s1, s2 = x * s1 + y * c1;
        /* gradients of the planar harmonics c_k + i s_k = (x + i y)^k */
        const REAL3 dc1 = (REAL3)(2 * x, -2 * y, 0), ds1 = (REAL3)(2 * y, 2 * x, 0);
        const REAL3 dc2 = (REAL3)(3 * c1, -3 * s1, 0), ds2 = (REAL3)(3 * s1, 3 * c1, 0);
        const REAL3 dc3 = (REAL3)(4 * c2, -4 * s2, 0), ds3 = (REAL3)(4 * s2, 4 * c2, 0);
        const REAL t = z * (-K5 * z2 + K6), dt = -3 * K5 * z2 + K6;   /* b19 = t y, b21 = t x */
        const REAL u = K3 * z2 - K4, du = 2 * K3 * z;                  /* b18 = u s1, b22 = u c1 */
        const REAL b12 = z * (C8 * z2 - C9), db12 = 3 * C8 * z2 - C9;
        const REAL db6 = 2 * C11 * z;
        g += vb[16] * K1 * ds3;
        g += vb[17] * -K2 * (z * ds2 + (REAL3)(0, 0, s2));
        g += vb[18] * (u * ds1 + (REAL3)(0, 0, du * s1));
        g += vb[19] * (REAL3)(0, t, dt * y);
        g += vb[20] * (REAL3)(0, 0, K7 * (b12 + z * db12) - K8 * db6);
        g += vb[21] * (REAL3)(t, 0, dt * x);
        g += vb[22] * (u * dc1 + (REAL3)(0, 0, du * c1));
        g += vb[23] * -K2 * (z * dc2 + (REAL3)(0, 0, c2));
        g += vb[24] * K1 * dc3;
    }
#endif
    return g;
}

__kernel void sh_colors_bwd(const int C, const int N,
                            __global const REAL *means,    /* [N, 3] */
                            __global const REAL *viewmats, /* [C, 4, 4] */
                            __global const REAL *coeffs,   /* [N, SH_COEFFS, 3] */
                            __global const int *radii,     /* [C, N, 2] */
                            __global const REAL *colors,   /* [C, N, 3] the forward's */
                            __global const REAL *v_colors, /* [C, N, 3] */
                            __global REAL *v_coeffs,       /* [N, SH_COEFFS, 3] */
                            __global REAL *v_means,        /* [N, 3] */
                            __global REAL *v_dirs)         /* [C, N, 3] (DIR_GRAD) */
{
    const int g = get_global_id(0);
    if (g >= N) return;
    __global const REAL *k = coeffs + (size_t)g * SH_COEFFS * 3;
    REAL vk[SH_BASIS_LEN * 3];
    for (int i = 0; i < SH_BASIS_LEN * 3; ++i) vk[i] = 0;
    REAL3 vm = (REAL3)(0, 0, 0);
    const REAL3 m = (REAL3)(means[3 * g], means[3 * g + 1], means[3 * g + 2]);
    for (int c = 0; c < C; ++c) {
        const size_t cg = (size_t)c * N + g;
        if (radii[2 * cg] == 0 && radii[2 * cg + 1] == 0) continue;
        const REAL3 raw = m - camera_centre(viewmats + 16 * c);
        const REAL inv_len = rsqrt(dot(raw, raw));
        const REAL3 d = raw * inv_len;
        REAL b[SH_BASIS_LEN], vb[SH_BASIS_LEN];
        sh_basis(d, b);
        /* the forward's colour max(x + 0.5, 0) is > 0 exactly where the clamp is inactive:
         * reading it saves evaluating the SH sum again (the same mask, bit for bit) */
        REAL vc[3];
        for (int ch = 0; ch < 3; ++ch) vc[ch] = colors[3 * cg + ch] > 0 ? v_colors[3 * cg + ch] : (REAL)0;
        for (int i = 0; i < SH_BASIS_LEN; ++i) {
            vb[i] = 0;
            for (int ch = 0; ch < 3; ++ch) {
                vk[3 * i + ch] += b[i] * vc[ch];
                vb[i] += k[3 * i + ch] * vc[ch];
            }
        }
#if MEANS_GRAD || DIR_GRAD
        const REAL3 vd = sh_basis_vjp(d, vb);
        const REAL3 vraw = (vd - d * dot(d, vd)) * inv_len; /* through the normalisation */
        vm += vraw;
#if DIR_GRAD
        vstore3(vraw, cg, v_dirs);
#endif
#endif
    }
    __global REAL *out = v_coeffs + (size_t)g * SH_COEFFS * 3;
    for (int i = 0; i < SH_COEFFS * 3; ++i) out[i] = i < SH_BASIS_LEN * 3 ? vk[i] : (REAL)0;
#if MEANS_GRAD
    v_means[3 * g] = vm.x;
    v_means[3 * g + 1] = vm.y;
    v_means[3 * g + 2] = vm.z;
#endif
}
