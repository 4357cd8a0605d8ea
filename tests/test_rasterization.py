"""Whole renders (clsplat.rasterization) against the dense float64 clsplat.reference.rasterization,
plus gsplat's meta contract and input validation.

Tolerances. float64 renders must match the float64 reference to 1e-9: both evaluate the same
formulas in the same precision, only in a different order. float32 renders must match to 1e-5
on every pixel whose threshold decisions are unambiguous: a float32 pass evaluates
alpha >= ALPHA_MIN and next_T <= T_MIN with ~1e-7 relative error, so where the float64 value
lies within relative 1e-4 of a threshold (reference meta["ambiguous"], margin=1e-4) float32 may
legitimately include or drop one sample, changing the pixel by up to ALPHA_MIN (or T_MIN) times
a colour. Such pixels are excluded, and we assert they are rare (< 2% of pixels).
"""
from __future__ import annotations

import pytest
import torch

import clsplat
from clsplat import reference as ref

F64 = torch.float64
MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")


def render_both(scene: dict, margin: float = 1e-4, **kw):
    got = clsplat.rasterization(**scene, **kw)
    want = ref.rasterization(**{k: (v.double() if isinstance(v, torch.Tensor) else v)
                                for k, v in scene.items()},
                             **{k: (v.double() if isinstance(v, torch.Tensor) else v) for k, v in kw.items()},
                             margin=margin)
    return got, want


def depth_aware_error(got: torch.Tensor, want: torch.Tensor, mode: str, n_col: int) -> torch.Tensor:
    """Per-element error: absolute for colour and alpha-like channels, relative (to the depth
    value, floor 1) for depth channels, whose values here are ~3-6 scene units."""
    err = (got.double() - want).abs()
    if mode in ("D", "ED", "RGB+D", "RGB+ED"):
        err[..., n_col:] = err[..., n_col:] / want[..., n_col:].abs().clamp_min(1.0)
    return err


@pytest.mark.parametrize("seed", range(10))
def test_float64_random_scenes(make_scene, seed):
    C = 1 + seed % 3
    scene = make_scene(seed, N=60, C=C, width=40 if seed % 2 else 64, height=56 if seed % 2 else 48)
    (img, alpha, meta), (w_img, w_alpha, w_meta) = render_both(scene, tile_size=(8, 16, 32)[seed % 3])
    assert img.dtype == F64 and img.shape == w_img.shape == (C, scene["height"], scene["width"], 3)
    assert alpha.shape == (C, scene["height"], scene["width"], 1)
    assert (img - w_img).abs().max() <= 1e-9
    assert (alpha - w_alpha).abs().max() <= 1e-9
    assert (alpha > 0.5).any()  # the scene is really drawn


@pytest.mark.parametrize("seed", range(10))
def test_float32_random_scenes(make_scene, seed):
    scene = make_scene(100 + seed, N=60, C=2, width=40, height=56, dtype=torch.float32)
    (img, alpha, meta), (w_img, w_alpha, w_meta) = render_both(scene)
    assert img.dtype == torch.float32
    amb = w_meta["ambiguous"]
    assert amb.float().mean() < 0.02
    ok = ~amb
    assert (img.double() - w_img)[ok].abs().max() <= 1e-5
    assert (alpha.double() - w_alpha)[ok].abs().max() <= 1e-5
    # even ambiguous pixels stay within one skipped/added sample of the reference
    assert (img.double() - w_img).abs().max() <= 0.05


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_render_modes(make_scene, mode, dtype):
    """Depth channels: float64 to 1e-9 relative; float32 to 1e-5 relative (depth is a float32
    number of ~4 units accumulated over ~10 samples; ED divides by alpha, which is why pixels
    with alpha < 1e-3 are also left out in float32: there ED amplifies rounding by 1/alpha)."""
    scene = make_scene(7, N=60, C=2, width=40, height=56, dtype=dtype)
    bg = torch.rand(2, 3, generator=torch.Generator().manual_seed(1), dtype=dtype)
    (img, alpha, meta), (w_img, w_alpha, w_meta) = render_both(scene, render_mode=mode, backgrounds=bg)
    n_col = 0 if mode in ("D", "ED") else 3
    assert img.shape[-1] == n_col + (mode != "RGB")
    err = depth_aware_error(img, w_img, mode, n_col)
    if dtype == F64:
        assert err.max() <= 1e-9
    else:
        ok = ~w_meta["ambiguous"] & (w_alpha[..., 0] > 1e-3)
        assert err[ok].max() <= 1e-5
    if "D" in mode:
        d = w_img[..., -1][w_alpha[..., 0] > 0.5]
        if "ED" in mode:  # expected depth lies within the range of depths in view
            assert d.min() >= 2.0 and d.max() <= 7.0
    if n_col:  # background shows where nothing is drawn
        empty = w_alpha[..., 0] == 0
        assert empty.any()
        assert torch.allclose(img[..., :3][empty].double(), bg.double()[:, None, None, :].expand(2, 56, 40, 3)[empty])


