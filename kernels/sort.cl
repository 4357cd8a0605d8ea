/* sort.cl — stage 4: order every tile segment by (depth bits, id).
 *
 * sort_local: one work-group per chunk of at most SORT_LOCAL keys, bitonic in local memory.
 * A chunk is a whole tile segment, or a SORT_LOCAL-sized piece of a larger one.
 * merge_runs: one pass of a global merge over the segments larger than SORT_LOCAL; each
 * work-item places one key by binary search in the sibling run, so a pass is fully parallel
 * and needs no atomics. log2(segment / SORT_LOCAL) passes finish the sort.
 *
 * sort_serial: the CPU layout. One work-item per whole segment, insertion-sorted runs then a
 * bottom-up merge through a scratch buffer: O(n log n) work and no barriers. On a CPU the
 * bitonic network's O(n log^2 n) compare-exchanges and its barrier per step (each one splits
 * PoCL's work-item loop) cost more than the parallelism inside a tile buys; the tiles
 * themselves give the cores enough independent work.
 *
 * Keys are unique (the id is in the low word), which makes the result independent of how
 * the bin stage's atomics ordered a segment: the sort is deterministic, in either layout.
 * Build parameters: SORT_LOCAL (a power of two), for the bitonic layout.
 */

/* Padding sorts after every real key: real keys hold finite positive depths. */
#define KEY_PAD 0xffffffffffffffffUL

__kernel void sort_local(__global ulong *keys,
                         __global const int *chunk_start, /* [n_chunks] */
                         __global const int *chunk_len)   /* [n_chunks], each <= SORT_LOCAL */
{
    __local ulong buf[SORT_LOCAL];
    const int lid = get_local_id(0), ls = get_local_size(0);
    const int start = chunk_start[get_group_id(0)], n = chunk_len[get_group_id(0)];
    /* Sort only the next power of two above n, not the whole buffer: small tiles dominate. */
    int np = 2;
    while (np < n) np <<= 1;
    for (int i = lid; i < np; i += ls) buf[i] = i < n ? keys[start + i] : KEY_PAD;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int k = 2; k <= np; k <<= 1) {
        for (int j = k >> 1; j > 0; j >>= 1) {
            for (int i = lid; i < (np >> 1); i += ls) {
                const int lo = 2 * j * (i / j) + (i & (j - 1)), hi = lo + j;
                const ulong a = buf[lo], b = buf[hi];
                if ((a > b) == ((lo & k) == 0)) {
                    buf[lo] = b;
                    buf[hi] = a;
                }
            }
            barrier(CLK_LOCAL_MEM_FENCE);
        }
    }
    for (int i = lid; i < n; i += ls) keys[start + i] = buf[i];
}

__kernel void merge_runs(__global const ulong *src, __global ulong *dst, const int total,
                         __global const int *seg_start,  /* [n_seg] offset in the key list */
                         __global const int *seg_prefix, /* [n_seg + 1] prefix of lengths */
                         const int n_seg, const int width)
{
    const int i = get_global_id(0);
    if (i >= total) return;
    int lo = 0, hi = n_seg;
    while (hi - lo > 1) {
        const int mid = (lo + hi) >> 1;
        if (seg_prefix[mid] <= i) lo = mid; else hi = mid;
    }
    const int len = seg_prefix[lo + 1] - seg_prefix[lo], j = i - seg_prefix[lo];
    __global const ulong *s = src + seg_start[lo];
    const int run = j / width, partner = run ^ 1;
    const int p0 = partner * width, p1 = min(p0 + width, len);
    const ulong key = s[j];
    int a = p0, b = max(p0, p1);
    while (a < b) { /* number of partner keys below key */
        const int mid = (a + b) >> 1;
        if (s[mid] < key) a = mid + 1; else b = mid;
    }
    dst[seg_start[lo] + min(run, partner) * width + (j - run * width) + (a - p0)] = key;
}

/* Runs this short are insertion-sorted first: below ~16 keys it beats merging. */
#define SERIAL_RUN 16

__kernel void sort_serial(__global ulong *keys, __global ulong *scratch,
                          __global const int *seg_start, /* [n_seg] */
                          __global const int *seg_len,   /* [n_seg] */
                          const int n_seg)
{
    const int s = get_global_id(0);
    if (s >= n_seg) return; /* no barrier in this kernel */
    const int n = seg_len[s];
    __global ulong *a = keys + seg_start[s];
    for (int r = 0; r < n; r += SERIAL_RUN) {
        const int e = min(r + SERIAL_RUN, n);
        for (int i = r + 1; i < e; ++i) {
            const ulong k = a[i];
            int j = i - 1;
            while (j >= r && a[j] > k) {
                a[j + 1] = a[j];
                --j;
            }
            a[j + 1] = k;
        }
    }
    __global ulong *src = a, *dst = scratch + seg_start[s];
    for (int w = SERIAL_RUN; w < n; w *= 2) {
        for (int lo = 0; lo < n; lo += 2 * w) {
            const int mid = min(lo + w, n), hi = min(lo + 2 * w, n);
            int i = lo, j = mid, o = lo;
            while (i < mid && j < hi) dst[o++] = src[i] <= src[j] ? src[i++] : src[j++];
            while (i < mid) dst[o++] = src[i++];
            while (j < hi) dst[o++] = src[j++];
        }
        __global ulong *t = src;
        src = dst;
        dst = t;
    }
    if (src != a)
        for (int i = 0; i < n; ++i) a[i] = src[i];
}
