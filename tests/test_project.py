"""kernels/project.cl (clsplat.stages.project) against clsplat.reference.project."""
from __future__ import annotations

import pytest
import torch

from clsplat.config import RenderConfig

F64 = torch.float64


def rel_err(a: torch.Tensor, b: torch.Tensor, floor: float = 1.0) -> float:
    """max |a-b| / max(|b|, floor), elementwise: relative where values are large."""
    a, b = a.to(F64), b.to(F64)
    if a.numel() == 0:
        return 0.0
    return float(((a - b).abs() / b.abs().clamp_min(floor)).max())


def check_against_reference(got: dict, want: dict, tol: float, exact_ints: bool = True) -> None:
    vis = want["visible"]
    got_vis = (got["radii"] != 0).any(-1)
    assert torch.equal(got_vis, vis), f"visibility differs at {(got_vis != vis).nonzero().tolist()}"
    if exact_ints:
        assert torch.equal(got["radii"], want["radii"])
        assert torch.equal(got["rects"], want["rects"])
    # depths are written for every pair, culled or not
    assert rel_err(got["depths"], want["depths"]) <= tol
    v = vis
    assert rel_err(got["means2d"][v], want["means2d"][v]) <= tol
    # conics: relative to the largest entry of each conic (the off-diagonal may cancel)
    scale = want["conics"][v].abs().amax(-1, keepdim=True).clamp_min(1e-300)
    if v.any():
        assert float(((got["conics"][v].to(F64) - want["conics"][v]).abs() / scale).max()) <= tol
    assert rel_err(got["opacities"][v], want["opacities"][v]) <= tol
    # culled pairs hold zeros
    assert not got["means2d"][~v].any() and not got["conics"][~v].any()
    assert not got["opacities"][~v].any() and not got["rects"][~v].any()


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_float64_matches_reference(rt, cfg64, make_scene, run_project, ref_project, seed):
    scene = make_scene(seed, N=200, C=3)
    got = run_project(rt, cfg64, scene)
    want = ref_project(scene, cfg64)
    assert want["visible"].float().mean() > 0.3  # the scene is mostly in view
    check_against_reference(got, want, 1e-9)


