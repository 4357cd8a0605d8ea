/* sh.cl — stage 2: view-dependent colour from spherical harmonics.
 *
 * One work-item per (camera, Gaussian). The degree is a build constant (SH_DEGREE), so a
 * degree-0 scene never evaluates a higher band. Culled pairs are skipped.
 * colour = max(SH(normalise(mean - camera centre)) + 0.5, 0).
 *
 * Build parameters: REAL_DOUBLE, SH_DEGREE, SH_COEFFS (stored per Gaussian, >= basis length).
 */

__kernel void sh_colors(const int C, const int N,
                        __global const REAL *means,    /* [N, 3] */
                        __global const REAL *viewmats, /* [C, 4, 4] */
                        __global const REAL *coeffs,   /* [N, SH_COEFFS, 3] */
                        __global const int *radii,     /* [C, N, 2] */
                        __global REAL *colors)         /* [C, N, 3] */
{
    const int cg = get_global_id(0);
    if (cg >= C * N) return;
    if (radii[2 * cg] == 0 && radii[2 * cg + 1] == 0) { /* culled: zeros (no host fill) */
        colors[(size_t)cg * 3] = colors[(size_t)cg * 3 + 1] = colors[(size_t)cg * 3 + 2] = 0;
        return;
    }
    const int c = cg / N, g = cg - c * N;
    const REAL3 dir = normalize((REAL3)(means[3 * g], means[3 * g + 1], means[3 * g + 2]) -
                                camera_centre(viewmats + 16 * c));
    REAL b[SH_BASIS_LEN];
    sh_basis(dir, b);
    __global const REAL *k = coeffs + (size_t)g * SH_COEFFS * 3;
    for (int ch = 0; ch < 3; ++ch) {
        REAL acc = 0;
        for (int i = 0; i < SH_BASIS_LEN; ++i) acc += b[i] * k[3 * i + ch];
        colors[(size_t)cg * 3 + ch] = fmax(acc + (REAL)0.5, (REAL)0);
    }
}
