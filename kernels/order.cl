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
 *   count:   hist[b * n_chunks + c] = elements of chunk c that fall in bin b (each count
 *            kernel first zeroes its own column);
 *   scan:    an exclusive prefix sum of hist in that bin-major, chunk-minor order gives each
 *            (bin, chunk) its first output position (on the host or by pyopencl's scan,
 *            as for bin.cl);
 *   scatter: chunk c walks its elements again, in order, writing each to pos[b*n_chunks+c]++.
 * Within a bin, earlier chunks come first (the scan's order) and a chunk keeps its own order:
 * stable. Each work-item writes only its own column: no atomics, deterministic anywhere.
 *
 * Depth sort: an LSD radix sort of the 32 depth bits, RADIX_BITS a pass. Pass 0 reads the
 * pairs straight from project's outputs in ascending cg order, drops those that touch no
 * tile and builds the keys; stability keeps equal depths in ascending cg, the full key order.
 * Tile placement: the bins are the (camera, tile) segments; a pair counts into, then writes
 * to, every tile of its rectangle (gathered once into key order first). Chunk 0's scanned positions are the segments' starts.
 * Build parameters: REAL_DOUBLE, RADIX_BITS.
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

inline void zero_column(__global int *hist, int n_bins, int n_chunks, int c) {
    for (int b = 0; b < n_bins; ++b) hist[b * n_chunks + c] = 0;
}

/* Pass 0, count: digit `shift` of the depth key of every pair of chunk c that touches a tile. */
__kernel void depth_count_pairs(const int CN, const int chunk, const int n_chunks,
                                __global const int *rects,   /* [C, N, 4] */
                                __global const REAL *depths, /* [C, N] */
                                __global int *hist)          /* [RADIX_BINS, n_chunks] */
{
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    zero_column(hist, RADIX_BINS, n_chunks, c);
    const int lo = c * chunk, hi = min(lo + chunk, CN);
    for (int cg = lo; cg < hi; ++cg)
        if (touches_tiles(rects, cg))
            ++hist[radix_digit(depth_key(depths[cg], (uint)cg), 0) * n_chunks + c];
}

/* Pass 0, scatter: the keys of those pairs, placed by their lowest depth digit. */
__kernel void depth_scatter_pairs(const int CN, const int chunk, const int n_chunks,
                                  __global const int *rects, __global const REAL *depths,
                                  __global int *pos,    /* [RADIX_BINS, n_chunks] scanned */
                                  __global ulong *dst)  /* [n visible pairs] */
{
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    const int lo = c * chunk, hi = min(lo + chunk, CN);
    for (int cg = lo; cg < hi; ++cg)
        if (touches_tiles(rects, cg)) {
            const ulong key = depth_key(depths[cg], (uint)cg);
            dst[pos[radix_digit(key, 0) * n_chunks + c]++] = key;
        }
}

/* Passes 1..: count the digit at `shift` of keys [n]. */
__kernel void depth_count(const int n, const int chunk, const int n_chunks, const int shift,
                          __global const ulong *src, __global int *hist)
{
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    zero_column(hist, RADIX_BINS, n_chunks, c);
    const int lo = c * chunk, hi = min(lo + chunk, n);
    for (int i = lo; i < hi; ++i) ++hist[radix_digit(src[i], shift) * n_chunks + c];
}

__kernel void depth_scatter(const int n, const int chunk, const int n_chunks, const int shift,
                            __global const ulong *src, __global int *pos, __global ulong *dst)
{
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    const int lo = c * chunk, hi = min(lo + chunk, n);
    for (int i = lo; i < hi; ++i) {
        const ulong key = src[i];
        dst[pos[radix_digit(key, shift) * n_chunks + c]++] = key;
    }
}

/* The sorted pairs' tile rectangles, read once in key order: rows of camera c's tiles
 * shifted by c * tiles_y, so that tile (x, y) is segment y * tiles_x + x. The placement passes
 * then read rectangles in sequence: gathering them there, inside loops whose trip counts
 * depend on the gathered values, stalls on every cache miss (measured: the placement ran at
 * about a third of its speed at 1M pairs), where this loop keeps many loads in flight. */
__kernel void gather_rects(const int n, const int chunk, const int n_chunks, const int N,
                           const int tiles_y,
                           __global const ulong *keys,  /* [n] depth-sorted */
                           __global const int *rects,   /* [C, N, 4] */
                           __global int *srects)        /* [n, 4] */
{
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    const int lo = c * chunk, hi = min(lo + chunk, n);
    for (int i = lo; i < hi; ++i) {
        const uint cg = key_id(keys[i]);
        const int4 r = vload4(cg, rects);
        const int dy = ((int)cg / N) * tiles_y;
        vstore4((int4)(r.x, r.y + dy, r.z, r.w + dy), i, srects);
    }
}

/* Tile placement, count: entries per (camera, tile) segment and chunk of the sorted keys. */
__kernel void place_count(const int n, const int chunk, const int n_chunks, const int tiles_x,
                          const int n_tiles,
                          __global const int *srects,  /* [n, 4] from gather_rects */
                          __global int *hist)          /* [n_tiles, n_chunks] */
{
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    zero_column(hist, n_tiles, n_chunks, c);
    const int lo = c * chunk, hi = min(lo + chunk, n);
    for (int i = lo; i < hi; ++i) {
        const int4 r = vload4(i, srects);
        for (int ty = r.y; ty < r.w; ++ty)
            for (int tx = r.x; tx < r.z; ++tx) ++hist[(ty * tiles_x + tx) * n_chunks + c];
    }
}

/* Segment starts: chunk 0's scanned position of each segment; offsets[n_tiles] = total. */
__kernel void segment_starts(const int n_tiles, const int n_chunks, const int total,
                             __global const int *pos,  /* [n_tiles, n_chunks] scanned */
                             __global int *offsets)    /* [n_tiles + 1] */
{
    const int t = get_global_id(0);
    if (t > n_tiles) return;
    offsets[t] = t < n_tiles ? pos[t * n_chunks] : total;
}

/* Tile placement, scatter: each key into every tile of its rectangle, in depth order. */
__kernel void place_scatter(const int n, const int chunk, const int n_chunks, const int tiles_x,
                            __global const ulong *keys,  /* [n] depth-sorted */
                            __global const int *srects,  /* [n, 4] from gather_rects */
                            __global int *pos,           /* [n_tiles, n_chunks] scanned */
                            __global ulong *out)         /* [M] the tile lists */
{
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    const int lo = c * chunk, hi = min(lo + chunk, n);
    for (int i = lo; i < hi; ++i) {
        const ulong key = keys[i];
        const int4 r = vload4(i, srects);
        for (int ty = r.y; ty < r.w; ++ty)
            for (int tx = r.x; tx < r.z; ++tx) out[pos[(ty * tiles_x + tx) * n_chunks + c]++] = key;
    }
}
