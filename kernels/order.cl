/* order.cl — stages 3 and 4 in one (issue 35): depth sort once, tiles in order.
 *
 * Every (camera, Gaussian) pair that touches a tile is sorted once by depth (N keys, not
 * N x tiles), then each pair's tile entries are placed with a stable counting pass over tile
 * ids, so every tile's list comes out in depth order and no per-tile sort is needed.
 *
 * Keys are bin.cl's: depth_key(depth, cg) = float32 depth bits << 32 | cg, cg = c * N + g.
 * The order, ties included: ascending key, i.e. by the float32 depth's bit pattern read as an
 * unsigned integer, equal bits by ascending cg (camera, then Gaussian id). That is exactly
 * the order sort.cl gives each tile's segment, so both paths make the same tile lists, key
 * for key, and the same images and gradients bit for bit.
 *
 * Every pass is a stable counting sort, parallel over chunks: work-item c owns the c-th run
 * of `chunk` consecutive input elements and walks it serially, in order.
 *   count:   counter (b, c) = elements of chunk c that fall in bin b (each count kernel
 *            first zeroes its own chunk's counters);
 *   scan:    an exclusive prefix sum of the counters in bin-major, chunk-minor order gives
 *            each (bin, chunk) its first output position (few chunks: each scatter
 *            work-item computes its own, see own_positions; else a scan launch);
 *   scatter: chunk c walks its elements again, in order, writing each to position (b, c)++.
 * Within a bin, earlier chunks come first (the scan's order) and a chunk keeps its own order:
 * stable. Each work-item writes only its own counters: no atomics, deterministic anywhere.
 * Counter (b, c) is stored at c * n_bins + b with HIST_CHUNK_MAJOR (the serial layout: each
 * chunk's counters are its own cache lines, which cores running neighbouring chunks would
 * otherwise both write), else at b * n_chunks + c (GPUs: the work-items of a group touch
 * neighbouring words, and pyopencl's flat scan reads them in order).
 *
 * Depth sort: an LSD radix sort of the 32 depth bits, RADIX_BITS a pass. Pass 0 reads the
 * pairs straight from project's outputs in ascending cg order, drops those that touch no
 * tile and builds the keys; stability keeps equal depths in ascending cg, the full key order.
 * Tile placement: the bins are the (camera, tile) segments; a pair counts into, then writes
 * to, every tile of its rectangle (packed by pass 0, gathered once into key order first).
 * Chunk 0's scanned positions are the segments' starts (the tile offsets).
 * order_small: all of it in one work-item, for small inputs of the serial layout.
 * Build parameters: REAL_DOUBLE, RADIX_BITS, HIST_CHUNK_MAJOR, PACK_BITS.
 */

/* RADIX_BITS (a divisor of 32) comes from the driver, clsplat.stages.ORDER_RADIX_BITS,
 * which sizes the counters: see there for the choice. */
#define RADIX_BINS (1 << RADIX_BITS)

inline uint radix_digit(ulong key, int shift) {
    return (uint)(key >> (32 + shift)) & (RADIX_BINS - 1);
}

/* A pair with an empty tile rectangle (culled, or off-image) has no tile entry. Scalar loads:
 * comparing two lanes of a vload4 crashes Oclgrind 21.10's uninitialised-value checker. */
inline int touches_tiles(__global const int *rects, int cg) {
    return rects[4 * cg + 2] > rects[4 * cg] && rects[4 * cg + 3] > rects[4 * cg + 1];
}

/* Where counter (b, c) lives; chunk c's counter b is counters(hist, n_bins, c)[b * stride]. */
#if HIST_CHUNK_MAJOR
#define COUNTER(b, c, n_bins, n_chunks) ((c) * (n_bins) + (b))
#define COUNTER_STRIDE(n_chunks) 1
#else
#define COUNTER(b, c, n_bins, n_chunks) ((b) * (n_chunks) + (c))
#define COUNTER_STRIDE(n_chunks) (n_chunks)
#endif
inline __global int *counters(__global int *hist, int n_bins, int n_chunks, int c) {
    return hist + COUNTER(0, c, n_bins, n_chunks);
}

inline void zero_counters(__global int *h, int n_bins, int stride) {
    for (int b = 0; b < n_bins; ++b) h[b * stride] = 0;
}

/* With own_scan, chunk c's scan positions, computed by its scatter work-item itself from every
 * chunk's counts and written to its own counters in pos: n_bins x n_chunks reads, a few
 * thousand for the serial layout's few chunks, less than the launch and wake-up of a separate
 * scan. Without (the GPU layout's thousands of chunks, or many cores' chunks: the reads grow
 * as chunks squared), a scan launch has filled pos already. */
