"""kernels/bin.cl (clsplat.stages.bin_tiles) and clsplat.stages.tile_ranges."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from clsplat import stages


def expected_intersections(rects: torch.Tensor, tiles_x: int, tiles_y: int) -> list:
    """Every (camera, Gaussian, tile) from the tile rectangles, as (segment, cg) pairs."""
    C, N, _ = rects.shape
    out = []
    r = rects.numpy()
    for c in range(C):
        for g in range(N):
            x0, y0, x1, y1 = r[c, g]
            for ty in range(y0, y1):
                for tx in range(x0, x1):
                    out.append((c * tiles_x * tiles_y + ty * tiles_x + tx, c * N + g))
    return out


def test_projection_tile_counts_give_the_rectangles_totals(rt, cfg32, make_scene, run_project, monkeypatch):
    """The projection's per-pair tile counts (Projection.tiles, what the intersection count and
    the backward's slot offsets sum) equal the rectangles' areas, culled pairs 0; counted from
    them, the total, the touching pairs and the slot offsets are the rectangles' own. Below
    TILE_COUNTS_MIN_PAIRS pairs the projection writes none."""
    assert run_project(rt, cfg32, make_scene(5, N=10, C=1))["_proj"].tiles is None
    monkeypatch.setattr(stages, "TILE_COUNTS_MIN_PAIRS", 1)
    scene = make_scene(5, N=300, C=3, width=40, height=56, dtype=torch.float32)
    scene["means"] = scene["means"] * 4  # some beside or behind a camera
    got = run_project(rt, cfg32, scene, tile_size=8)
    p = got["_proj"]
    r = got["rects"]
    area = ((r[..., 2] - r[..., 0]) * (r[..., 3] - r[..., 1])).to(torch.int32)
    assert torch.equal(p.tiles.host(), area)
    assert (area == 0).any() and (area > 1).any()
    from_rects, from_tiles = [], []
    a = stages._intersections(rt, p.rects, 16, 0, pair_tiles=from_rects)
    b = stages._intersections(rt, p.rects, 16, 0, pair_tiles=from_tiles, tiles=p.tiles)
    assert a == b and a[0] == int(area.sum()) and a[1] == int((area > 0).sum())
    assert torch.equal(stages.isect_offsets(rt, p.rects, from_rects[0]).host(),
                       stages.isect_offsets(rt, p.rects, from_tiles[0]).host())


@pytest.mark.parametrize("pooled", [True, False])
def test_isect_offsets_are_the_exclusive_prefix_of_the_tile_counts(rt, pooled, monkeypatch):
    """The backward's slot offsets (numpy's scan for few pairs, torch's int32 scan from
    TORCH_SCAN_MIN_PAIRS on; written into a pooled array or, with the pool off, uploaded) equal
    numpy's int64 exclusive prefix of the tile counts, culled pairs (0 tiles) included, down to
    one pair."""
    if not pooled:
        monkeypatch.setattr(rt, "pool_limit", 0)
        assert not rt.pools
    rng = np.random.default_rng(3)
    assert 1000 < stages.TORCH_SCAN_MIN_PAIRS < 70_001  # both scans below
    for P in (1, 2, 1000, 70_001):
        n = np.where(rng.random(P) < 0.3, rng.integers(1, 9, P), 0).astype(np.int32)
        want = (np.cumsum(n.astype(np.int64)) - n).astype(np.int32)
        got = stages.isect_offsets(rt, None, n).host().reshape(-1).numpy()
        assert got.dtype == np.int32 and np.array_equal(got, want), P


@pytest.mark.parametrize("scan", ["host", "device"])
@pytest.mark.parametrize("tile_size,precision", [(16, "float64"), (8, "float32"), (32, "float64"), (4, "float32")])
def test_bin_counts_offsets_and_keys(rt, make_scene, run_project, ref_project, tile_size, precision, scan,
                                     monkeypatch):
    """Both prefix scans (the host's, PoCL's default, and pyopencl's on the device) give the
    exact tile offsets."""
    from clsplat.config import RenderConfig
    monkeypatch.setenv("CLSPLAT_HOST_SCAN", "1" if scan == "host" else "0")
    cfg = RenderConfig(precision=precision)
    W, H = 40, 56
    scene = make_scene(30 + tile_size, N=120, C=3, width=W, height=H,
                       dtype=torch.float64 if precision == "float64" else torch.float32)
    got = run_project(rt, cfg, scene, tile_size=tile_size)
    if precision == "float64":  # the rectangles themselves are checked against the reference
        assert torch.equal(got["rects"], ref_project(scene, cfg, tile_size=tile_size)["rects"])
    tx, ty = -(-W // tile_size), -(-H // tile_size)
    offsets, keys = stages.bin_tiles(rt, cfg, got["_proj"].rects, got["_proj"].depths, W, H, tile_size)
    off = offsets.host().numpy().astype(np.int64)
    k = keys.host().numpy().view(np.uint64)
    inter = expected_intersections(got["rects"], tx, ty)
    C = 3
    counts = np.bincount([s for s, _ in inter], minlength=C * tx * ty)
    assert off.shape == (C * tx * ty + 1,)
    assert off[0] == 0 and np.array_equal(np.diff(off), counts)
    assert len(k) == off[-1] == len(inter)
    # every (camera, Gaussian, tile) exactly once, in its own tile's segment
    seg_of = np.repeat(np.arange(C * tx * ty), counts)
    ids = (k & np.uint64(0xFFFFFFFF)).astype(np.int64)
    assert sorted(zip(seg_of.tolist(), ids.tolist())) == sorted(inter)
    # the high word is the float32 depth bits
    depths32 = got["depths"].reshape(-1).to(torch.float32).numpy()
    assert np.array_equal((k >> np.uint64(32)).astype(np.uint32), depths32[ids].view(np.uint32))
    # tile_ranges: [C, ty, tx, 2] (start, end), consistent with the offsets
    rng = stages.tile_ranges(offsets, C, ty, tx)
    assert rng.shape == (C, ty, tx, 2)
    flat = rng.reshape(-1, 2).numpy()
    assert np.array_equal(flat[:, 0], off[:-1]) and np.array_equal(flat[:, 1], off[1:])
    assert (flat[:, 1] >= flat[:, 0]).all()


def test_bin_nothing_visible(rt, cfg32, make_scene, run_project):
    scene = make_scene(1, N=20, C=1)
    scene["means"][:, 2] = -5.0  # everything behind the (identity) camera
    scene["viewmats"] = torch.eye(4, dtype=torch.float64)[None]
    got = run_project(rt, cfg32, scene)
    assert not got["radii"].any()
    offsets, keys = stages.bin_tiles(rt, cfg32, got["_proj"].rects, got["_proj"].depths, 64, 48, 16)
    assert keys.tensor.numel() == 0 and not offsets.host().any()
    assert tuple(stages.tile_ranges(offsets, 1, 3, 4).shape) == (1, 3, 4, 2)


def test_intersections_over_device_limit_are_a_clear_error():
    """Huge Gaussians in many cameras: more intersections than the device can hold is a
    ValueError naming the arguments, not an allocation failure or a crash."""
    import clsplat
    N, C = 200_000, 4
    means = torch.zeros(N, 3)
    means[:, 2] = 5.0
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(N, 1)
    scales = torch.full((N, 3), 50.0)
    vm = torch.eye(4).repeat(C, 1, 1)
    K = torch.tensor([[[500.0, 0, 1024], [0, 500, 1024], [0, 0, 1]]]).repeat(C, 1, 1)
    with pytest.raises(ValueError, match="intersections"):
        clsplat.rasterization(means, quats, scales, torch.full((N,), 0.5), torch.rand(N, 3), vm, K,
                              2048, 2048)


def test_bad_host_scan_setting_is_one_line(rt, cfg32, make_scene, run_project, monkeypatch):
    scene = make_scene(2, N=20, C=1)
    got = run_project(rt, cfg32, scene)
    monkeypatch.setenv("CLSPLAT_HOST_SCAN", "yes")
    with pytest.raises(ValueError, match="^CLSPLAT_HOST_SCAN: expected 0, 1 or unset"):
        stages.bin_tiles(rt, cfg32, got["_proj"].rects, got["_proj"].depths, 64, 48, 16)


def test_rasterization_counts_from_tiles_or_rectangles_alike(make_scene, monkeypatch):
    """A render whose intersections and slot offsets are counted from the projection's tile
    counts gives the bits of one counted from the rectangles: image, alpha and every gradient."""
    import clsplat

    def run(min_pairs: int) -> list:
        monkeypatch.setattr(stages, "TILE_COUNTS_MIN_PAIRS", min_pairs)
        sc = make_scene(9, N=400, C=3, width=40, height=56, dtype=torch.float32)
        sc["means"] = sc["means"] * 3
        p = {k: sc[k].clone().requires_grad_() for k in ("means", "quats", "scales", "opacities", "colors")}
        img, alpha, _ = clsplat.rasterization(p["means"], p["quats"], p["scales"], p["opacities"], p["colors"],
                                              sc["viewmats"], sc["Ks"], 40, 56)
        (img.square().sum() + alpha.sum()).backward()
        return [img.detach(), alpha.detach()] + [p[k].grad for k in p]

    for a, b in zip(run(1), run(1 << 40)):
        assert torch.equal(a, b)
