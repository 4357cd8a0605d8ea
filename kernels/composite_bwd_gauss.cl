/* composite_bwd_gauss.cl — backward of compositing, summed per Gaussian (RenderConfig
 * backward_impl="gaussian"): one work-item per tile walks the tile's Gaussians and, for each,
 * the tile's row segments it can reach, adding that Gaussian's gradient over the pixels into
 * registers; the sums are written once per (tile, Gaussian) intersection.
 *
 * The maths is composite_bwd.cl's (see there: d loss / d alpha_i from T_i, A_i = f_i . v_out
 * and the running scalar B_i, replay or divide order, the ALPHA_MAX clamp, the forward's
 * decisions replayed with the same arithmetic). What differs is who sums over pixels:
 *  - composite_bwd.cl ("pixel"): a work-item per row segment of PIX pixels; every item writes
 *    its partials of every sample of a batch to local memory (one horizontal sum per value,
 *    sample and item), and the group then sums them over its items per sample;
 *  - here ("gaussian"): the item owns the whole tile, so each sample's partials accumulate
 *    lane-wise in PIX-wide registers over the segments it reaches and are summed across lanes
 *    once. No partials array, no zeroing, no barriers, no group sum; the per-pixel state (T, B,
 *    last, v_T T_final, v_out) lives in local memory, one entry per segment, loaded and stored
 *    per visit.
 * A sample visits only the rows and segments its extent bounds reach (computed per sample, then
 * tested exactly as extent_bits / outside_extent test them), so the skipped samples are those the
 * forward skipped; the l_sm bound and each segment's last contributor skip as in composite_bwd.cl.
 *
 * Order of the sums (fixed, so results are bitwise reproducible, and the same for any number of
 * compute units): per sample, segments row by row, left to right, each lane accumulating in
 * that order; then VSUM's pairwise lane order. The pixel backward sums per item first, then over
 * items: the two agree to rounding (float32 close, float64 tight), not bit for bit.
 *
 * Channels come CCHUNK per launch as in composite_bwd.cl; the geometry launch (GEOM_GRAD, the
 * first) needs A over all CHANNELS, from the local v_out when they fit in one chunk, else read
 * from global memory (WIDE).
 *
 * Slots: the layout of composite_bwd.cl (SLOT_G values per intersection, colour from column
 * SLOT_COLOR0), reduced per pair by reduce.cl; the caller zeroes them (a sample no pixel reaches
 * is not written). With FUSED_REDUCE (small calls on PoCL's CPU device, one launch: see the end
 * of the kernel) the last work-item to finish sums them here instead.
 *
 * Build parameters: REAL_DOUBLE, TILE, PIX, CHANNELS, CCHUNK, GEOM_GRAD, COLOR_GRAD, ABSGRAD,
 * BWD_DIVIDE, SLOT_G, SLOT_COLOR0, ALPHA_MIN, ALPHA_MAX, CLS_POCL_CPU, FUSED_REDUCE.
 */

#if FUSED_REDUCE && (SLOT_G != REDUCE_G || CCHUNK < CHANNELS)
#error "FUSED_REDUCE needs the whole slot in one launch (the geometry and every channel)"
#endif

#define NSEG (TILE * TILE / PIX) /* row segments of PIX pixels in a tile */
#define SEGS_PER_ROW (TILE / PIX)
/* Samples ahead whose parameters are prefetched (PoCL's CPU device): the next sample's loads
 * are random Gaussians, a cache miss each, and a sample costs a few hundred cycles. */
#ifndef PREFETCH_AHEAD /* (a -D for side-by-side timings) */
#define PREFETCH_AHEAD 4
#endif

/* First and one-past-last index i in [0, n) with |c - (base + i + CLS_PIXEL_CENTRE)| <= bound
 * possible, widened by one each way (the exact test is made per index); bound >= 0. */
inline int2 index_range(REAL c, REAL bound, REAL base, int n) {
    const REAL lo = CLS_FLOOR(c - bound - base - (REAL)CLS_PIXEL_CENTRE) - 1;
    const REAL hi = CLS_CEIL(c + bound - base - (REAL)CLS_PIXEL_CENTRE) + 2;
    /* Clamp before converting: a far off-screen mean would overflow int. */
    return (int2)((int)CLS_FMIN((REAL)n, CLS_FMAX((REAL)0, lo)), (int)CLS_FMIN((REAL)n, CLS_FMAX((REAL)0, hi)));
}