inline void own_positions(int own_scan, __global const int *hist, __global int *pos, int n_bins,
                          int n_chunks, int c) {
    if (!own_scan) return;
    int run = 0;
    for (int b = 0; b < n_bins; ++b)
        for (int c2 = 0; c2 < n_chunks; ++c2) {
            const int i = COUNTER(b, c2, n_bins, n_chunks);
            if (c2 == c) pos[i] = run;
            run += hist[i];
        }
}

/* A pair's tile rectangle in 8 bytes, (x0 | x1 << PACK_BITS, y0 | y1 << PACK_BITS), the
 * rows of camera c shifted by c * tiles_y so that tile (x, y) is segment y * tiles_x + x (the
 * driver checks that tiles_x and C * tiles_y fit in PACK_BITS, clsplat.stages.ORDER_PACK_BITS).
 * Half of project's 16 bytes for the random gather of the sorted pairs' rectangles, which
 * dominates the placement at 1M pairs. Scalar loads and stores, as in touches_tiles. */
#define PACK_MASK ((1u << PACK_BITS) - 1u)
inline void store_packed(__global uint *prects, int i, int4 r, int dy) {
    prects[2 * i] = (uint)r.x | ((uint)r.z << PACK_BITS);
    prects[2 * i + 1] = (uint)(r.y + dy) | ((uint)(r.w + dy) << PACK_BITS);
}
inline int4 load_packed(__global const uint *prects, int i) {
    const uint a = prects[2 * i], b = prects[2 * i + 1];
    return (int4)((int)(a & PACK_MASK), (int)(b & PACK_MASK), (int)(a >> PACK_BITS), (int)(b >> PACK_BITS));
}

/* Pass 0, count: digit `shift` of the depth key of every pair of chunk c that touches a tile. */
__kernel void depth_count_pairs(const int CN, const int chunk, const int n_chunks, const int N,
                                const int tiles_y,
                                __global const int *rects,   /* [C, N, 4] */
                                __global const REAL *depths, /* [C, N] */
                                __global uint *prects,       /* [C * N, 2] packed; 0: no tile */
                                __global int *hist)          /* RADIX_BINS x n_chunks counters */
{
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    __global int *h = counters(hist, RADIX_BINS, n_chunks, c);
    const int st = COUNTER_STRIDE(n_chunks);
    zero_counters(h, RADIX_BINS, st);
    const int lo = c * chunk, hi = min(lo + chunk, CN);
    int cam = lo / N, next = (cam + 1) * N; /* one division per chunk, not per pair */
    for (int cg = lo; cg < hi; ++cg) {
        if (cg == next) {
            ++cam;
            next += N;
        }
        if (touches_tiles(rects, cg)) {
            ++h[radix_digit(depth_key(depths[cg], (uint)cg), 0) * st];
            store_packed(prects, cg, vload4(cg, rects), cam * tiles_y);
        } else {
            prects[2 * cg] = prects[2 * cg + 1] = 0u;
        }
    }
}

/* Pass 0, scatter: the keys of those pairs, placed by their lowest depth digit. */
__kernel void depth_scatter_pairs(const int CN, const int chunk, const int n_chunks, const int N,
                                  const int tiles_y,
                                  __global const uint *prects, __global const REAL *depths,
                                  const int own_scan,
                                  __global const int *hist, /* the counts */
                                  __global int *pos,        /* the scanned counts */
                                  __global ulong *dst)      /* [n visible pairs] */
{
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    own_positions(own_scan, hist, pos, RADIX_BINS, n_chunks, c);
    __global int *p = counters(pos, RADIX_BINS, n_chunks, c);
    const int st = COUNTER_STRIDE(n_chunks);
    const int lo = c * chunk, hi = min(lo + chunk, CN);
    for (int cg = lo; cg < hi; ++cg)
        if (prects[2 * cg] != 0u || prects[2 * cg + 1] != 0u) { /* touches a tile */
            const ulong key = depth_key(depths[cg], (uint)cg);
            dst[p[radix_digit(key, 0) * st]++] = key;
        }
}

