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
 * Two builds of one kernel (RenderConfig.composite_impl), chosen by CLS_TUNED; the per-sample
 * arithmetic (sigma, alpha, the tests, the blend) is written once, so the two give the same
 * outputs bit for bit:
 *  - CLS_TUNED=0 ("baseline", the GPU default): a batch is staged as array-of-structures and
 *    an item tests each sample's extent against its row segment before the exp;
 *  - CLS_TUNED=1 ("tuned", the CPU default): a batch is staged as structure-of-arrays, and an
 *    item tests the extents of CLS_WORD samples at once (vector compares into a bit mask),
 *    then visits only the samples its row segment can see, in order, instead of a
 *    hard-to-predict branch per sample, and skips the exp where sigma exceeds a safe bound
 *    on every lane (common.h: l_sm); on PoCL's CPU device (CLS_POCL_CPU) the maths is inline
 *    (see common.h: there the library builtins are out-of-line calls that spill every vector
 *    register) and the next batch's samples are prefetched while this one is composited.
 *
 * Channels are composited CCHUNK at a time (gsplat's channel_chunk): one launch per chunk,
 * from channel ch0 on, so private and local memory stay bounded for any number of channels.
 * Every launch makes the same decisions; the first (ch0 = 0) writes T and the last index.
 *
 * CLS_COUNT=1 (the bench's counted flops, clsplat.stages.composite(counts=...); off in
 * production, where the counting compiles to nothing): each item adds, over the launches, to
 * counts[item][0..3] the samples it tested against its row segment's extent (the tuned build:
 * whole words of them), those past the extent test, those past the sigma bound (the baseline
 * build has none: as many as past the extent test) and those past the alpha test (some lane
 * valid, so the blend ran), where item = tile * GROUP + its local id.
 *
 * Build parameters: CLS_TUNED (default 1), REAL_DOUBLE, TILE, PIX, BATCH, CHANNELS,
 * CCHUNK, SAVE_LAST, ALPHA_MIN, ALPHA_MAX, T_MIN, CLS_POCL_CPU, CLS_COUNT (default 0).
 */

#ifndef CLS_COUNT
#define CLS_COUNT 0
#endif
#if CLS_COUNT
#define COUNT(j, n) (n_count[j] += (uint)(n))
#else
#define COUNT(j, n) ((void)0)
#endif
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
#if CLS_COUNT
                   , __global uint *counts           /* [C * tiles_per_cam * GROUP, 4] */
