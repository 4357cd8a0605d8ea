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

/* REDUCE_G, REDUCE_OUT_ARGS, reduce_pair: common.h, shared with composite_bwd_gauss.cl's
 * FUSED_REDUCE (the same sums, launched apart here for renders with many pairs) */
__kernel void reduce_slots(const int CN,
                           __global const int *rects,          /* [C, N, 4] */
                           __global const int *isect_offsets,  /* [C * N] */
                           __global const REAL *slots,         /* [M, REDUCE_G] */
                           REDUCE_OUT_ARGS)
{
    const int cg = get_global_id(0);
    if (cg >= CN) return;
    reduce_pair(cg, rects, isect_offsets, slots, v_means2d, v_conics, v_opac, absgrad, v_feats);
}
