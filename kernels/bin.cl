/* bin.cl — stage 3: tile binning.
 *
 * count_tiles: per tile, how many (camera, Gaussian) pairs touch it.
 * An exclusive scan of those counts (pyopencl's scan, on the host side) gives each tile's
 * segment in the intersection list; scatter_keys then writes every pair's key into its
 * tile's segment. The order inside a segment depends on atomic timing, which is why the
 * sort stage orders each segment by a total key (depth bits, id) afterwards.
 *
 * A segment index is (camera, tile), so a key only needs the depth bits and the id.
 * Build parameters: REAL_DOUBLE.
 */

__kernel void count_tiles(const int CN, const int tiles_x, const int tiles_per_cam, const int N,
                          __global const int *rects,            /* [C, N, 4] */
                          __global volatile int *tile_counts)   /* [C * tiles_per_cam] */
{
    const int cg = get_global_id(0);
    if (cg >= CN) return;
    const int4 r = vload4(cg, rects);
    const int base = (cg / N) * tiles_per_cam;
    for (int ty = r.y; ty < r.w; ++ty)
        for (int tx = r.x; tx < r.z; ++tx) atomic_inc(&tile_counts[base + ty * tiles_x + tx]);
}

__kernel void scatter_keys(const int CN, const int tiles_x, const int tiles_per_cam, const int N,
                           __global const int *rects,         /* [C, N, 4] */
                           __global const REAL *depths,       /* [C, N] */
                           __global const int *tile_offsets,  /* [C * tiles_per_cam + 1] */
                           __global volatile int *cursor,     /* [C * tiles_per_cam], zeroed */
                           __global ulong *keys)              /* [M] */
{
    const int cg = get_global_id(0);
    if (cg >= CN) return;
    const int4 r = vload4(cg, rects);
    if (r.z <= r.x) return;
    const int base = (cg / N) * tiles_per_cam;
    const ulong key = depth_key(depths[cg], (uint)cg);
    for (int ty = r.y; ty < r.w; ++ty)
        for (int tx = r.x; tx < r.z; ++tx) {
            const int t = base + ty * tiles_x + tx;
            keys[tile_offsets[t] + atomic_inc(&cursor[t])] = key;
        }
}