@pytest.mark.parametrize("D", [1, 5, 32])
@pytest.mark.parametrize("per_camera", [False, True])
def test_feature_channels(make_scene, D, per_camera):
    scene = make_scene(D, N=50, C=2, width=40, height=56, D=D, colors_per_camera=per_camera)
    bg = torch.rand(2, D, dtype=F64, generator=torch.Generator().manual_seed(D))
    (img, alpha, _), (w_img, w_alpha, _) = render_both(scene, backgrounds=bg, render_mode="RGB+ED")
    assert img.shape == (2, 56, 40, D + 1)
    err = depth_aware_error(img, w_img, "RGB+ED", D)
    assert err.max() <= 1e-9


@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
def test_sh_colours(make_scene, degree):
    scene = make_scene(degree, N=50, C=2, width=40, height=56, sh_degree=degree, K_extra=degree)
    (img, alpha, _), (w_img, w_alpha, _) = render_both(scene)
    assert (img - w_img).abs().max() <= 1e-9
    s32 = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    (img32, _, _), (w32, _, m32) = render_both(s32)
    ok = ~m32["ambiguous"]
    assert (img32.double() - w32)[ok].abs().max() <= 1e-5


def test_antialiased_and_radius_rules(make_scene):
    scene = make_scene(3, N=60, C=2, width=40, height=56)
    # a RenderConfig carries its own precision (default float32), so float64 is asked for here
    for kw in (dict(rasterize_mode="antialiased"),
               dict(config=clsplat.RenderConfig(radius_rule="opacity", precision="float64")),
               dict(config=clsplat.RenderConfig(radius_rule="4sigma"), precision="float64"), dict(eps2d=0.1, radius_clip=1.5),
               dict(near_plane=3.0, far_plane=4.5)):
        (img, alpha, _), (w_img, w_alpha, _) = render_both(scene, **kw)
        assert (img - w_img).abs().max() <= 1e-9, kw
        assert (alpha - w_alpha).abs().max() <= 1e-9, kw


def test_n_zero_renders_background(camera):
    vm, K = camera(40, 56)
    vm, K = vm.repeat(2, 1, 1), K.repeat(2, 1, 1)
    bg = torch.tensor([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]], dtype=F64)
    z = torch.zeros
    for mode in MODES:
        img, alpha, meta = clsplat.rasterization(z(0, 3, dtype=F64), z(0, 4, dtype=F64), z(0, 3, dtype=F64),
                                                 z(0, dtype=F64), z(0, 3, dtype=F64), vm, K, 40, 56,
                                                 backgrounds=bg, render_mode=mode)
        assert not alpha.any() and alpha.shape == (2, 56, 40, 1)
        if mode.startswith("RGB"):
            assert torch.equal(img[..., :3], bg[:, None, None, :].expand(2, 56, 40, 3))
        if mode != "RGB":
            assert not img[..., -1].any()
        assert meta["means2d"].shape == (0, 2) and meta["flatten_ids"].numel() == 0  # packed
    _, _, meta = clsplat.rasterization(z(0, 3, dtype=F64), z(0, 4, dtype=F64), z(0, 3, dtype=F64),
                                       z(0, dtype=F64), z(0, 3, dtype=F64), vm, K, 40, 56, packed=False)
    assert meta["means2d"].shape == (2, 0, 2) and meta["flatten_ids"].numel() == 0


