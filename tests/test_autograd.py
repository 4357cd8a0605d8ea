"""clsplat/autograd.py: gradients of rasterization() through the backward kernels.

gradcheck runs the float64 kernels against finite differences (fast mode: it checks
u^T J v for random u, v, one backward instead of one per output pixel); float32 gradients are compared
with the float64 reference's autograd; determinism, retain_grad/absgrad, specialisation and
bad grad_output are checked here too.
"""
from __future__ import annotations

import pytest
import torch

import clsplat
from clsplat import reference as ref

F64 = torch.float64
NAMES = ("means", "quats", "scales", "opacities", "colors", "viewmats", "backgrounds")


def _inputs(scene: dict, bg: bool = True) -> list[torch.Tensor]:
    C = scene["viewmats"].shape[0]
    D = 3 if "sh_degree" in scene else scene["colors"].shape[-1]
    g = torch.Generator().manual_seed(7)
    xs = [scene[k] for k in NAMES[:6]]
    xs.append(torch.rand(C, D, generator=g, dtype=F64).to(scene["means"].dtype))
    return [x.clone().requires_grad_() for x in xs]


def _render(fn, xs, scene, **kw):
    return fn(xs[0], xs[1], xs[2], xs[3], xs[4], xs[5], scene["Ks"], scene["width"],
              scene["height"], backgrounds=xs[6], sh_degree=scene.get("sh_degree"), **kw)


def _grads(fn, scene, weight_mask=None, **kw):
    """Gradients of a fixed weighted sum of both outputs (weights vary per pixel and channel,
    so every output element matters)."""
    xs = _inputs(scene)
    r, a, meta = _render(fn, xs, scene, **kw)
    w = torch.linspace(0.5, 1.5, r.numel(), dtype=r.dtype).reshape(r.shape)
    wa = torch.linspace(1.0, -1.0, a.numel(), dtype=a.dtype).reshape(a.shape)
    if weight_mask is not None:
        w = w * weight_mask[..., None]
        wa = wa * weight_mask[..., None]
    ((r * w).sum() + (a * wa).sum()).backward()
    return [x.grad for x in xs], meta


def _gradcheck(scene, xs, **kw) -> bool:
    def f(*args):
        r, a, _ = _render(clsplat.rasterization, list(args), scene, **kw)
        return r, a

    return torch.autograd.gradcheck(f, xs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


@pytest.mark.parametrize("mode", ["RGB", "D", "ED", "RGB+D", "RGB+ED"])
def test_gradcheck_render_modes(make_scene, mode):
    scene = make_scene(seed=3, N=6, C=2, width=24, height=16, scale_range=(0.15, 0.4))
    xs = _inputs(scene)
    if mode in ("D", "ED"):
        xs[4].requires_grad_(False)  # colours do not enter a depth-only render
        xs[6].requires_grad_(False)
    assert _gradcheck(scene, xs, render_mode=mode)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_gradcheck_sh(make_scene, degree):
    scene = make_scene(seed=5, N=5, C=2, width=24, height=16, sh_degree=degree, K_extra=1,
                       scale_range=(0.15, 0.4))
    assert _gradcheck(scene, _inputs(scene), render_mode="RGB+ED")


def test_gradcheck_antialiased_and_per_camera_colors(make_scene):
    scene = make_scene(seed=11, N=6, C=2, width=24, height=16, D=2, colors_per_camera=True,
                       scale_range=(0.05, 0.3))
    assert _gradcheck(scene, _inputs(scene), rasterize_mode="antialiased")


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("sh", [None, 3])
def test_float64_matches_reference_autograd(make_scene, seed, sh):
    scene = make_scene(seed=seed, N=80, C=2, width=48, height=40, sh_degree=sh)
    g_engine, _ = _grads(clsplat.rasterization, scene, render_mode="RGB+ED")
    g_ref, _ = _grads(ref.rasterization, scene, render_mode="RGB+ED")
    for name, a, b in zip(NAMES, g_engine, g_ref):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-9 * (1 + b.abs().max().item())), name


