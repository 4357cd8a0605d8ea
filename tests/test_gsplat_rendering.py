"""gsplat compatibility of clsplat.rasterization: every case of gsplat's own
tests/test_rasterization.py (per-view colours x SH degree x render mode x packed x batch
dimensions, at gsplat's tolerances, against clsplat.reference), gsplat 1.6's signature, and
the semantics where clsplat once differed (scale sign, ALPHA_MAX, radius rule, viewmats
gradient through torch.inverse, antialiased compensation floor, tile_size=None, SH degree 4).
"""
from __future__ import annotations

import inspect
from typing import Optional

import pytest
import torch

import clsplat
from clsplat import reference as ref

F64 = torch.float64


def gsplat_scene(batch_dims: tuple, per_view_color: bool, sh_degree: Optional[int], C: int = 3,
                 N: int = 80, width: int = 32, height: int = 24, seed: int = 42) -> dict:
    """gsplat's test scene, scaled down: means and scales uniform in [0, 1], random quats and
    opacities, C identity cameras with a centred pinhole of focal length `width`."""
    g = torch.Generator().manual_seed(seed)
    rand = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    means, quats = rand(batch_dims + (N, 3)), torch.randn(batch_dims + (N, 4), generator=g)
    scales, opacities = rand(batch_dims + (N, 3)), rand(batch_dims + (N,))
    lead = batch_dims + ((C,) if per_view_color else ())
    colors = rand(lead + (N, 3)) if sh_degree is None else rand(lead + (N, (sh_degree + 1) ** 2, 3))
    f = float(width)
    Ks = torch.tensor([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    return dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
                viewmats=torch.eye(4).expand(batch_dims + (C, 4, 4)),
                Ks=Ks.expand(batch_dims + (C, 3, 3)), width=width, height=height,
                sh_degree=sh_degree)


@pytest.mark.parametrize("per_view_color", [True, False])
@pytest.mark.parametrize("sh_degree", [None, 3])
@pytest.mark.parametrize("render_mode", ["RGB", "RGB+D", "D"])
@pytest.mark.parametrize("packed", [True, False])
@pytest.mark.parametrize("batch_dims", [(), (2,), (1, 2)])
def test_rasterization(per_view_color, sh_degree, render_mode, packed, batch_dims):
    """gsplat's test_rasterization case for case: shapes, and images and alphas within
    rtol = atol = 1e-4 of the reference (float32 in, float32 out, as in gsplat)."""
    C, H, W = 3, 24, 32
    scene = gsplat_scene(batch_dims, per_view_color, sh_degree)
    renders, alphas, meta = clsplat.rasterization(**scene, render_mode=render_mode, packed=packed)
    X = {"RGB": 3, "RGB+D": 4, "D": 1}[render_mode]
    assert renders.shape == batch_dims + (C, H, W, X)
    assert alphas.shape == batch_dims + (C, H, W, 1)
    _renders, _alphas, _ = ref._rasterization(**scene, render_mode=render_mode)
    torch.testing.assert_close(renders, _renders, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(alphas, _alphas, rtol=1e-4, atol=1e-4)
    nnz_expected = int((ref.rasterization(**scene)[2]["radii"] > 0).all(-1).sum())
    if packed:
        assert meta["means2d"].shape == (nnz_expected, 2)
        assert meta["camera_ids"].shape == meta["gaussian_ids"].shape == meta["batch_ids"].shape == (nnz_expected,)
    else:
        assert meta["means2d"].shape == batch_dims + (C, 80, 2)
        assert meta["gaussian_ids"] is None and meta["camera_ids"] is None
    assert meta["isect_offsets"].shape == batch_dims + (C, 2, 2)
    assert meta["n_batches"] == max(1, int(torch.tensor(batch_dims).prod())) and meta["n_cameras"] == C


# ---- gsplat 1.6's signature ------------------------------------------------------------------

GSPLAT_SIGNATURE = [
    ("means", inspect.Parameter.empty), ("quats", inspect.Parameter.empty),
    ("scales", inspect.Parameter.empty), ("opacities", inspect.Parameter.empty),
    ("colors", inspect.Parameter.empty), ("viewmats", inspect.Parameter.empty),
    ("Ks", inspect.Parameter.empty), ("width", inspect.Parameter.empty),
    ("height", inspect.Parameter.empty), ("near_plane", 0.01), ("far_plane", 1e10),
    ("radius_clip", 0.0), ("eps2d", 0.3), ("sh_degree", None), ("packed", True),
    ("tile_size", None), ("backgrounds", None), ("render_mode", "RGB"), ("sparse_grad", False),
    ("absgrad", False), ("rasterize_mode", "classic"), ("channel_chunk", 32),
    ("distributed", False), ("camera_model", "pinhole"), ("segmented", False), ("covars", None),
    ("with_ut", False), ("with_eval3d", False), ("radial_coeffs", None),
    ("tangential_coeffs", None), ("thin_prism_coeffs", None), ("ftheta_coeffs", None),
    ("rolling_shutter", "GLOBAL"), ("viewmats_rs", None),
]


def test_signature_is_gsplats():
    params = list(inspect.signature(clsplat.rasterization).parameters.values())
    positional = [p for p in params if p.kind == p.POSITIONAL_OR_KEYWORD]
    assert [p.name for p in positional] == [n for n, _ in GSPLAT_SIGNATURE]
    for p, (name, default) in zip(positional, GSPLAT_SIGNATURE):
        got = getattr(p.default, "name", p.default)
        assert got == default, name
    assert all(p.kind == p.KEYWORD_ONLY for p in params[len(positional):])  # clsplat's own


def small_scene(**kw):
    return dict(gsplat_scene((), False, None, C=2, N=30, width=24, height=20), **kw)


@pytest.mark.parametrize("name,value", [
    ("distributed", True), ("camera_model", "fisheye"), ("camera_model", "ortho"),
    ("camera_model", "ftheta"), ("covars", torch.eye(3).expand(30, 3, 3)), ("with_ut", True),
    ("with_eval3d", True), ("radial_coeffs", torch.zeros(2, 6)),
    ("tangential_coeffs", torch.zeros(2, 2)), ("thin_prism_coeffs", torch.zeros(2, 4)),
    ("ftheta_coeffs", object()), ("rolling_shutter", clsplat.RollingShutterType.ROLLING_TOP_TO_BOTTOM),
    ("viewmats_rs", torch.eye(4).expand(2, 4, 4)), ("channel_chunk", 0), ("packed", 1),
])
def test_unimplemented_arguments_name_themselves(name, value):
    with pytest.raises(ValueError, match=name):
        clsplat.rasterization(**small_scene(), **{name: value})


def test_defaults_of_unimplemented_arguments_are_accepted():
    scene = small_scene()
    base = clsplat.rasterization(**scene)[0]
    kw = {n: (clsplat.RollingShutterType.GLOBAL if n == "rolling_shutter" else d)
          for n, d in GSPLAT_SIGNATURE[9:] if n not in ("sh_degree",)}
    img = clsplat.rasterization(**scene, **dict(kw, segmented=True, channel_chunk=1))[0]
    assert torch.equal(img, base)
    assert torch.equal(clsplat.rasterization(**scene, tile_size=16)[0], base)  # None is 16


# ---- semantics where clsplat once differed -----------------------------------------------------

def test_scales_of_either_sign():
    """The covariance uses s^2: a negated scale renders the same image, and its gradient is
    the negated gradient."""
    scene = small_scene()
    s = scene["scales"].clone()
    s[::2, 1] *= -1
    outs = []
    for sc in (scene["scales"], s):
        x = sc.clone().requires_grad_()
        img = clsplat.rasterization(**dict(scene, scales=x))[0]
        img.square().sum().backward()
        outs.append((img.detach(), x.grad))
    assert torch.equal(outs[0][0], outs[1][0])
    assert torch.allclose(outs[1][1], outs[0][1] * torch.sign(s), atol=1e-6)


def test_alpha_max_default_and_knob():
    """An opaque stack on one pixel: with gsplat's ALPHA_MAX 0.999 the first sample leaves
    T = 0.001, and the next stops the pixel; RenderConfig(alpha_max=0.99) is the 3DGS value."""
    N = 4
    scene = dict(means=torch.tensor([[0.0, 0.0, 2.0 + 0.1 * i] for i in range(N)], dtype=F64),
                 quats=torch.tensor([[1.0, 0, 0, 0]] * N, dtype=F64),
                 scales=torch.full((N, 3), 0.5, dtype=F64), opacities=torch.ones(N, dtype=F64),
                 colors=torch.eye(3, dtype=F64)[torch.arange(N) % 3], viewmats=torch.eye(4, dtype=F64)[None],
                 Ks=torch.tensor([[[16.0, 0, 8.5], [0, 16, 8.5], [0, 0, 1]]], dtype=F64), width=16, height=16)
    centre = {}
    for amax in (0.999, 0.99):
        cfg = None if amax == 0.999 else clsplat.RenderConfig(alpha_max=amax, precision="float64")
        img, alpha, _ = clsplat.rasterization(**scene, config=cfg)
        w_img, w_alpha, _ = ref.rasterization(**scene, config=cfg or clsplat.RenderConfig())
        assert (img - w_img).abs().max() <= 1e-12 and (alpha - w_alpha).abs().max() <= 1e-12
        centre[amax] = img[0, 8, 8]
    # the means project onto the centre of pixel (8, 8): the first sample's alpha is the clamp
    assert abs(float(centre[0.999][0]) - 0.999) < 1e-12  # and it ends the pixel (T would be 1e-6)
    assert abs(float(centre[0.99][0]) - 0.99) < 1e-12 and float(centre[0.99][1]) > 0  # 3DGS: one more
    with pytest.raises(ValueError, match="alpha_max"):
        clsplat.RenderConfig(alpha_max=1.5)


@pytest.mark.parametrize("rule", ["opacity", "3.33sigma"])
def test_radius_rule_default_is_gsplats(rule):
    scene = {k: (v.double() if isinstance(v, torch.Tensor) else v) for k, v in small_scene().items()}
    scene["opacities"][:5] = torch.tensor([0.002, 0.004, 0.01, 0.5, 1.0], dtype=F64)
    cfg = clsplat.RenderConfig(radius_rule=rule) if rule != "opacity" else None
    _, _, meta = clsplat.rasterization(**scene, packed=False, config=cfg)
    _, _, w_meta = ref.rasterization(**scene, config=cfg or clsplat.RenderConfig())
    assert torch.equal(meta["radii"], w_meta["radii"])
    assert clsplat.RenderConfig().radius_rule == "opacity"
    # opacity 0.002 < ALPHA_MIN: culled by gsplat's rule, kept by the fixed one
    assert bool(meta["radii"][:, 0].any()) == (rule == "3.33sigma")


def reference_grads(scene: dict, names: tuple, loss, **kw) -> dict:
    x = {k: scene[k].clone().requires_grad_() for k in names}
    img, alpha, _ = ref.rasterization(**dict(scene, **x), **kw)
    loss(img, alpha).backward()
    return {k: v.grad for k, v in x.items()}


def engine_grads(scene: dict, names: tuple, loss, **kw) -> dict:
    x = {k: scene[k].clone().requires_grad_() for k in names}
    img, alpha, _ = clsplat.rasterization(**dict(scene, **x), **kw)
    loss(img, alpha).backward()
    return {k: v.grad for k, v in x.items()}


def weighted_loss(seed: int):
    def loss(img, alpha):
        g = torch.Generator().manual_seed(seed)
        return (img * torch.rand(img.shape, generator=g, dtype=img.dtype)).sum() + alpha.sum()
    return loss


def test_viewmats_gradient_through_inverse(make_scene):
    """With SH colours, gsplat differentiates the camera centre through torch.inverse(viewmats):
    every entry, the last row included, gets the reference's autograd gradient."""
    scene = make_scene(5, N=40, C=2, width=32, height=24, sh_degree=4)
    vm = scene["viewmats"].clone()
    vm[0, :3, :3] *= 1.1  # not a rigid motion: -R^T t and the inverse differ here
    scene["viewmats"] = vm
    names = ("viewmats", "means", "colors")
    e = engine_grads(scene, names, weighted_loss(1), packed=False)
    w = reference_grads(scene, names, weighted_loss(1))
    for k in names:
        assert (e[k] - w[k]).abs().max() <= 1e-8 * max(1.0, float(w[k].abs().max())), k
    assert e["viewmats"][:, 3].abs().max() > 0  # the inverse reaches the last row


def test_antialiased_compensation_gradient(make_scene):
    """rasterize_mode="antialiased": opacities and scales get gsplat's gradient, whose
    compensation term uses the floor 0.5 / (comp + 1e-6); the reference implements the same."""
    scene = make_scene(8, N=40, C=2, width=32, height=24, scale_range=(0.002, 0.2))
    names = ("opacities", "scales", "means", "quats")
    e = engine_grads(scene, names, weighted_loss(2), rasterize_mode="antialiased")
    w = reference_grads(scene, names, weighted_loss(2), rasterize_mode="antialiased")
    for k in names:
        assert (e[k] - w[k]).abs().max() <= 1e-8 * max(1.0, float(w[k].abs().max())), k


@pytest.mark.parametrize("per_view", [False, True])
def test_sh_degree_4_and_per_view_sh_gradients(make_scene, per_view):
    scene = make_scene(9, N=40, C=2, width=32, height=24, sh_degree=4)
    if per_view:
        scene["colors"] = torch.stack([scene["colors"], scene["colors"].flip(0)])
    names = ("colors", "means", "viewmats")
    e = engine_grads(scene, names, weighted_loss(3))
    w = reference_grads(scene, names, weighted_loss(3))
    for k in names:
        assert (e[k] - w[k]).abs().max() <= 1e-8 * max(1.0, float(w[k].abs().max())), k


def test_batch_dimension_gradients(make_scene):
    """[B, N, 3] Gaussians with [B, C, 4, 4] cameras: each batch element renders its own
    Gaussians, and every input gets the reference's gradient."""
    a, b = make_scene(10, N=30, C=2, width=24, height=20), make_scene(11, N=30, C=2, width=24, height=20)
    scene = {k: (torch.stack([a[k], b[k]]) if isinstance(a[k], torch.Tensor) else a[k]) for k in a}
    bg = torch.rand(2, 2, 3, dtype=F64, generator=torch.Generator().manual_seed(0))
    names = ("means", "quats", "scales", "opacities", "colors", "viewmats")
    e = engine_grads(scene, names, weighted_loss(4), backgrounds=bg, render_mode="RGB+ED")
    w = reference_grads(scene, names, weighted_loss(4), backgrounds=bg, render_mode="RGB+ED")
    for k in names:
        assert (e[k] - w[k]).abs().max() <= 1e-8 * max(1.0, float(w[k].abs().max())), k
    img_b1 = clsplat.rasterization(**b, backgrounds=bg[1])[0]
    assert torch.equal(clsplat.rasterization(**scene, backgrounds=bg)[0][1], img_b1)


def test_batch_shape_errors_name_the_argument():
    scene = gsplat_scene((2,), False, None, N=10)
    with pytest.raises(ValueError, match="viewmats"):
        clsplat.rasterization(**dict(scene, viewmats=scene["viewmats"][0]))
    with pytest.raises(ValueError, match="colors"):
        clsplat.rasterization(**dict(scene, colors=scene["colors"][:1]))


def test_dtype_round_trip():
    """float64 inputs rendered in float32 come back as float64, gradients too; meta["means2d"]
    is still the node on the loss path (grad and absgrad), as on another torch device."""
    scene = {k: (v.double() if isinstance(v, torch.Tensor) else v) for k, v in small_scene().items()}
    m = scene["means"].clone().requires_grad_()
    img, alpha, meta = clsplat.rasterization(**dict(scene, means=m), precision="float32", absgrad=True)
    assert img.dtype == alpha.dtype == meta["means2d"].dtype == F64
    meta["means2d"].retain_grad()
    img.sum().backward()
    assert m.grad.dtype == F64 and meta["means2d"].grad is not None
    assert meta["means2d"].absgrad.shape == meta["means2d"].shape
    assert (meta["means2d"].absgrad >= meta["means2d"].grad.abs() - 1e-6).all()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA torch device")
def test_cuda_tensors_round_trip():
    scene = {k: (v.cuda() if isinstance(v, torch.Tensor) else v) for k, v in small_scene().items()}
    m = scene["means"].clone().requires_grad_()
    img, alpha, meta = clsplat.rasterization(**dict(scene, means=m))
    assert img.device == m.device and meta["means2d"].device == m.device
    img.sum().backward()
    assert m.grad.device == m.device
    cpu = clsplat.rasterization(**{k: (v.cpu() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()})[0]
    assert torch.equal(img.cpu(), cpu)