@pytest.mark.parametrize("tile_size", [8, 16, 32])
def test_float64_tile_rects(rt, cfg64, make_scene, run_project, ref_project, tile_size):
    scene = make_scene(10 + tile_size, N=150, C=2, width=40, height=56)
    got = run_project(rt, cfg64, scene, tile_size=tile_size)
    want = ref_project(scene, cfg64, tile_size=tile_size)
    check_against_reference(got, want, 1e-9)
    tx, ty = -(-40 // tile_size), -(-56 // tile_size)
    r = got["rects"][want["visible"]]
    assert (r[:, 0] >= 0).all() and (r[:, 2] <= tx).all() and (r[:, 1] >= 0).all() and (r[:, 3] <= ty).all()
    assert (r[:, 2] > r[:, 0]).all() and (r[:, 3] > r[:, 1]).all()


def test_float32_matches_reference(rt, cfg32, cfg64, make_scene, run_project, ref_project):
    """float32: positions to 1e-5 relative (about 1e-3 px here), conics and opacities to 1e-4
    relative to the conic's scale; integer radii may round differently by one pixel where
    3.33*sigma lies within float32 rounding of an integer, which also may change visibility
    of a pair sitting exactly on a culling boundary (we allow 1% of pairs)."""
    for seed in range(3):
        scene = make_scene(seed, N=200, C=3, dtype=torch.float32)
        got = run_project(rt, cfg32, scene)
        want = ref_project(scene, cfg64)
        vis = want["visible"] & (got["radii"] != 0).any(-1)
        mism = ((got["radii"] != 0).any(-1) != want["visible"]).float().mean()
        assert mism <= 0.01
        assert (got["radii"][vis] - want["radii"][vis]).abs().max() <= 1
        assert rel_err(got["depths"], want["depths"]) <= 1e-6
        assert rel_err(got["means2d"][vis], want["means2d"][vis]) <= 1e-5
        scale = want["conics"][vis].abs().amax(-1, keepdim=True)
        assert float(((got["conics"][vis].double() - want["conics"][vis]).abs() / scale).max()) <= 1e-4
        assert rel_err(got["opacities"][vis], want["opacities"][vis]) <= 1e-6
        assert got["means2d"].dtype == torch.float32 and got["radii"].dtype == torch.int32


def test_antialiased(rt, cfg64, make_scene, run_project, ref_project):
    scene = make_scene(5, N=200, C=2)
    got = run_project(rt, cfg64, scene, antialiased=True)
    want = ref_project(scene, cfg64, antialiased=True)
    check_against_reference(got, want, 1e-9)
    classic = ref_project(scene, cfg64)
    v = want["visible"]
    # the compensation sqrt(det_orig/det) lies in (0, 1]: opacities only shrink
    assert (want["opacities"][v] <= classic["opacities"][v] + 1e-15).all()
    assert (want["opacities"][v] < classic["opacities"][v]).any()


@pytest.mark.parametrize("rule", ["3.33sigma", "4sigma", "opacity"])
def test_radius_rules(rt, make_scene, run_project, ref_project, rule):
    cfg = RenderConfig(precision="float64", radius_rule=rule)
    scene = make_scene(7, N=200, C=2, opacity_range=(0.001, 1.0))
    scene["opacities"][::10] = 0.002  # some below alpha_min = 1/255
    got = run_project(rt, cfg, scene)
    want = ref_project(scene, cfg)
    check_against_reference(got, want, 1e-9)
    base = ref_project(scene, RenderConfig(precision="float64", radius_rule="3.33sigma"))
    v = want["visible"] & base["visible"]
    if rule == "4sigma":
        assert torch.equal(want["visible"], base["visible"])
        assert (got["radii"][v] >= base["radii"][v]).all() and (got["radii"][v] > base["radii"][v]).any()
    elif rule == "opacity":
        # pairs whose opacity is below alpha_min can never contribute and are culled
        low = scene["opacities"] < cfg.alpha_min
        assert low.any() and not got["radii"][:, low].any()
        # extent sqrt(2 ln(o / alpha_min)) < 3.33 for every opacity <= 1: radii never grow
        assert (got["radii"][v] <= base["radii"][v]).all() and (got["radii"][v] < base["radii"][v]).any()


def test_culling(rt, cfg64, camera, run_project, ref_project):
    vm, K = camera(64, 48)
    means = torch.tensor([
        [0.0, 0.0, 2.0],     # 0 visible
        [0.0, 0.0, -2.0],    # 1 behind the camera
        [0.0, 0.0, 0.005],   # 2 before the near plane (0.01)
        [0.0, 0.0, 200.0],   # 3 beyond far_plane=100
        [50.0, 0.0, 2.0],    # 4 far off-screen to the right
        [0.0, -50.0, 2.0],   # 5 far off-screen above
        [0.2, 0.1, 3.0],     # 6 small: radius 2 px (eps2d) <= radius_clip=2
        [0.0, 0.0, 0.0105],  # 7 just beyond the near plane: kept
    ], dtype=F64)
    N = len(means)
    scales = torch.full((N, 3), 0.05, dtype=F64)
    scales[6] = 1e-4
    scene = dict(means=means, quats=torch.tensor([[1.0, 0, 0, 0]], dtype=F64).repeat(N, 1),
                 scales=scales, opacities=torch.full((N,), 0.8, dtype=F64), viewmats=vm, Ks=K,
                 width=64, height=48)
    got = run_project(rt, cfg64, scene, far_plane=100.0, radius_clip=2.0)
    vis = (got["radii"] != 0).any(-1)[0]
    assert vis.tolist() == [True, False, False, False, False, False, False, True]
    assert not got["rects"][0, ~vis].any() and not got["means2d"][0, ~vis].any()
    assert torch.allclose(got["depths"][0], means[:, 2])
    # without the clip, the small one is visible (its radius is ceil(3.33*sqrt(0.3)) = 2 px)
    got2 = run_project(rt, cfg64, scene, far_plane=100.0, radius_clip=0.0)
    assert got2["radii"][0, 6].tolist() == [2, 2]
    # sweep a Gaussian across the right image border: the engine culls exactly where the
    # reference's rule (x - rx >= width) does, and both outcomes occur
    fx = K[0, 0, 0].item()
    xs_px = torch.arange(50.0, 80.0, 0.37, dtype=F64)
    m = torch.zeros(len(xs_px), 3, dtype=F64)
    m[:, 0] = (xs_px - 32) * 2.0 / fx
    m[:, 2] = 2.0
    n = len(xs_px)
    sc = dict(scene, means=m, quats=scene["quats"][:1].repeat(n, 1), scales=scene["scales"][:1].repeat(n, 1),
              opacities=scene["opacities"][:1].repeat(n))
    out = run_project(rt, cfg64, sc)
    want = ref_project(sc, cfg64)
    got_vis = (out["radii"] != 0).any(-1)
    assert torch.equal(got_vis, want["visible"])
    assert got_vis.any() and not got_vis.all()


@pytest.mark.parametrize("eps2d", [0.3, 0.0])
def test_offscreen_means_cull_exactly_as_the_full_projection(rt, cfg64, make_scene, run_project, ref_project,
                                                             eps2d):
    """project culls a pair whose mean is off the image by more than its scales' radius bound
    (common.h radius_bounds) before the EWA: that early test may only cull what the full
    computation culls. Means scattered well beyond the frustum with large, anisotropic scales
    (needles reaching into the image), cameras with off-centre principal points, one of them
    outside the image (a negative frustum limit): visibility, radii and every output as the
    reference's, and off-screen means both culled and kept, so both outcomes of the test occur."""
    scene = make_scene(7, N=3000, C=4, width=64, height=48, scale_range=(0.01, 1.5))
    g = torch.Generator().manual_seed(3)
    scene["means"] = (torch.rand(3000, 3, generator=g, dtype=F64) - 0.5) * 9.0
    scene["scales"][::5, 0] *= 20.0            # needles
    Ks = scene["Ks"].clone()
    Ks[1, 0, 2] += 40.0                        # principal point beyond the right edge
    Ks[2, 1, 2] -= 30.0                        # ... above the top edge
    scene["Ks"] = Ks
    got = run_project(rt, cfg64, scene, eps2d=eps2d)
    want = ref_project(scene, cfg64, eps2d=eps2d)
    check_against_reference(got, want, 1e-9)
    vm = scene["viewmats"]
    p = torch.einsum("cij,nj->cni", vm[:, :3, :3], scene["means"]) + vm[:, None, :3, 3]
    front = p[..., 2] > 0.01
    u = Ks[:, None, 0, 0] * p[..., 0] / p[..., 2] + Ks[:, None, 0, 2]
    v = Ks[:, None, 1, 1] * p[..., 1] / p[..., 2] + Ks[:, None, 1, 2]
    off = ~((u >= 0) & (u < 64) & (v >= 0) & (v < 48))
    assert (want["visible"] & off).sum() > 50        # kept though the mean is off the image
    assert (front & off & ~want["visible"]).sum() > 500


def test_extents_bound_where_alpha_reaches_alpha_min(rt, make_scene, run_project, ref_project, cfg64):
    """extents[c, g] = (x, y) distances beyond which alpha < ALPHA_MIN on every row/column;
    compositing skips samples past them, so they must equal sqrt(2 ln(o / ALPHA_MIN) cov_ii)."""
    from clsplat import constants as K
    scene = make_scene(seed=4, N=150, C=2)
    got = run_project(rt, cfg64, scene)
    want = ref_project(scene, cfg64)
    vis = want["visible"]
    conic = want["conics"][vis]
    det = conic[:, 0] * conic[:, 2] - conic[:, 1] ** 2
    cov_xx, cov_yy = conic[:, 2] / det, conic[:, 0] / det
    cut = torch.log(want["opacities"][vis] / K.ALPHA_MIN)
    ext = got["_proj"].extents.host()[vis]
    ok = cut >= 0
    assert torch.allclose(ext[ok, 0], torch.sqrt(2 * cut[ok] * cov_xx[ok]), rtol=1e-9)
    assert torch.allclose(ext[ok, 1], torch.sqrt(2 * cut[ok] * cov_yy[ok]), rtol=1e-9)
    assert bool((ext[~ok] == -1).all())