__kernel __attribute__((reqd_work_group_size(1, 1, 1)))
void composite_bwd_gauss(COMPOSITE_BWD_ARGS
#if FUSED_REDUCE
                         , const int CN,      /* C * N */
                         __global int *done,  /* [1] items finished: 0 before and after a launch */
                         REDUCE_OUT_ARGS
#endif
                         )
{
    /* Per-segment state: T (running), B (running), the last contributor's position, v_T T_final,
     * v_out of this launch's channels [channel][segment], and each segment's largest last. */
    __local VREAL l_T[NSEG], l_B[NSEG], l_last[NSEG], l_vTT[NSEG], l_vo[CCHUNK * NSEG];
    __local int l_seg_last[NSEG];

    const int tile = get_group_id(0);
    const int c = tile / tiles_per_cam, t = tile - c * tiles_per_cam;
    const int ty = t / tiles_x, tx = t - ty * tiles_x;
    const REAL x_base = (REAL)(tx * TILE), y_base = (REAL)(ty * TILE);

    int n_used = 0; /* samples past every pixel's last contributor get no gradient */
    for (int s = 0; s < NSEG; ++s) {
        const int row = s / SEGS_PER_ROW;
        const int py = ty * TILE + row, px0 = tx * TILE + (s - row * SEGS_PER_ROW) * PIX;
        REAL Tf_l[PIX], last_l[PIX], vTT_l[PIX], B_l[PIX], vo_l[PIX * CCHUNK];
        int seg_last = 0;
        for (int q = 0; q < PIX; ++q) {
            const int px = px0 + q;
            const int ok = px < width && py < height;
            const size_t pix = ((size_t)c * height + (ok ? py : 0)) * width + (ok ? px : 0);
            const REAL Tf = ok ? out_T[pix] : (REAL)1;
            const int lst = ok ? out_last[pix] : 0;
            Tf_l[q] = Tf;
            last_l[q] = (REAL)lst;
            seg_last = max(seg_last, lst);
            vTT_l[q] = (ok ? v_T[pix] : (REAL)0) * Tf; /* the product composite_bwd.cl forms */
            REAL b = 0;
#if GEOM_GRAD && !BWD_DIVIDE
            for (int ch = 0; ch < CHANNELS && ok; ++ch) b += out_feats[pix * CHANNELS + ch] * v_out[pix * CHANNELS + ch];
#endif
            B_l[q] = b;
            for (int ch = 0; ch < CCHUNK; ++ch)
                vo_l[PIX * ch + q] = ok && ch0 + ch < CHANNELS ? v_out[pix * CHANNELS + ch0 + ch] : (REAL)0;
        }
#if PIX == 1
        l_T[s] = BWD_DIVIDE ? Tf_l[0] : (REAL)1;
        l_last[s] = last_l[0];
        l_vTT[s] = vTT_l[0];
        l_B[s] = B_l[0];
        for (int ch = 0; ch < CCHUNK; ++ch) l_vo[ch * NSEG + s] = vo_l[ch];
#else
        l_T[s] = BWD_DIVIDE ? CAT(vload, PIX)(0, Tf_l) : (VREAL)1;
        l_last[s] = CAT(vload, PIX)(0, last_l);
        l_vTT[s] = CAT(vload, PIX)(0, vTT_l);
        l_B[s] = CAT(vload, PIX)(0, B_l);
        for (int ch = 0; ch < CCHUNK; ++ch) l_vo[ch * NSEG + s] = CAT(vload, PIX)(0, vo_l + PIX * ch);
#endif
        l_seg_last[s] = seg_last;
        n_used = max(n_used, seg_last);
    }

    const int start = tile_offsets[tile];
    for (int ii = 0; ii < n_used; ++ii) {
#if BWD_DIVIDE
        const int i = n_used - 1 - ii; /* back to front */
#else
        const int i = ii;
#endif
#if CLS_PREFETCH
        /* The parameters of a sample PREFETCH_AHEAD ahead in the walk, and the rectangle and
         * first slot of its pair (the slot write's loads; a cache miss each, a fifth of this
         * kernel's cycles on scene A without them). */
        {
            const int ia = BWD_DIVIDE ? i - PREFETCH_AHEAD : i + PREFETCH_AHEAD;
            if (ia >= 0 && ia < n_used) {
                const uint ca_ = key_id(keys[start + ia]);
                prefetch_sample(ca_, means2d, conics, opac_cg, extents, feats, ch0, CCHUNK);
                __builtin_prefetch(rects + 4 * ca_);
                __builtin_prefetch(isect_offsets + ca_);
            }
        }
#endif
        const uint cg = key_id(keys[start + i]);
        const REAL ey = extents[2 * cg + 1];
        if (ey < 0) continue; /* no pixel reaches ALPHA_MIN (outside_extent's first test) */
        __global REAL *slot = slots + (size_t)pair_slot(cg, tx, ty, rects, isect_offsets) * SLOT_G;
#if CLS_PREFETCH
        /* its slot, written after the visits below: fetched for writing meanwhile */
        __builtin_prefetch(slot, 1);
        __builtin_prefetch(slot + SLOT_G - 1, 1);
#endif
        const REAL x = means2d[2 * cg], y = means2d[2 * cg + 1];
        const REAL bx = extent_bound(extents[2 * cg]), by = extent_bound(ey);
        const REAL ca = conics[3 * cg], cb = conics[3 * cg + 1], cc = conics[3 * cg + 2];
        const REAL op = opac_cg[cg];
        /* stage_sample_soa's sigma bound, the same expression */
        const REAL sm = !((REAL)ALPHA_MIN > 0) ? (REAL)1e30
                        : op >= (REAL)ALPHA_MIN
                            ? log(op / (REAL)ALPHA_MIN) * (1 + (REAL)CLS_SIGMA_MARGIN) + (REAL)CLS_SIGMA_MARGIN
                            : (REAL)-1;
        const REAL pos = (REAL)(i + 1);
        REAL f[CCHUNK];
        for (int ch = 0; ch < CCHUNK; ++ch)
            f[ch] = ch0 + ch < CHANNELS ? feats[(size_t)cg * CHANNELS + ch0 + ch] : (REAL)0;

#if GEOM_GRAD
        /* Moments of s = v_alpha raw (= -v_sigma) over the pixels, from which the sample's
         * geometry gradients follow once (see the slot write below), and sum v_alpha g. */
        VREAL m_x = (VREAL)0, m_y = (VREAL)0, m_xx = (VREAL)0, m_xy = (VREAL)0, m_yy = (VREAL)0;
        VREAL m_o = (VREAL)0;
#if ABSGRAD
        VREAL m_ax = (VREAL)0, m_ay = (VREAL)0;
#endif
#endif
#if COLOR_GRAD
        VREAL acc_c[CCHUNK];
        for (int ch = 0; ch < CCHUNK; ++ch) acc_c[ch] = (VREAL)0;
#endif
        int touched = 0;
        const int2 rows = index_range(y, by, y_base, TILE);
        /* segments: pixel columns in range, as segment indices */
        const int2 cols = index_range(x, bx, x_base, TILE);
        const int s_lo = cols.x / PIX, s_hi = (cols.y + PIX - 1) / PIX;
        for (int row = rows.x; row < rows.y; ++row) {
            const REAL pyc = y_base + (REAL)row + (REAL)CLS_PIXEL_CENTRE;
            if (!(CLS_FABS(y - pyc) <= by)) continue; /* extent_bits' row test */
            const REAL dy = y - pyc, dy2 = dy * dy;
            for (int sx = s_lo; sx < s_hi; ++sx) {
                const int s = row * SEGS_PER_ROW + sx;
                if (pos > (REAL)l_seg_last[s]) continue; /* past every lane's last contributor */
                const REAL px_first = x_base + (REAL)(sx * PIX) + (REAL)CLS_PIXEL_CENTRE;
                const REAL px_last = px_first + (REAL)(PIX - 1);
                if (!(CLS_FMAX((REAL)0, CLS_FMAX(px_first - x, x - px_last)) <= bx)) continue;
                /* ---- one sample's gradients at this segment's PIX pixels ---- */
                const VREAL dx = x - (px_first + VRAMP);
                const VREAL sigma = (REAL)0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy;
                if (!CLS_VANY(sigma <= sm)) continue; /* alpha < ALPHA_MIN in every lane */
                const VREAL g = CLS_VEXP(-sigma);
                const VREAL raw = op * g;
                const VREAL alpha = CLS_FMIN((VREAL)(REAL)ALPHA_MAX, raw);
                /* Masks combine with & (all bits of a true lane are set, and a scalar's are 1):
                 * && would make clang narrow and widen the vector masks at every use. */
                const VMASK valid = (pos <= l_last[s]) & (sigma >= (REAL)0) & (alpha >= (REAL)ALPHA_MIN);
                if (!CLS_VANY(valid)) continue;
                touched = 1;
                VREAL T = l_T[s];
                const VREAL one_m = (REAL)1 - alpha;
                const VREAL inv_one_m = (REAL)1 / one_m;
#if BWD_DIVIDE
                T = valid ? T * inv_one_m : T;
#endif
                const VREAL w = valid ? alpha * T : (VREAL)0;
#if COLOR_GRAD
#pragma unroll
                for (int ch = 0; ch < CCHUNK; ++ch) acc_c[ch] += w * l_vo[ch * NSEG + s];
#endif
#if GEOM_GRAD
                VREAL A = (VREAL)0; /* f . v_out at each pixel */
#if WIDE
                {
                    const int py = ty * TILE + row, px0 = tx * TILE + sx * PIX;
                    for (int ch = 0; ch < CHANNELS; ++ch) {
                        REAL v_l[PIX];
                        for (int q = 0; q < PIX; ++q) {
                            const int ok = px0 + q < width && py < height;
                            v_l[q] = ok ? v_out[(((size_t)c * height + py) * width + px0 + q) * CHANNELS + ch] : (REAL)0;
                        }
#if PIX == 1
                        A += feats[(size_t)cg * CHANNELS + ch] * v_l[0];
#else
                        A += feats[(size_t)cg * CHANNELS + ch] * CAT(vload, PIX)(0, v_l);
#endif
                    }
                }
#else
#pragma unroll
                for (int ch = 0; ch < CHANNELS; ++ch) A += f[ch] * l_vo[ch * NSEG + s];
#endif
                VREAL B = l_B[s];
#if BWD_DIVIDE
                VREAL v_alpha = T * A - (B + l_vTT[s]) * inv_one_m;
                B += w * A;
#else
                B -= w * A;
                VREAL v_alpha = T * A - (B + l_vTT[s]) * inv_one_m;
#endif
                l_B[s] = B;
                /* The clamp makes alpha constant: nothing flows to sigma or the opacity. */
                const VMASK live = valid & (raw < (REAL)ALPHA_MAX);
                v_alpha = live ? v_alpha : (VREAL)0;
                /* d sigma / d (x, y) = (ca dx + cb dy, cb dx + cc dy) and d sigma / d conic =
                 * (dx^2 / 2, dx dy, dy^2 / 2) are linear in dx, dx^2, dy, dy^2 and dx dy, and the
                 * conic is the sample's: summing s times each moment costs 5 accumulations per
                 * visit instead of forming the 5 gradients at every pixel (13 operations). */
                const VREAL s_ = v_alpha * raw, t_ = s_ * dx;
                m_x += t_;
                m_xx += t_ * dx;
                m_y += s_ * dy;
                m_xy += t_ * dy;
                m_yy += s_ * dy2;
                m_o += v_alpha * g;
#if ABSGRAD /* |d loss / d (x, y)| per pixel: no moment gives it */
                m_ax += CLS_FABS(t_ * ca + s_ * (cb * dy));
                m_ay += CLS_FABS(t_ * cb + s_ * (cc * dy));
#endif
#endif
#if !BWD_DIVIDE
                T = valid ? T * one_m : T;
#endif
                l_T[s] = T;
            }
        }
        if (!touched) continue; /* its slot stays zero */
#if GEOM_GRAD
        {
            const REAL sx = -VSUM(m_x), sy = -VSUM(m_y); /* sums of v_sigma dx, v_sigma dy */
            slot[0] = ca * sx + cb * sy;
            slot[1] = cb * sx + cc * sy;
            slot[2] = (REAL)-0.5 * VSUM(m_xx);
            slot[3] = -VSUM(m_xy);
            slot[4] = (REAL)-0.5 * VSUM(m_yy);
            slot[5] = VSUM(m_o);
#if ABSGRAD
            slot[6] = VSUM(m_ax);
            slot[7] = VSUM(m_ay);
#endif
        }
#endif
#if COLOR_GRAD
        for (int ch = 0; ch < CCHUNK && ch0 + ch < CHANNELS; ++ch) slot[SLOT_COLOR0 + ch0 + ch] = VSUM(acc_c[ch]);
#endif
    }
#if FUSED_REDUCE
    /* The work-item that finishes last sums every pair's slots (reduce_pair: reduce.cl's sums,
     * the same bits), which saves a small call the reduce's launch and its wake-up of the
     * device's threads (clsplat.stages.FUSED_REDUCE_SLOTS). The count orders each item's slot
     * writes before its increment and the last item's reads after its own: the driver builds
     * this only for PoCL's CPU device, whose atomic_inc is a sequentially consistent
     * read-modify-write on shared memory (OpenCL 1.2 promises no order between work-groups). */
    mem_fence(CLK_GLOBAL_MEM_FENCE); /* this item's slot writes before its count (intent; */
    if (atomic_inc(done) == (int)get_num_groups(0) - 1) { /* PoCL's atomic orders them anyway) */
        mem_fence(CLK_GLOBAL_MEM_FENCE); /* the others' writes before the sums read them */
        for (int cg = 0; cg < CN; ++cg)
            reduce_pair(cg, rects, isect_offsets, slots, v_means2d, v_conics, v_opac, absgrad, v_feats);
        *done = 0; /* ready for the next launch */
    }
#endif
}
