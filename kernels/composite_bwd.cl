/* composite_bwd.cl — backward of compositing: per-intersection gradient slots.
 *
 * One work-group per tile, the forward's pixel layout. For every sample a pixel composited,
 * with w_i = alpha_i T_i, out = sum_i f_i w_i and T_final = prod_i (1 - alpha_i):
 *   d out / d f_i       = w_i
 *   d out / d alpha_i   = T_i f_i - S_i / (1 - alpha_i),   S_i = sum_{j > i} f_j w_j
 *   d T_final / d alpha_i = -T_final / (1 - alpha_i)
 * and alpha_i = o_i exp(-sigma_i) unless the ALPHA_MAX clamp was active, in which case no
 * gradient reaches o_i or sigma_i. Samples the forward skipped (alpha < ALPHA_MIN, sigma < 0)
 * or never reached (past the pixel's last contributor) get none either: the forward's
 * decisions are replayed exactly, with the same arithmetic.
 *
 * Only the dot products with the pixel's v_out enter d loss / d alpha_i: with
 * A_i = f_i . v_out and B_i = S_i . v_out = sum_{j > i} w_j A_j,
 *   d loss / d alpha_i = T_i A_i - (B_i + v_T T_final) / (1 - alpha_i),
 * so each pixel carries one running scalar B, not one per channel.
 *
 * T_i is recovered in one of two ways (BWD_DIVIDE):
 *   0 (replay, default): walk front to back as the forward did, so T_i is the forward's own
 *     running product and B_i = out . v_out - sum_{j <= i} w_j A_j. No division by 1 - alpha.
 *   1 (divide): walk back to front from T_final with T_i = T_{i+1} / (1 - alpha_i),
 *     accumulating B_i. Rounding grows with every division through an opaque stack.
 *
 * Channel chunks (gsplat's channel_chunk): a launch writes the colour gradients of CCHUNK
 * channels from ch0 on; the geometry gradients (GEOM_GRAD, first launch only) need A_i over
 * all CHANNELS, which come from local memory when they fit in one chunk and from global
 * memory otherwise (WIDE), so local and private memory stay bounded for any channel count.
 *
 * The pixel sums of each sample's gradient are reduced inside the group in a fixed order and
 * written to that intersection's slot; no float atomics, so results are bitwise reproducible.
 * The partials of a batch are summed over the group's items in item order. With WAVES > 1
 * (large groups, e.g. 32x32 tiles at one pixel per item) each item keeps its partials in
 * private memory and the items hand them over in WAVES waves of GROUP / WAVES, so local
 * memory holds one wave; the sums, and so the results, are the same as with one wave.
 *
 * Two builds of one kernel (RenderConfig.composite_impl), chosen by CLS_TUNED, as in
 * composite.cl; the per-sample gradient arithmetic is written once, and every sum runs in the
 * same order, so the two give the same slots bit for bit:
 *  - CLS_TUNED=0 ("baseline", the GPU default): array-of-structures staging, an extent test
 *    per sample, and partials laid out [sample][item][value];
 *  - CLS_TUNED=1 ("tuned", the CPU default): structure-of-arrays staging and the extent test a
 *    word of samples at a time (common.h: extent_bits); an item visits only the samples its
 *    row segment can see and that lie before its last contributor, and skips the exp where
 *    sigma exceeds a safe bound on every lane (common.h: l_sm); an item's partials of a batch
 *    are one contiguous block [sample][value], zeroed once per batch, so the group's sum over
 *    items reads CLS_MV consecutive values at once; on PoCL's CPU device (CLS_POCL_CPU) inline
 *    maths (see common.h) and the next batch's samples prefetched (replay order only: with
 *    BWD_DIVIDE the batches run back to front and nothing is prefetched).
 *
 * Slot layout (SLOT_G values): [geometry: v_xy(2) v_conic(3) v_opacity(1) (|v_xy|(2))]
 * [colour: v_feat(CHANNELS)], the colour block starting at column SLOT_COLOR0.
 *
 * Build parameters: CLS_TUNED (default 1), REAL_DOUBLE, TILE, PIX, BATCH, CHANNELS, CCHUNK,
 * GEOM_GRAD, COLOR_GRAD, ABSGRAD, BWD_DIVIDE, SLOT_G, SLOT_COLOR0, WAVES, ALPHA_MIN, ALPHA_MAX,
 * CLS_POCL_CPU.
 */