def test_bitwise_deterministic(make_scene):
    scene = make_scene(11, N=150, C=2, width=40, height=56, dtype=torch.float32)
    scene["means"][:20, 2] = scene["means"][20:40, 2]  # some shared coordinates
    a = clsplat.rasterization(**scene, render_mode="RGB+ED")
    b = clsplat.rasterization(**scene, render_mode="RGB+ED")
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    assert torch.equal(a[2]["flatten_ids"], b[2]["flatten_ids"])


def test_meta_contract(make_scene):
    C, N, W, H, ts = 2, 40, 40, 56, 16
    scene = make_scene(12, N=N, C=C, width=W, height=H)
    img, alpha, meta = clsplat.rasterization(**scene, tile_size=ts, packed=False)
    _, _, w_meta = ref.rasterization(**scene)
    shapes = {"means2d": (C, N, 2), "radii": (C, N, 2), "depths": (C, N), "conics": (C, N, 3),
              "opacities": (C, N), "isect_offsets": (C, 4, 3)}
    for k, s in shapes.items():
        assert tuple(meta[k].shape) == s, k
    assert meta["radii"].dtype == torch.int32 and meta["means2d"].dtype == F64
    assert meta["tile_width"] == 3 and meta["tile_height"] == 4
    assert meta["width"] == W and meta["height"] == H and meta["n_cameras"] == C
    assert meta["flatten_ids"].dim() == 1 and meta["flatten_ids"].dtype == torch.int32
    assert torch.equal(meta["radii"], w_meta["radii"])
    for k in ("means2d", "conics", "depths", "opacities"):
        assert (meta[k].detach() - w_meta[k]).abs().max() <= 1e-9 * max(1.0, float(w_meta[k].abs().max())), k
    # isect_offsets start each tile's run of flatten_ids, which hold c*N+g of visible pairs
    ids = meta["flatten_ids"].long()
    assert (ids >= 0).all() and (ids < C * N).all()
    vis = (meta["radii"] > 0).any(-1).reshape(-1)
    assert vis[ids].all()
    off = meta["isect_offsets"].reshape(-1)
    assert off[0] == 0 and (off[1:] >= off[:-1]).all() and off[-1] <= len(ids)
    # means2d is a non-leaf tensor that accepts retain_grad()
    scene2 = dict(scene, means=scene["means"].clone().requires_grad_(True))
    _, _, m2 = clsplat.rasterization(**scene2, packed=False)
    m2["means2d"].retain_grad()
    assert not m2["means2d"].is_leaf


# ---- bad input: every failure is a ValueError naming the argument ---------------------------

@pytest.fixture
def good(make_scene):
    return make_scene(0, N=8, C=2, width=32, height=24)


def expect_error(name, **kw):
    with pytest.raises(ValueError) as exc:
        clsplat.rasterization(**kw)
    assert name in str(exc.value), str(exc.value)
    return exc.value


TENSORS = ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")


@pytest.mark.parametrize("name", TENSORS)
def test_bad_shapes(good, name):
    bad = dict(good)
    x = good[name]
    if name == "means":  # N comes from means, so a wrong N there is reported on quats
        bad[name] = torch.cat([x, x[:, :1]], 1)
    else:
        bad[name] = torch.cat([x, x[:1]], 0) if name not in ("viewmats", "Ks") else x[..., :2]
    expect_error(name, **bad)
    bad[name] = x.reshape(-1) if x.dim() > 1 else x[:, None]  # wrong rank
    expect_error(name, **bad)


