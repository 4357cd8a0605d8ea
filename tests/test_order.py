"""kernels/order.cl (clsplat.stages.depth_tiles): depth sort once, tiles in order (issue 35).

The new path must give the baseline's tile lists (kernels/bin.cl + sort.cl, ``sort_impl=
"tiles"``) key for key, so that images and gradients stay bitwise identical: checked on
random rectangles with heavy depth ties (including float64 depths equal only after the
float32 cast the keys use), in both layouts, both scans and many chunk counts, and on whole
renders (forward and backward) with equal depths.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

import clsplat
from clsplat import stages
from clsplat.config import RenderConfig


def random_pairs(seed: int, C: int, N: int, tiles_x: int, tiles_y: int, n_depths: int | None,
                 dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """rects [C,N,4] (about a fifth empty: culled or off-image) and depths [C,N]; with
    ``n_depths``, depths drawn from that few values so that ties are frequent."""
    g = torch.Generator().manual_seed(seed)
    x0 = torch.randint(0, tiles_x, (C, N), generator=g)
    y0 = torch.randint(0, tiles_y, (C, N), generator=g)
    x1 = torch.minimum(x0 + torch.randint(1, 5, (C, N), generator=g), torch.tensor(tiles_x))
    y1 = torch.minimum(y0 + torch.randint(1, 4, (C, N), generator=g), torch.tensor(tiles_y))
    rects = torch.stack([x0, y0, x1, y1], -1).to(torch.int32)
    empty = torch.rand(C, N, generator=g) < 0.2
    rects[empty] = torch.tensor([3, 1, 3, 2], dtype=torch.int32)  # zero width
    if n_depths:
        pool = (0.1 + 50 * torch.rand(n_depths, generator=g, dtype=torch.float64))
        depths = pool[torch.randint(0, n_depths, (C, N), generator=g)]
    else:
        depths = 0.01 + 1e4 * torch.rand(C, N, generator=g, dtype=torch.float64)
    if dtype == torch.float64:  # distinct in float64, equal once cast to float32
        depths[:, ::7] = 3.0
        depths[:, 1::7] = 3.0 + 1e-12
    return rects, depths.to(dtype)


def both(rt, cfg: RenderConfig, rects, depths, width, height, tile):
    """(offsets, keys) of the new path and of the baseline, as host tensors."""
    res = []
    for impl in ("depth", "tiles"):
        off, keys = stages.tile_lists(rt, cfg.with_(sort_impl=impl), rt.array(rects.clone()),
                                      rt.array(depths.clone()), width, height, tile)
        res.append((off.host().clone(), keys.host().clone()))
    return res


@pytest.mark.parametrize("scan", ["host", "device"])
@pytest.mark.parametrize("layout", ["serial", "bitonic"])
@pytest.mark.parametrize("chunks", [None, 1, 3, 64, 100])  # 100: serial counters too many for
# own_positions (ORDER_OWN_SCAN_MAX): a scan_counters launch on chunk-major counters
@pytest.mark.parametrize("n_depths,dtype", [(None, torch.float32), (3, torch.float32), (4, torch.float64)])
def test_same_tile_lists_as_the_per_tile_sort(rt, monkeypatch, scan, layout, chunks, n_depths, dtype):
    monkeypatch.setenv("CLSPLAT_HOST_SCAN", "1" if scan == "host" else "0")
    W, H, tile = 72, 40, 8  # 9 x 5 tiles
    rects, depths = random_pairs(chunks or 0, 3, 700, 9, 5, n_depths, dtype)
    cfg = RenderConfig(precision="float64" if dtype == torch.float64 else "float32",
                       sort_layout=layout, sort_chunks=chunks)
    (off, keys), (off_b, keys_b) = both(rt, cfg, rects, depths, W, H, tile)
    assert torch.equal(off, off_b) and torch.equal(keys, keys_b)
    # and against numpy: each segment ascending by (float32 depth bits, c*N+g)
    k = keys.numpy().view(np.uint64)
    o = off.numpy()
    for s, e in zip(o[:-1], o[1:]):
        assert np.all(k[s:e - 1] < k[s + 1:e])
    assert len(k) == int(((rects[..., 2] - rects[..., 0]) * (rects[..., 3] - rects[..., 1])).sum())


@pytest.mark.parametrize("layout,chunks", [("serial", None), ("serial", 5), ("bitonic", 5)])
def test_all_depths_equal_and_trivial_passes(rt, layout, chunks):
    """One depth for every pair: each radix pass after the first is trivial (order_small, the
    serial layout's default at this size, skips them); the lists are then in c*N+g order, as
    the baseline's."""
    rects, depths = random_pairs(5, 2, 3000, 9, 5, None, torch.float32)
    depths[:] = 7.25
    cfg = RenderConfig(sort_layout=layout, sort_chunks=chunks)
    (off, keys), (off_b, keys_b) = both(rt, cfg, rects, depths, 72, 40, 8)
    assert torch.equal(off, off_b) and torch.equal(keys, keys_b)
    ids = keys & 0xFFFFFFFF
    for s, e in zip(off[:-1].tolist(), off[1:].tolist()):
        assert bool((ids[s + 1:e] > ids[s:e - 1]).all())


def test_own_scan_threshold():
    """The chunk counts the tests use meet both sides of ORDER_OWN_SCAN_MAX (9 x 5 tiles x 3
    cameras; 256 radix bins)."""
    assert 135 * 64 * 64 <= stages.ORDER_OWN_SCAN_MAX < 135 * 100 * 100
    assert 256 * 64 * 64 <= stages.ORDER_OWN_SCAN_MAX < 256 * 100 * 100


@pytest.mark.parametrize("layout", ["serial", "bitonic"])
def test_default_chunks_split_a_large_pass(rt, layout):
    """Above ORDER_SMALL pairs the serial layout splits each pass into several chunks (what
    the default path runs at scale; the GPU layout: ~200 chunks of ORDER_GPU_CHUNK keys and
    pyopencl's scan), and the lists still equal the baseline's."""
    n = 50_000
    cfg = RenderConfig(sort_layout=layout)
    assert n > stages.ORDER_SMALL
    assert stages._order_chunks(rt, cfg, n, 256, n) > (1 if layout == "serial" else 100)
    rects, depths = random_pairs(11, 1, n, 40, 22, 50, torch.float32)
    (off, keys), (off_b, keys_b) = both(rt, cfg, rects, depths, 640, 352, 16)
    assert torch.equal(off, off_b) and torch.equal(keys, keys_b)


def test_nothing_touches_a_tile(rt, cfg32):
    rects = torch.tensor([[[2, 1, 2, 3], [0, 0, 1, 0]]], dtype=torch.int32)
    depths = torch.tensor([[1.0, 2.0]])
    off, keys = stages.depth_tiles(rt, cfg32, rt.array(rects), rt.array(depths), 64, 48, 16)
    assert keys.tensor.numel() == 0 and not off.host().any() and off.tensor.numel() == 13


def _scene(seed: int, N: int, dtype: torch.dtype, equal_depths: bool) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([(torch.rand(N, 2, generator=g) - 0.5) * 3, 3 + 2 * torch.rand(N, 1, generator=g)], 1)
    if equal_depths:  # identity camera: depth = z; three planes of Gaussians
        means[:, 2] = torch.tensor([3.0, 4.0, 4.5])[torch.randint(0, 3, (N,), generator=g)]
    xs = [means, torch.randn(N, 4, generator=g), 0.02 + 0.15 * torch.rand(N, 3, generator=g),
          0.2 + 0.7 * torch.rand(N, generator=g), torch.rand(N, 4, 3, generator=g) - 0.3]
    return [x.to(dtype) for x in xs]


@pytest.mark.parametrize("precision", ["float32", "float64"])
@pytest.mark.parametrize("equal_depths", [True, False])
def test_renders_and_gradients_bitwise_equal(rt, precision, equal_depths):
    """rasterization() with the depth sort once equals the per-tile sort bit for bit: images,
    alphas, meta's intersection lists and every gradient; two cameras."""
    dt = torch.float64 if precision == "float64" else torch.float32
    W, H = 80, 48
    vm = torch.eye(4, dtype=dt).repeat(2, 1, 1)
    vm[1, 0, 3] = 0.3  # the second camera shifted: other tiles, the same depths
    K = torch.tensor([[60.0, 0, W / 2], [0, 60, H / 2], [0, 0, 1]], dtype=dt).repeat(2, 1, 1)
    res = {}
    for impl in ("tiles", "depth"):
        xs = [x.requires_grad_() for x in _scene(7, 400, dt, equal_depths)]
        img, alpha, meta = clsplat.rasterization(*xs, vm, K, W, H, sh_degree=1, render_mode="RGB+ED",
                                                 config=RenderConfig(precision=precision, sort_impl=impl),
                                                 device=rt, packed=False)
        w = torch.linspace(-1, 1, img.numel(), dtype=dt).reshape(img.shape)
        ((img * w).sum() + alpha.square().sum()).backward()
        res[impl] = [img.detach(), alpha.detach(), meta["isect_offsets"], meta["flatten_ids"]] + [x.grad for x in xs]
    assert int(res["depth"][3].numel()) > 400  # many intersections
    for a, b in zip(res["tiles"], res["depth"]):
        assert torch.equal(a, b)


def test_default_by_device(rt):
    """None sorts by depth on CPU devices (PoCL, Oclgrind) and per tile on GPUs; an explicit
    value is kept on either."""
    assert RenderConfig().sort_impl is None
    assert stages.sort_by_depth(rt, RenderConfig()) == rt.is_cpu
    assert stages.sort_by_depth(rt, RenderConfig(sort_impl="depth"))
    assert not stages.sort_by_depth(rt, RenderConfig(sort_impl="tiles"))


def test_bad_settings_are_one_line():
    with pytest.raises(ValueError, match="^sort_impl: expected 'depth' or 'tiles'"):
        RenderConfig(sort_impl="radix")
    with pytest.raises(ValueError, match="^sort_chunks: must be >= 1"):
        RenderConfig(sort_chunks=0)
    with pytest.raises(ValueError, match="^sort_chunks: expected an int"):
        RenderConfig(sort_chunks=2.0)


@pytest.mark.parametrize("C", [1600, 1700])
def test_packed_coordinates_up_to_their_limit(rt, cfg32, monkeypatch, C):
    """1600 cameras of 40 tile rows: packed rows up to 63999, the depth sort's lists equal the
    baseline's. 1700 (68000 rows, over ORDER_PACK_MAX): tile_lists runs the baseline."""
    tiles_y = 40
    rects, depths = random_pairs(2, C, 3, 2, tiles_y, 2, torch.float32)
    if C * tiles_y > stages.ORDER_PACK_MAX:
        def refuse(*a, **k):
            raise AssertionError("depth_tiles called beyond the packed coordinates")
        monkeypatch.setattr(stages, "depth_tiles", refuse)
    cfg = cfg32.with_(sort_chunks=3)  # the chunked passes (pack, gather, unpack)
    off, keys = stages.tile_lists(rt, cfg, rt.array(rects), rt.array(depths), 32, tiles_y * 16, 16)
    off_b, keys_b = stages.tile_lists(rt, cfg.with_(sort_impl="tiles"), rt.array(rects.clone()),
                                      rt.array(depths.clone()), 32, tiles_y * 16, 16)
    assert torch.equal(off.host(), off_b.host()) and torch.equal(keys.host(), keys_b.host())
    assert keys.tensor.numel() > C


def test_memory_check_counts_the_depth_sorts_arrays(rt, cfg32, monkeypatch):
    """Pairs of one tile each: the depth sort's per-pair arrays (8 + 24 bytes) outweigh the
    per-tile sort's scratch (8 per intersection) it does not allocate; the intersection check
    sees them, spread over the intersections (16 + 24 bytes each here)."""
    seen = []
    monkeypatch.setattr(stages, "check_intersection_memory",
                        lambda rt_, total, per, reserve=0: seen.append((total, per, reserve)))
    rects = torch.tensor([[[0, 0, 1, 1], [1, 0, 2, 1], [0, 0, 0, 0], [1, 1, 2, 2]]], dtype=torch.int32)
    depths = torch.tensor([[1.0, 2.0, 3.0, 4.0]])
    stages.depth_tiles(rt, cfg32, rt.array(rects), rt.array(depths), 32, 32, 16, per_intersection=16,
                       reserve=5)
    # 3 intersections; extra = 8 x 4 pairs + 24 x 3 touching - 8 x 3 = 80 -> 27 per intersection
    assert seen == [(3, 16 + 27, 5)]
