/* composite.cl — stage 6: front-to-back alpha compositing, one work-group per tile.
 *
 * Each work-item owns PIX adjacent pixels of one tile row. The group walks its tile's sorted
 * segment in batches staged in local memory and stops early once every pixel is done.
 * Per pixel: alpha_i = min(ALPHA_MAX, o_i exp(-sigma_i)); samples with sigma < 0 or
 * alpha < ALPHA_MIN are skipped; the pixel stops before the sample whose next transmittance
 * would fall to T_MIN or below (that sample is not composited).
 * Outputs: sum_i f_i alpha_i T_i per channel, the final T (alpha = 1 - T; the background is
 * added by the host), and with SAVE_LAST the 1-based segment position of the last sample
 * composited, which bounds the backward pass.
 *
 * Channels are composited CCHUNK at a time (gsplat's channel_chunk): one launch per chunk,
 * from channel ch0 on, so private and local memory stay bounded for any number of channels.
 * Every launch makes the same decisions; the first (ch0 = 0) writes T and the last index.
 *
 * Build parameters: REAL_DOUBLE, TILE, PIX, BATCH, CHANNELS (features per Gaussian and
 * pixel), CCHUNK (channels per launch), SAVE_LAST, ALPHA_MIN, ALPHA_MAX, T_MIN.
 */

#define GROUP (TILE * TILE / PIX)
#define ITEMS_PER_ROW (TILE / PIX)

__kernel __attribute__((reqd_work_group_size(GROUP, 1, 1)))
void composite_fwd(const int width, const int height, const int tiles_x, const int tiles_per_cam,
                   const int ch0,                    /* first channel of this launch */
                   __global const int *tile_offsets, /* [C * tiles_per_cam + 1] */
                   __global const ulong *keys,       /* [M] sorted per segment */
                   __global const REAL *means2d,     /* [C, N, 2] */
                   __global const REAL *conics,      /* [C, N, 3] */
                   __global const REAL *opac_cg,     /* [C, N] */
                   __global const REAL *extents,     /* [C, N, 2] */
                   __global const REAL *feats,       /* [C, N, CHANNELS] */
                   __global REAL *out_feats,         /* [C, H, W, CHANNELS] */
                   __global REAL *out_T              /* [C, H, W] */
#if SAVE_LAST
                   , __global int *out_last          /* [C, H, W] */
#endif
) {
    __local REAL l_xy[2 * BATCH], l_conic[3 * BATCH], l_op[BATCH], l_ext[2 * BATCH];
    __local REAL l_f[CCHUNK * BATCH];
    __local int n_done;

    const int tile = get_group_id(0), lid = get_local_id(0);
    const int c = tile / tiles_per_cam, t = tile - c * tiles_per_cam;
    const int ty = t / tiles_x, tx = t - ty * tiles_x;
    const int row = lid / ITEMS_PER_ROW;
    const int py = ty * TILE + row, px0 = tx * TILE + (lid - row * ITEMS_PER_ROW) * PIX;
    const VREAL xs = (REAL)px0 + VRAMP;
    const VREAL pxc = xs + (REAL)CLS_PIXEL_CENTRE;
    const REAL pyc = (REAL)py + (REAL)CLS_PIXEL_CENTRE;
    const VMASK inside = (xs < (REAL)width) && (py < height);
    VMASK done = !inside;

    VREAL T = (VREAL)1;
    VREAL acc[CCHUNK];
    for (int ch = 0; ch < CCHUNK; ++ch) acc[ch] = (VREAL)0;
    VMASK last = (VMASK)0;

    const int start = tile_offsets[tile], end = tile_offsets[tile + 1];
    for (int b0 = start; b0 < end; b0 += BATCH) {
        /* Group-wide early stop without work-group collectives: count finished items. */
        barrier(CLK_LOCAL_MEM_FENCE);
        if (lid == 0) n_done = 0;
        barrier(CLK_LOCAL_MEM_FENCE);
        if (VALL(done)) atomic_inc(&n_done);
        barrier(CLK_LOCAL_MEM_FENCE);
        if (n_done == GROUP) break;

        const int nb = min(BATCH, end - b0);
        for (int i = lid; i < nb; i += GROUP) {
            const uint cg = key_id(keys[b0 + i]);
            stage_sample(i, cg, means2d, conics, opac_cg, extents, feats, l_xy, l_conic, l_op, l_ext, l_f,
                         ch0, CCHUNK);
        }
        barrier(CLK_LOCAL_MEM_FENCE);

        for (int k = 0; k < nb; ++k) {
            if (VALL(done)) break;
            /* Most samples of a tile miss a given row segment: reject them before the exp. */
            if (outside_extent(l_xy[2 * k], l_xy[2 * k + 1], l_ext[2 * k], l_ext[2 * k + 1],
                               (REAL)px0 + (REAL)CLS_PIXEL_CENTRE,
                               (REAL)(px0 + PIX - 1) + (REAL)CLS_PIXEL_CENTRE, pyc))
                continue;
            const VREAL dx = l_xy[2 * k] - pxc;
            const REAL dy = l_xy[2 * k + 1] - pyc;
            const VREAL sigma = (REAL)0.5 * (l_conic[3 * k] * dx * dx + l_conic[3 * k + 2] * dy * dy) +
                                l_conic[3 * k + 1] * dx * dy;
            const VREAL alpha = fmin((VREAL)(REAL)ALPHA_MAX, l_op[k] * exp(-sigma));
            VMASK valid = !done && sigma >= (REAL)0 && alpha >= (REAL)ALPHA_MIN;
            if (!VANY(valid)) continue;
            const VREAL next_T = T * ((REAL)1 - alpha);
            const VMASK stop = valid && next_T <= (REAL)T_MIN;
            done = done || stop;
            valid = valid && !stop;
            const VREAL w = valid ? alpha * T : (VREAL)0;
            for (int ch = 0; ch < CCHUNK; ++ch) acc[ch] += l_f[CCHUNK * k + ch] * w;
            T = valid ? next_T : T;
            last = valid ? (VMASK)(b0 - start + k + 1) : last;
        }
    }

    REAL T_l[PIX], acc_l[PIX * CCHUNK];
    VSTORE(T, T_l);
    for (int ch = 0; ch < CCHUNK; ++ch) VSTORE(acc[ch], acc_l + PIX * ch);
#if SAVE_LAST
    MASK_SCALAR last_l[PIX];
    VSTORE(last, last_l);
#endif
    for (int q = 0; q < PIX; ++q) {
        const int px = px0 + q;
        if (px >= width || py >= height) continue;
        const size_t pix = ((size_t)c * height + py) * width + px;
        for (int ch = 0; ch < CCHUNK && ch0 + ch < CHANNELS; ++ch)
            out_feats[pix * CHANNELS + ch0 + ch] = acc_l[PIX * ch + q];
        if (ch0 == 0) {
            out_T[pix] = T_l[q];
#if SAVE_LAST
            out_last[pix] = (int)last_l[q];
#endif
        }
    }
}