@pytest.mark.parametrize("name", TENSORS)
@pytest.mark.parametrize("dtype", [torch.int32, torch.float16, torch.bool])
def test_bad_dtypes(good, name, dtype):
    expect_error(name, **dict(good, **{name: good[name].to(dtype)}))


@pytest.mark.parametrize("name", TENSORS)
def test_bad_device(good, name):
    expect_error(name, **dict(good, **{name: good[name].to("meta")}))


@pytest.mark.parametrize("name", TENSORS)
@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_non_finite(good, name, value):
    x = good[name].clone()
    x.reshape(-1)[1] = value
    expect_error(name, **dict(good, **{name: x}))


def test_non_finite_backgrounds(good):
    bg = torch.zeros(2, 3, dtype=F64)
    bg[1, 2] = float("nan")
    expect_error("backgrounds", **good, backgrounds=bg)
    expect_error("backgrounds", **good, backgrounds=torch.zeros(2, 4, dtype=F64))


@pytest.mark.parametrize("name", ["width", "height"])
@pytest.mark.parametrize("value", [0, -3, 20000, 32.0, "32", None, True])
def test_bad_image_size(good, name, value):
    expect_error(name, **dict(good, **{name: value}))


@pytest.mark.parametrize("kw,name", [
    (dict(render_mode="RGBD"), "render_mode"), (dict(render_mode="rgb"), "render_mode"),
    (dict(tile_size=12), "tile_size"), (dict(tile_size=0), "tile_size"), (dict(tile_size=16.0), "tile_size"),
    (dict(tile_size=64), "tile_size"), (dict(device="no-such-device"), "device"),
    (dict(device="7:3"), "device"), (dict(near_plane=0.0), "near_plane"),
    (dict(near_plane=2.0, far_plane=1.0), "far_plane"), (dict(eps2d=-1.0), "eps2d"),
    (dict(radius_clip=-1.0), "radius_clip"), (dict(near_plane=float("nan")), "near_plane"),
    (dict(rasterize_mode="fancy"), "rasterize_mode"), (dict(sh_degree=5), "sh_degree"),
])
def test_bad_options(good, kw, name):
    expect_error(name, **dict(good, **kw))


def test_unknown_device_is_device_error(good):
    with pytest.raises(clsplat.DeviceError) as exc:
        clsplat.rasterization(**good, device="no-such-device")
    assert isinstance(exc.value, ValueError) and "device" in str(exc.value)


def test_sh_degree_too_big_for_K(make_scene):
    scene = make_scene(0, N=8, C=1, sh_degree=1)  # K = 4
    expect_error("colors", **dict(scene, sh_degree=2))
    expect_error("colors", **dict(scene, sh_degree=3))


def test_bad_values(good):
    q = good["quats"].clone()
    q[3] = 0
    expect_error("quats", **dict(good, quats=q))
    for o in (1.0001, -0.01):
        op = good["opacities"].clone()
        op[0] = o
        expect_error("opacities", **dict(good, opacities=op))
    K = good["Ks"].clone()
    K[1, 0, 0] = 0
    expect_error("Ks", **dict(good, Ks=K))
    expect_error("viewmats", **dict(good, viewmats=good["viewmats"][:0], Ks=good["Ks"][:0]))
    expect_error("colors", **dict(good, colors=good["colors"][:, :0]))


def test_build_error_carries_log_and_options(rt):
    with pytest.raises(clsplat.BuildError) as exc:
        rt.program("composite", {"REAL_DOUBLE": 0, "TILE": 16, "PIX": 3, "BATCH": 64, "CHANNELS": 3,
                                 "SAVE_LAST": 0})
    e = exc.value
    assert "-DPIX=3" in e.options and "-DPIX=3" in str(e)
    assert "PIX must be 1, 2, 4, 8 or 16" in e.log
    assert e.stage == "composite" and e.device == rt.name
