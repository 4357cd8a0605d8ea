/* reduce.cl — per (camera, Gaussian) sum of its intersection slots, in tile order.
 *
 * composite_bwd wrote one slot of G values per (pair, tile); a pair's slots are contiguous
 * (isect_offsets[cg] onwards, one per tile of its rectangle), so the sum is a short loop in
 * a fixed order: deterministic without float atomics.
 * Outputs follow the slot layout: geometry gradients (v_means2d, v_conics, v_opacity,
 * absgrad) and feature gradients, each only when built in (GEOM_GRAD, COLOR_GRAD, ABSGRAD).
 *
 * Build parameters: REAL_DOUBLE, CHANNELS, GEOM_GRAD, COLOR_GRAD, ABSGRAD.
 */

/* G_GEOM: common.h, the slot layout the backward compositors write */
#define G (G_GEOM + (COLOR_GRAD ? CHANNELS : 0))

__kernel void reduce_slots(const int CN,
                           __global const int *rects,          /* [C, N, 4] */
                           __global const int *isect_offsets,  /* [C * N] */
                           __global const REAL *slots,         /* [M, G] */
                           __global REAL *v_means2d,           /* [C, N, 2] */
                           __global REAL *v_conics,            /* [C, N, 3] */
                           __global REAL *v_opac,              /* [C, N] */
                           __global REAL *absgrad,             /* [C, N, 2] */
                           __global REAL *v_feats)             /* [C, N, CHANNELS] */
{
    const int cg = get_global_id(0);
    if (cg >= CN) return;
    /* scalar loads: vload4 is an out-of-line call on PoCL's CPU device (common.h: pair_slot) */
    const int n = (rects[4 * cg + 2] - rects[4 * cg]) * (rects[4 * cg + 3] - rects[4 * cg + 1]);
    __global const REAL *s = slots + (size_t)isect_offsets[cg] * G;
    /* One column at a time, summed in tile order: no private array, so any G fits. */
    for (int j = 0; j < G; ++j) {
        REAL acc = 0;
        for (int i = 0; i < n; ++i) acc += s[(size_t)i * G + j];
#if GEOM_GRAD
        if (j < 2) v_means2d[2 * cg + j] = acc;
        else if (j < 5) v_conics[3 * cg + j - 2] = acc;
        else if (j == 5) v_opac[cg] = acc;
        else if (j < G_GEOM) absgrad[2 * cg + j - 6] = acc;
        else
#endif
            v_feats[(size_t)cg * CHANNELS + j - G_GEOM] = acc;
    }
}