#define GROUP (TILE * TILE / PIX)
#define ITEMS_PER_ROW (TILE / PIX)
#define PG (G_GEOM + (COLOR_GRAD ? CCHUNK : 0)) /* partials per item and sample, this launch */
#if CLS_TUNED
/* Partials per item and batch, padded to whole vectors so the group sum can read CLS_MV
 * consecutive values (of consecutive samples and values) as one vector. */
#define PB ((BATCH * PG + CLS_MV - 1) / CLS_MV * CLS_MV)
#endif
#define WAVE (GROUP / WAVES)

__kernel __attribute__((reqd_work_group_size(GROUP, 1, 1)))
void composite_bwd(COMPOSITE_BWD_ARGS)
{
#if CLS_TUNED
    __local MVREAL l_xv[NPAD / CLS_MV], l_yv[NPAD / CLS_MV], l_bxv[NPAD / CLS_MV], l_byv[NPAD / CLS_MV];
    __local REAL l_ca[BATCH], l_cb[BATCH], l_cc[BATCH], l_op[BATCH], l_sm[BATCH];
#else
    __local REAL l_xy[2 * BATCH], l_conic[3 * BATCH], l_op[BATCH], l_ext[2 * BATCH];
#endif
    __local REAL l_f[(WIDE ? 1 : CCHUNK) * BATCH];
    __local int l_slot[BATCH];
    __local uint l_cg[BATCH];
#if CLS_TUNED
    __local MVREAL partv[WAVE * PB / CLS_MV]; /* [item of the wave][sample][value] */
#if WAVES > 1
    __local MVREAL l_accv[PB / CLS_MV];
    REAL my_p[PB];
#endif
#else
    __local REAL part[BATCH * WAVE * PG]; /* [sample][item of the wave][value] */
#if WAVES > 1
    __local REAL l_acc[BATCH * PG];
    REAL my_p[BATCH * PG];
#endif
#endif
    __local int l_max_last;
#if CLS_TUNED
    __local REAL *l_x = (__local REAL *)l_xv, *l_y = (__local REAL *)l_yv;
    __local REAL *l_bx = (__local REAL *)l_bxv, *l_by = (__local REAL *)l_byv;
    __local REAL *part = (__local REAL *)partv;
#endif

    const int tile = get_group_id(0), lid = get_local_id(0);
    const int c = tile / tiles_per_cam, t = tile - c * tiles_per_cam;
    const int ty = t / tiles_x, tx = t - ty * tiles_x;
    const int row = lid / ITEMS_PER_ROW;
    const int py = ty * TILE + row, px0 = tx * TILE + (lid - row * ITEMS_PER_ROW) * PIX;

    /* Per-lane state, gathered from the forward's per-pixel outputs. */
    REAL Tf_l[PIX], lastf_l[PIX], vT_l[PIX], B_l[PIX], vo_l[PIX * CCHUNK];
    size_t pix_l[PIX]; /* pixel index of each lane, or ~0 outside the image */
    int my_max = 0;
    for (int q = 0; q < PIX; ++q) {
        const int px = px0 + q;
        const int ok = px < width && py < height;
        const size_t pix = ((size_t)c * height + (ok ? py : 0)) * width + (ok ? px : 0);
        pix_l[q] = ok ? pix : ~(size_t)0;
        Tf_l[q] = ok ? out_T[pix] : (REAL)1;
        const int lst = ok ? out_last[pix] : 0;
        lastf_l[q] = (REAL)lst;
        my_max = max(my_max, lst);
        vT_l[q] = ok ? v_T[pix] : (REAL)0;
        REAL b = 0;
#if GEOM_GRAD && !BWD_DIVIDE
        for (int ch = 0; ch < CHANNELS && ok; ++ch) b += out_feats[pix * CHANNELS + ch] * v_out[pix * CHANNELS + ch];
#endif
        B_l[q] = b;
        for (int ch = 0; ch < CCHUNK; ++ch)
            vo_l[PIX * ch + q] = ok && ch0 + ch < CHANNELS ? v_out[pix * CHANNELS + ch0 + ch] : (REAL)0;
    }
#if PIX == 1
    const VREAL T_final = Tf_l[0], last = lastf_l[0], vT = vT_l[0];
    VREAL B = B_l[0];
#else
    const VREAL T_final = CAT(vload, PIX)(0, Tf_l), last = CAT(vload, PIX)(0, lastf_l);
    const VREAL vT = CAT(vload, PIX)(0, vT_l);
    VREAL B = CAT(vload, PIX)(0, B_l);
#endif
    VREAL vo[CCHUNK];
    for (int ch = 0; ch < CCHUNK; ++ch) {
#if PIX == 1
        vo[ch] = vo_l[ch];
#else
        vo[ch] = CAT(vload, PIX)(0, vo_l + PIX * ch);
#endif
    }
    const VREAL pxc = (REAL)px0 + VRAMP + (REAL)CLS_PIXEL_CENTRE;
    const REAL pyc = (REAL)py + (REAL)CLS_PIXEL_CENTRE;
#if CLS_TUNED
    const REAL px_first = (REAL)px0 + (REAL)CLS_PIXEL_CENTRE;
    const REAL px_last = (REAL)(px0 + PIX - 1) + (REAL)CLS_PIXEL_CENTRE;
#endif

    if (lid == 0) l_max_last = 0;
    barrier(CLK_LOCAL_MEM_FENCE);
    atomic_max(&l_max_last, my_max);
    barrier(CLK_LOCAL_MEM_FENCE);
    const int start = tile_offsets[tile];
    const int n_used = l_max_last; /* samples past every pixel's last contributor: no gradient */
    const int n_batches = (n_used + BATCH - 1) / BATCH;
#if BWD_DIVIDE
    VREAL T = T_final;
#else
    VREAL T = (VREAL)1;
#endif

    for (int bi = 0; bi < n_batches; ++bi) {
#if BWD_DIVIDE
        const int b0 = (n_batches - 1 - bi) * BATCH; /* back to front */
#else
        const int b0 = bi * BATCH;
#endif
        const int nb = min(BATCH, n_used - b0);
#if CLS_TUNED
        const int n_words = (nb + CLS_WORD - 1) / CLS_WORD;
#endif
        barrier(CLK_LOCAL_MEM_FENCE);
#if CLS_TUNED
        for (int i = lid; i < n_words * CLS_WORD; i += GROUP) {
            if (i < nb) {
                const uint cg = key_id(keys[start + b0 + i]);
                stage_sample_soa(i, cg, means2d, conics, opac_cg, extents, feats, l_x, l_y, l_ca, l_cb,
                                 l_cc, l_op, l_sm, l_bx, l_by, l_f, 0, (GEOM_GRAD && !WIDE) ? CCHUNK : 0);
                l_cg[i] = cg;
                l_slot[i] = pair_slot(cg, tx, ty, rects, isect_offsets); /* (common.h) */
            } else {
                pad_sample_soa(i, l_x, l_y, l_bx, l_by);
            }
        }
#else
        for (int i = lid; i < nb; i += GROUP) {
            const uint cg = key_id(keys[start + b0 + i]);
            stage_sample(i, cg, means2d, conics, opac_cg, extents, feats, l_xy, l_conic, l_op,
                         l_ext, l_f, 0, (GEOM_GRAD && !WIDE) ? CCHUNK : 0);
            l_cg[i] = cg;
            l_slot[i] = pair_slot(cg, tx, ty, rects, isect_offsets);
        }
#endif
        barrier(CLK_LOCAL_MEM_FENCE);

#if CLS_PREFETCH && !BWD_DIVIDE
        for (int i = start + b0 + BATCH + lid; i < start + min(b0 + 2 * BATCH, n_used); i += GROUP)
            prefetch_sample(key_id(keys[i]), means2d, conics, opac_cg, extents, feats, 0,
                            (GEOM_GRAD && !WIDE) ? CCHUNK : 0);
#endif
        /* The samples k of the batch this item's row segment may see, in the walk's order,
         * and ``my``, the item's PG partials of sample k (both variants open two blocks
         * here, closed after the per-sample code). */
#if CLS_TUNED
#if WAVES == 1
        __local REAL *mine = part + lid * PB;
#else
        REAL *mine = my_p;
#endif
        const int n_vec = (nb * PG + CLS_MV - 1) / CLS_MV; /* vectors of partials this batch */
        for (int i = 0; i < n_vec * CLS_MV; ++i) mine[i] = 0; /* samples not visited stay 0 */
        /* Samples from position my_max on lie past every lane's last contributor. */
        const int lim = min(nb, my_max - b0);
        for (int wi = 0; wi < (lim + CLS_WORD - 1) / CLS_WORD; ++wi) {
#if BWD_DIVIDE
            const int w0 = ((lim + CLS_WORD - 1) / CLS_WORD - 1 - wi) * CLS_WORD; /* back to front */
#else
            const int w0 = wi * CLS_WORD;
#endif
            uint seen = extent_bits(w0, l_x, l_y, l_bx, l_by, px_first, px_last, pyc);
            if (lim - w0 < CLS_WORD) seen &= (1u << (lim - w0)) - 1;
            while (seen != 0) {
#if BWD_DIVIDE
                const int bit = CLS_TOP_BIT(seen);
#else
                const int bit = CLS_CTZ(seen);
#endif
                seen &= ~(1u << bit);
                const int k = w0 + bit;
#if WAVES == 1
                __local REAL *my = mine + k * PG;
#else
                REAL *my = mine + k * PG;
#endif
#else
        for (int kk = 0; kk < nb; ++kk) {
            {
#if BWD_DIVIDE
                const int k = nb - 1 - kk;
#else
                const int k = kk;
#endif
#if WAVES == 1
                __local REAL *my = part + (k * GROUP + lid) * PG;
#else
                REAL *my = my_p + k * PG;
#endif
                for (int j = 0; j < PG; ++j) my[j] = 0;
                if (outside_extent(l_xy[2 * k], l_xy[2 * k + 1], l_ext[2 * k], l_ext[2 * k + 1],
                                   (REAL)px0 + (REAL)CLS_PIXEL_CENTRE,
                                   (REAL)(px0 + PIX - 1) + (REAL)CLS_PIXEL_CENTRE, pyc))
                    continue; /* the forward skipped it too */
#endif
                /* ---- one sample's gradients at this item's PIX pixels ---- */
                const REAL pos = (REAL)(b0 + k + 1);
                const VREAL dx = S_X(k) - pxc;
                const REAL dy = S_Y(k) - pyc;
                const REAL ca = S_CA(k), cb = S_CB(k), cc = S_CC(k);
                const VREAL sigma = (REAL)0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy;
#if CLS_TUNED
                if (!CLS_VANY(sigma <= l_sm[k])) continue; /* alpha < ALPHA_MIN in every lane */
#endif
                const VREAL g = CLS_VEXP(-sigma);
                const VREAL raw = l_op[k] * g;
                const VREAL alpha = CLS_FMIN((VREAL)(REAL)ALPHA_MAX, raw);
                const VMASK valid = pos <= last && sigma >= (REAL)0 && alpha >= (REAL)ALPHA_MIN;
                if (!CLS_VANY(valid)) continue;
                const VREAL one_m = (REAL)1 - alpha;
                const VREAL inv_one_m = (REAL)1 / one_m;
#if BWD_DIVIDE
                T = valid ? T * inv_one_m : T;
#endif
                const VREAL w = valid ? alpha * T : (VREAL)0;
#if COLOR_GRAD
#if CLS_TUNED
#pragma unroll /* channel loops unrolled, so vo[] and the sums stay in registers */
#endif
                for (int ch = 0; ch < CCHUNK; ++ch) my[G_GEOM + ch] = VSUM(w * vo[ch]);
#endif
#if GEOM_GRAD
                VREAL A = (VREAL)0; /* f_k . v_out at each pixel */
#if WIDE
                const size_t fb = (size_t)l_cg[k] * CHANNELS;
                for (int ch = 0; ch < CHANNELS; ++ch) {
                    REAL v_l[PIX];
                    for (int q = 0; q < PIX; ++q)
                        v_l[q] = pix_l[q] == ~(size_t)0 ? (REAL)0 : v_out[pix_l[q] * CHANNELS + ch];
#if PIX == 1
                    A += feats[fb + ch] * v_l[0];
#else
                    A += feats[fb + ch] * CAT(vload, PIX)(0, v_l);
#endif
                }
#else
#if CLS_TUNED
#pragma unroll
#endif
                for (int ch = 0; ch < CHANNELS; ++ch) A += l_f[CCHUNK * k + ch] * vo[ch];
#endif
#if BWD_DIVIDE
                VREAL v_alpha = T * A - (B + vT * T_final) * inv_one_m;
                B += w * A;
#else
                B -= w * A;
                VREAL v_alpha = T * A - (B + vT * T_final) * inv_one_m;
#endif
                /* The clamp makes alpha constant: nothing flows to sigma or the opacity. */
                const VMASK live = valid && raw < (REAL)ALPHA_MAX;
                v_alpha = live ? v_alpha : (VREAL)0;
                const VREAL v_sigma = -v_alpha * raw;
                const VREAL vx = v_sigma * (ca * dx + cb * dy), vy = v_sigma * (cb * dx + cc * dy);
                my[0] = VSUM(vx);
                my[1] = VSUM(vy);
                my[2] = VSUM((REAL)0.5 * v_sigma * dx * dx);
                my[3] = VSUM(v_sigma * dx * dy);
                my[4] = VSUM((REAL)0.5 * v_sigma * dy * dy);
                my[5] = VSUM(v_alpha * g);
#if ABSGRAD
                my[6] = VSUM(CLS_FABS(vx));
                my[7] = VSUM(CLS_FABS(vy));
#endif
#endif
#if !BWD_DIVIDE
                T = valid ? T * one_m : T;
#endif
            }
        }
        barrier(CLK_LOCAL_MEM_FENCE);
#if CLS_TUNED
        /* Sum each sample's per-item partials in item order and write its slot: an item sums
         * CLS_MV consecutive partials at once, each lane in item order as one scalar would. */
#if WAVES == 1
        for (int v = lid; v < n_vec; v += GROUP) {
            MVREAL acc = (MVREAL)0;
            for (int w = 0; w < GROUP; ++w) acc += partv[w * (PB / CLS_MV) + v];
#else
        for (int v = lid; v < n_vec; v += GROUP) l_accv[v] = (MVREAL)0;
        for (int wave = 0; wave < WAVES; ++wave) {
            if (lid / WAVE == wave)
                for (int i = 0; i < n_vec * CLS_MV; ++i) part[(lid - wave * WAVE) * PB + i] = my_p[i];
            barrier(CLK_LOCAL_MEM_FENCE);
            for (int v = lid; v < n_vec; v += GROUP) {
                MVREAL acc = l_accv[v];
                for (int w = 0; w < WAVE; ++w) acc += partv[w * (PB / CLS_MV) + v];
                l_accv[v] = acc;
            }
            barrier(CLK_LOCAL_MEM_FENCE);
        }
        for (int v = lid; v < n_vec; v += GROUP) {
            const MVREAL acc = l_accv[v];
#endif
            const REAL *acc_l = (const REAL *)&acc;
            for (int q = 0; q < CLS_MV; ++q) {
                const int idx = v * CLS_MV + q;
                const int k = idx / PG, j = idx - k * PG;
                if (k >= nb) break;
                const int col = j < G_GEOM ? j : SLOT_COLOR0 + ch0 + (j - G_GEOM);
                if (j >= G_GEOM && ch0 + (j - G_GEOM) >= CHANNELS) continue;
                slots[(size_t)l_slot[k] * SLOT_G + col] = acc_l[q];
            }
        }
#else
        /* Sum each sample's per-item partials in item order and write its slot. */
#if WAVES == 1
        for (int idx = lid; idx < nb * PG; idx += GROUP) {
            const int k = idx / PG, j = idx - k * PG;
            REAL acc = 0;
            for (int w = 0; w < GROUP; ++w) acc += part[(k * GROUP + w) * PG + j];
#else
        for (int idx = lid; idx < nb * PG; idx += GROUP) l_acc[idx] = 0;
        for (int wave = 0; wave < WAVES; ++wave) {
            if (lid / WAVE == wave)
                for (int k = 0; k < nb; ++k)
                    for (int j = 0; j < PG; ++j)
                        part[(k * WAVE + lid - wave * WAVE) * PG + j] = my_p[k * PG + j];
            barrier(CLK_LOCAL_MEM_FENCE);
            for (int idx = lid; idx < nb * PG; idx += GROUP) {
                const int k = idx / PG, j = idx - k * PG;
                REAL acc = l_acc[idx];
                for (int w = 0; w < WAVE; ++w) acc += part[(k * WAVE + w) * PG + j];
                l_acc[idx] = acc;
            }
            barrier(CLK_LOCAL_MEM_FENCE);
        }
        for (int idx = lid; idx < nb * PG; idx += GROUP) {
            const int k = idx / PG, j = idx - k * PG;
            const REAL acc = l_acc[idx];
#endif
            const int col = j < G_GEOM ? j : SLOT_COLOR0 + ch0 + (j - G_GEOM);
            if (j >= G_GEOM && ch0 + (j - G_GEOM) >= CHANNELS) continue;
            slots[(size_t)l_slot[k] * SLOT_G + col] = acc;
        }
#endif
    }
}