@pytest.mark.parametrize("seed", range(3))
def test_float32_gradients_match_float64_reference(make_scene, seed):
    """float32 gradients within 1e-4 relative L2 of the float64 reference.

    Pixels where a threshold decision (alpha_min, t_min) is within 1e-4 of flipping are
    weighted out: there float32 may legitimately take the other branch (a jump, not an error).
    1e-4 is ~1000 float32 ulps, room for the sums over hundreds of pixels per Gaussian.
    """
    scene = make_scene(seed=seed, N=150, C=2, width=64, height=48)
    _, _, meta = _render(ref.rasterization, _inputs(scene), scene, margin=1e-4)
    mask = (~meta["ambiguous"]).to(F64)
    assert mask.mean() > 0.95
    g_ref, _ = _grads(ref.rasterization, scene, weight_mask=mask)
    s32 = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    g32, _ = _grads(clsplat.rasterization, s32, weight_mask=mask.float())
    for name, a, b in zip(NAMES, g32, g_ref):
        assert a.dtype == torch.float32
        rel = ((a.double() - b).norm() / b.norm()).item()
        assert rel < 1e-4, (name, rel)


def test_backward_is_bitwise_deterministic(make_scene):
    scene = make_scene(seed=1, N=3000, C=2, width=128, height=96, dtype=torch.float32)
    g1, m1 = _grads(clsplat.rasterization, scene, absgrad=True)
    g2, m2 = _grads(clsplat.rasterization, scene, absgrad=True)
    for name, a, b in zip(NAMES, g1, g2):
        assert torch.equal(a, b), name


@pytest.mark.parametrize("dtype,kw", [
    (torch.float32, dict(absgrad=True)),
    (torch.float32, dict(packed=False, render_mode="RGB+D", rasterize_mode="antialiased")),
    (F64, dict(render_mode="RGB+ED", bwd_divide=True)),
])
def test_small_call_paths_give_the_general_paths_bits(make_scene, monkeypatch, dtype, kw):
    """A small call's tile lists launched behind the projection (stages.early_tile_lists) and
    the per-Gaussian backward's own sum of the slots (FUSED_REDUCE) give the images, gradients,
    absgrad and tile lists of the general paths bit for bit; with both off, the launches are the
    general ones (order_small after a wait, reduce_slots)."""
    from clsplat import stages
    rt = clsplat.get_runtime()
    scene = make_scene(seed=5, N=80, C=2, width=48, height=40, dtype=dtype)

    def run():
        events = []
        g, meta = _grads(clsplat.rasterization, scene, events=events, **kw)
        names = [name for name, _ in events]
        absg = meta["means2d"].absgrad if kw.get("absgrad") else None
        return g, meta, absg, names

    g1, m1, a1, names1 = run()
    monkeypatch.setattr(stages, "EARLY_TILES_MAX", 0)
    monkeypatch.setattr(stages, "FUSED_REDUCE_VALUES", 0)
    g2, m2, a2, names2 = run()
    for name, a, b in zip(NAMES, g1, g2):
        assert torch.equal(a, b), name
    assert (a1 is None and a2 is None) or torch.equal(a1, a2)
    for k in ("isect_offsets", "flatten_ids", "isect_ids"):
        assert torch.equal(m1[k], m2[k]), k
    if rt.pools and stages.backward_gaussian(rt, clsplat.RenderConfig()):
        assert "reduce" not in names1 and "reduce" in names2


def test_means2d_retain_grad_and_absgrad(make_scene):
    scene = make_scene(seed=2, N=60, C=2, width=48, height=40)
    xs = _inputs(scene)
    r, a, meta = _render(clsplat.rasterization, xs, scene, absgrad=True, packed=False)
    meta["means2d"].retain_grad()
    r.sum().backward()
    g = meta["means2d"].grad
    assert g is not None and g.shape == (2, 60, 2)
    absg = meta["means2d"].absgrad
    assert absg.shape == (2, 60, 2)
    assert bool((absg >= g.abs() - 1e-12).all()) and absg.sum() > 0
    # the reference's means2d is a graph node too: the screen-space gradients agree
    xr = _inputs(scene)
    rr, _, mr = _render(ref.rasterization, xr, scene)
    mr["means2d"].retain_grad()
    rr.sum().backward()
    assert torch.allclose(g, mr["means2d"].grad, atol=1e-9)