/* Passes 1..: count the digit at `shift` of keys [n]. */
__kernel void depth_count(const int n, const int chunk, const int n_chunks, const int shift,
                          __global const ulong *src, __global int *hist)
{
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    __global int *h = counters(hist, RADIX_BINS, n_chunks, c);
    const int st = COUNTER_STRIDE(n_chunks);
    zero_counters(h, RADIX_BINS, st);
    const int lo = c * chunk, hi = min(lo + chunk, n);
    for (int i = lo; i < hi; ++i) ++h[radix_digit(src[i], shift) * st];
}

__kernel void depth_scatter(const int n, const int chunk, const int n_chunks, const int shift,
                            __global const ulong *src, const int own_scan,
                            __global const int *hist, __global int *pos, __global ulong *dst)
{
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    own_positions(own_scan, hist, pos, RADIX_BINS, n_chunks, c);
    __global int *p = counters(pos, RADIX_BINS, n_chunks, c);
    const int st = COUNTER_STRIDE(n_chunks);
    const int lo = c * chunk, hi = min(lo + chunk, n);
    for (int i = lo; i < hi; ++i) {
        const ulong key = src[i];
        dst[p[radix_digit(key, shift) * st]++] = key;
    }
}

/* The sorted pairs' packed rectangles, read once in key order, so that the placement passes
 * read them in sequence (a random read per pair is the placement's main cost at 1M pairs). */
__kernel void gather_rects(const int n, const int chunk, const int n_chunks,
                           __global const ulong *keys,   /* [n] depth-sorted */
                           __global const uint *prects,  /* [C * N, 2] from depth_count_pairs */
                           __global uint *srects)        /* [n, 2] */
{
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    const int lo = c * chunk, hi = min(lo + chunk, n);
    for (int i = lo; i < hi; ++i) {
        const uint cg = key_id(keys[i]);
        srects[2 * i] = prects[2 * cg];
        srects[2 * i + 1] = prects[2 * cg + 1];
    }
}

/* Tile placement, count: entries per (camera, tile) segment and chunk of the sorted keys. */
__kernel void place_count(const int n, const int chunk, const int n_chunks, const int tiles_x,
                          const int n_tiles,
                          __global const uint *srects,  /* [n, 2] from gather_rects */
                          __global int *hist)          /* n_tiles x n_chunks counters */
{
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    __global int *h = counters(hist, n_tiles, n_chunks, c);
    const int st = COUNTER_STRIDE(n_chunks);
    zero_counters(h, n_tiles, st);
    const int lo = c * chunk, hi = min(lo + chunk, n);
    for (int i = lo; i < hi; ++i) {
        const int4 r = load_packed(srects, i);
        for (int ty = r.y; ty < r.w; ++ty)
            for (int tx = r.x; tx < r.z; ++tx) ++h[(ty * tiles_x + tx) * st];
    }
}

/* The exclusive prefix sum of the counters in (bin, chunk) order, in one work-item: for
 * chunk-major counters too many for own_positions, and in the GPU layout where pyopencl's
 * scan cannot run (Oclgrind's uninitialised-value checker). */
__kernel void scan_counters(const int n_bins, const int n_chunks,
                            __global const int *hist, __global int *pos)
{
    if (get_global_id(0) != 0) return; /* no barrier in this kernel */
    int run = 0;
    for (int b = 0; b < n_bins; ++b)
        for (int c = 0; c < n_chunks; ++c) {
            const int i = COUNTER(b, c, n_bins, n_chunks);
            pos[i] = run;
            run += hist[i];
        }
}

/* Segment starts: chunk 0's scanned position of each segment; offsets[n_tiles] = total. */
__kernel void segment_starts(const int n_tiles, const int n_chunks, const int total,
                             __global const int *pos,  /* the scanned counters */
                             __global int *offsets)    /* [n_tiles + 1] */
{
    const int t = get_global_id(0);
    if (t > n_tiles) return;
    offsets[t] = t < n_tiles ? pos[COUNTER(t, 0, n_tiles, n_chunks)] : total; /* chunk 0's */
}