#endif
) {
#if CLS_TUNED
    /* Vector-typed, so that extent_bits may load them as vectors (alignment). */
    __local MVREAL l_xv[NPAD / CLS_MV], l_yv[NPAD / CLS_MV], l_bxv[NPAD / CLS_MV], l_byv[NPAD / CLS_MV];
    __local REAL l_ca[BATCH], l_cb[BATCH], l_cc[BATCH], l_op[BATCH], l_sm[BATCH];
    __local REAL *l_x = (__local REAL *)l_xv, *l_y = (__local REAL *)l_yv;
    __local REAL *l_bx = (__local REAL *)l_bxv, *l_by = (__local REAL *)l_byv;
#else
    __local REAL l_xy[2 * BATCH], l_conic[3 * BATCH], l_op[BATCH], l_ext[2 * BATCH];
#endif
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
#if CLS_TUNED
    const REAL px_first = (REAL)px0 + (REAL)CLS_PIXEL_CENTRE;
    const REAL px_last = (REAL)(px0 + PIX - 1) + (REAL)CLS_PIXEL_CENTRE;
#endif
    const VMASK inside = (xs < (REAL)width) && (py < height);
    VMASK done = !inside;

    VREAL T = (VREAL)1;
    VREAL acc[CCHUNK];
#if CLS_TUNED
#pragma unroll
#endif
    for (int ch = 0; ch < CCHUNK; ++ch) acc[ch] = (VREAL)0;
    VMASK last = (VMASK)0;
#if CLS_COUNT
    uint n_count[4] = {0, 0, 0, 0}; /* tested, past the extent test, the sigma bound, the alpha test */
#endif

    const int start = tile_offsets[tile], end = tile_offsets[tile + 1];
    for (int b0 = start; b0 < end; b0 += BATCH) {
        /* Group-wide early stop without work-group collectives: count finished items. */
        barrier(CLK_LOCAL_MEM_FENCE);
        if (lid == 0) n_done = 0;
        barrier(CLK_LOCAL_MEM_FENCE);
        if (CLS_VALL(done)) atomic_inc(&n_done);
        barrier(CLK_LOCAL_MEM_FENCE);
        if (n_done == GROUP) break;

        const int nb = min(BATCH, end - b0);
#if CLS_TUNED
        const int n_words = (nb + CLS_WORD - 1) / CLS_WORD;
        for (int i = lid; i < n_words * CLS_WORD; i += GROUP) {
            if (i < nb) {
                const uint cg = key_id(keys[b0 + i]);
                stage_sample_soa(i, cg, means2d, conics, opac_cg, extents, feats, l_x, l_y, l_ca,
                                 l_cb, l_cc, l_op, l_sm, l_bx, l_by, l_f, ch0, CCHUNK);
            } else {
                pad_sample_soa(i, l_x, l_y, l_bx, l_by);
            }
        }
#else
        for (int i = lid; i < nb; i += GROUP) {
            const uint cg = key_id(keys[b0 + i]);
            stage_sample(i, cg, means2d, conics, opac_cg, extents, feats, l_xy, l_conic, l_op, l_ext, l_f,
                         ch0, CCHUNK);
        }
#endif
        barrier(CLK_LOCAL_MEM_FENCE);
#if CLS_PREFETCH
        for (int i = b0 + BATCH + lid; i < min(b0 + 2 * BATCH, end); i += GROUP)
            prefetch_sample(key_id(keys[i]), means2d, conics, opac_cg, extents, feats, ch0, CCHUNK);
#endif

        /* The samples k of the batch this item's row segment may see, in order (both
         * variants open two blocks here, closed after the per-sample code). */
#if CLS_TUNED
        for (int w0 = 0; w0 < nb; w0 += CLS_WORD) {
            if (CLS_VALL(done)) break;
            COUNT(0, min(CLS_WORD, nb - w0));
            uint seen = extent_bits(w0, l_x, l_y, l_bx, l_by, px_first, px_last, pyc);
            while (seen != 0) {
                if (CLS_VALL(done)) break;
                const int k = w0 + CLS_CTZ(seen);
                seen &= seen - 1;
#else
        for (int k = 0; k < nb; ++k) {
            {
                if (CLS_VALL(done)) break;
                COUNT(0, 1);
                /* Most samples of a tile miss a given row segment: reject them before the exp. */
                if (outside_extent(l_xy[2 * k], l_xy[2 * k + 1], l_ext[2 * k], l_ext[2 * k + 1],
                                   (REAL)px0 + (REAL)CLS_PIXEL_CENTRE,
                                   (REAL)(px0 + PIX - 1) + (REAL)CLS_PIXEL_CENTRE, pyc))
                    continue;
#endif
                /* ---- one sample against this item's PIX pixels ---- */
                COUNT(1, 1);
                const VREAL dx = S_X(k) - pxc;
                const REAL dy = S_Y(k) - pyc;
                const VREAL sigma = (REAL)0.5 * (S_CA(k) * dx * dx + S_CC(k) * dy * dy) + S_CB(k) * dx * dy;
#if CLS_TUNED
                if (!CLS_VANY(sigma <= l_sm[k])) continue; /* alpha < ALPHA_MIN in every lane */
#endif
                COUNT(2, 1);
                const VREAL alpha = CLS_FMIN((VREAL)(REAL)ALPHA_MAX, l_op[k] * CLS_VEXP(-sigma));
                VMASK valid = !done && sigma >= (REAL)0 && alpha >= (REAL)ALPHA_MIN;
                if (!CLS_VANY(valid)) continue;
                COUNT(3, 1);
                const VREAL next_T = T * ((REAL)1 - alpha);
                const VMASK stop = valid && next_T <= (REAL)T_MIN;
                done = done || stop;
                valid = valid && !stop;
                const VREAL w = valid ? alpha * T : (VREAL)0;
#if CLS_TUNED
#pragma unroll /* so the accumulators can stay in registers */
#endif
                for (int ch = 0; ch < CCHUNK; ++ch) acc[ch] += l_f[CCHUNK * k + ch] * w;
                T = valid ? next_T : T;
                last = valid ? (VMASK)(b0 - start + k + 1) : last;
            }
        }
    }

#if CLS_COUNT
    for (int j = 0; j < 4; ++j) counts[(size_t)get_global_id(0) * 4 + j] += n_count[j];
#endif
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

#if CLS_INLINE_MATH && !REAL_DOUBLE && PIX > 1
/* The inline exp against the library's, lane by lane, as built here (same options): out[i] is
 * the XOR of their bit patterns at x[i], so all zeros means the inline exp is the library's on
 * these inputs. clsplat.stages.inline_exp_exact runs it once per device. */
__kernel void exp_probe(__global const REAL *x, __global uint *out) {
    const int i = get_global_id(0) * PIX;
    const VREAL v = CAT(vload, PIX)(0, x + i);
    const VREAL a = CLS_VEXP(v), b = exp(v);
    CAT(vstore, PIX)(CAT(as_, CAT(uint, PIX))(a) ^ CAT(as_, CAT(uint, PIX))(b), 0, out + i);
}
#endif