def test_only_requested_gradients_are_built(make_scene, rt):
    scene = make_scene(seed=4, N=40, C=1, width=32, height=32)
    xs = [scene[k].clone() for k in NAMES[:6]]
    xs[0].requires_grad_()  # geometry only: colours are frozen
    r, a, _ = clsplat.rasterization(*xs, scene["Ks"], 32, 32)
    r.sum().backward()
    assert xs[0].grad is not None and xs[4].grad is None
    bwd = [" ".join(k[1]) for k in rt._programs if "-DBWD_DIVIDE=0" in k[1]]
    assert any("-DCOLOR_GRAD=0" in o and "-DGEOM_GRAD=1" in o for o in bwd)
    # colours only: no geometry gradient is computed
    xs = [scene[k].clone() for k in NAMES[:6]]
    xs[4].requires_grad_()
    r, a, _ = clsplat.rasterization(*xs, scene["Ks"], 32, 32)
    r.sum().backward()
    opts = [" ".join(k[1]) for k in rt._programs]
    assert any("-DCOLOR_GRAD=1" in o and "-DGEOM_GRAD=0" in o for o in opts)
    # nothing requires grad: the forward saves nothing for backward (no SAVE_LAST build)
    with torch.no_grad():
        r2, _, _ = clsplat.rasterization(*[scene[k] for k in NAMES[:6]], scene["Ks"], 32, 32)
    assert r2.grad_fn is None


def test_bad_grad_output(make_scene):
    scene = make_scene(seed=6, N=30, C=1, width=32, height=24)
    xs = _inputs(scene)
    r, a, _ = _render(clsplat.rasterization, xs, scene)
    bad = torch.ones_like(r)
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="grad_output"):
        r.backward(bad)
    r, a, _ = _render(clsplat.rasterization, xs, scene)
    with pytest.raises(RuntimeError, match="shape"):
        r.backward(torch.ones(3, 3, dtype=r.dtype))


@pytest.mark.parametrize("bad", ["nan", "inf"])
def test_bad_alpha_grad_output(make_scene, bad):
    """A NaN or Inf in the alphas' gradient is refused once, naming it, whether T's gradient also
    arrives from the background blend (the two are combined, then checked) or not."""
    scene = make_scene(seed=6, N=30, C=1, width=32, height=24)
    xs = _inputs(scene)
    for with_bg in (True, False):
        r, a, _ = clsplat.rasterization(xs[0], xs[1], xs[2], xs[3], xs[4], xs[5], scene["Ks"],
                                        scene["width"], scene["height"],
                                        backgrounds=xs[6] if with_bg else None)
        g = torch.ones_like(a)
        g[0, 3, 5, 0] = float(bad)
        with pytest.raises(ValueError, match="render_alphas"):
            torch.autograd.backward([r.sum(), a], [None, g])


def test_replay_and_divide_agree(make_scene):
    scene = make_scene(seed=8, N=200, C=1, width=48, height=48, opacity_range=(0.8, 0.999))
    g1, _ = _grads(clsplat.rasterization, scene)
    g2, _ = _grads(clsplat.rasterization, scene, bwd_divide=True)
    for name, a, b in zip(NAMES, g1, g2):
        assert torch.allclose(a, b, rtol=1e-8, atol=1e-10 * (1 + b.abs().max().item())), name


def test_renders_free_their_buffers(make_scene):
    """Nothing a differentiable render kept for backward outlives it (the outputs were once
    held by their own autograd node: a cycle through C++ that the GC cannot free)."""
    import gc
    scene = make_scene(seed=6, N=40, C=2, width=32, height=24, dtype=torch.float32)

    def live() -> int:
        gc.collect()
        return sum(isinstance(o, torch.Tensor) for o in gc.get_objects())

    def render(backward: bool) -> None:
        xs = _inputs(scene)
        r, a, _ = _render(clsplat.rasterization, xs, scene, absgrad=True)
        if backward:
            (r.sum() + a.sum()).backward()

    render(True)  # warm caches (and the runtime's array pool: both kinds of call, as below)
    render(False)
    before = live()
    for i in range(10):
        render(backward=i % 2 == 0)
    assert live() - before <= 2