/* Tile placement, scatter: each key into every tile of its rectangle, in depth order. */
__kernel void place_scatter(const int n, const int chunk, const int n_chunks, const int tiles_x,
                            const int n_tiles, const int total,
                            __global const ulong *keys,  /* [n] depth-sorted */
                            __global const uint *srects,  /* [n, 2] from gather_rects */
                            const int own_scan,
                            __global const int *hist,    /* the counts */
                            __global int *pos,           /* the scanned counts */
                            __global int *offsets,       /* [n_tiles + 1] */
                            __global ulong *out)         /* [M] the tile lists */
{
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    own_positions(own_scan, hist, pos, n_tiles, n_chunks, c);
    if (own_scan && c == 0) { /* the segment starts (else segment_starts' work) */
        for (int t = 0; t < n_tiles; ++t) offsets[t] = pos[COUNTER(t, 0, n_tiles, n_chunks)];
        offsets[n_tiles] = total;
    }
    __global int *p = counters(pos, n_tiles, n_chunks, c);
    const int st = COUNTER_STRIDE(n_chunks);
    const int lo = c * chunk, hi = min(lo + chunk, n);
    for (int i = lo; i < hi; ++i) {
        const ulong key = keys[i];
        const int4 r = load_packed(srects, i);
        for (int ty = r.y; ty < r.w; ++ty)
            for (int tx = r.x; tx < r.z; ++tx) out[p[(ty * tiles_x + tx) * st]++] = key;
    }
}

/* The same passes in one work-item, scans included, for the serial layout's small inputs
 * (clsplat.stages.ORDER_SMALL): one launch and no host round trip per pass, where the
 * chunked passes' launches and waits cost more than the work (a 10k-pair render paid 2-3x
 * the per-tile sort's time). The order is the chunked passes' with one chunk: the same lists.
 * Counters are in cnt: RADIX_BINS during the sort, n_tiles during the placement. */
__kernel void order_small(const int CN, const int N, const int tiles_x, const int tiles_y,
                          const int n_tiles,
                          __global const int *rects,   /* [C, N, 4] */
                          __global const REAL *depths, /* [C, N] */
                          __global ulong *a,           /* [pairs that touch a tile] scratch */
                          __global ulong *b,           /* [the same] scratch */
                          __global int *cnt,           /* [max(RADIX_BINS, n_tiles)] scratch */
                          __global int *offsets,       /* [n_tiles + 1] */
                          __global ulong *out)         /* [M] the tile lists */
{
    if (get_global_id(0) != 0) return; /* no barrier in this kernel */
    for (int d = 0; d < RADIX_BINS; ++d) cnt[d] = 0;
    for (int cg = 0; cg < CN; ++cg)
        if (touches_tiles(rects, cg)) ++cnt[radix_digit(depth_key(depths[cg], (uint)cg), 0)];
    int n = 0;
    for (int d = 0; d < RADIX_BINS; ++d) {
        const int k = cnt[d];
        cnt[d] = n;
        n += k;
    }
    for (int cg = 0; cg < CN; ++cg)
        if (touches_tiles(rects, cg)) {
            const ulong key = depth_key(depths[cg], (uint)cg);
            a[cnt[radix_digit(key, 0)]++] = key;
        }
    __global ulong *src = a, *dst = b;
    for (int shift = RADIX_BITS; shift < 32; shift += RADIX_BITS) {
        for (int d = 0; d < RADIX_BINS; ++d) cnt[d] = 0;
        for (int i = 0; i < n; ++i) ++cnt[radix_digit(src[i], shift)];
        int run = 0, trivial = 0;
        for (int d = 0; d < RADIX_BINS; ++d) {
            const int k = cnt[d];
            trivial |= k == n;
            cnt[d] = run;
            run += k;
        }
        if (trivial) continue; /* one bin holds every key: the pass would change nothing */
        for (int i = 0; i < n; ++i) {
            const ulong key = src[i];
            dst[cnt[radix_digit(key, shift)]++] = key;
        }
        __global ulong *t = src;
        src = dst;
        dst = t;
    }
    for (int t = 0; t < n_tiles; ++t) cnt[t] = 0;
    for (int i = 0; i < n; ++i) {
        const int cg = (int)key_id(src[i]);
        const int4 r = vload4(cg, rects);
        const int base = (cg / N) * tiles_x * tiles_y;
        for (int ty = r.y; ty < r.w; ++ty)
            for (int tx = r.x; tx < r.z; ++tx) ++cnt[base + ty * tiles_x + tx];
    }
    int total = 0;
    for (int t = 0; t < n_tiles; ++t) {
        const int k = cnt[t];
        offsets[t] = cnt[t] = total;
        total += k;
    }
    offsets[n_tiles] = total;
    for (int i = 0; i < n; ++i) {
        const ulong key = src[i];
        const int cg = (int)key_id(key);
        const int4 r = vload4(cg, rects);
        const int base = (cg / N) * tiles_x * tiles_y;
        for (int ty = r.y; ty < r.w; ++ty)
            for (int tx = r.x; tx < r.z; ++tx) out[cnt[base + ty * tiles_x + tx]++] = key;
    }
}
