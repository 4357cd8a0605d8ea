"""RenderConfig.composite_impl: the tuned builds of the compositing kernels
(kernels/composite.cl, composite_bwd.cl with CLS_TUNED=1) give the baseline builds'
(CLS_TUNED=0) images and gradients bit for bit, in every layout and precision, on dense scenes where many
samples fall outside a row segment's extent and many pixels stop early."""
from __future__ import annotations

import pytest
import torch

import clsplat
from clsplat import stages
from clsplat.config import RenderConfig
from clsplat.runtime import get_runtime



def _scene(channels: int | None, dtype: torch.dtype, n: int = 1500) -> dict:
    """n Gaussians of a few pixels in front of one 70x52 camera (partial tiles at 8, 16, 32),
    SH degree 1, or ``channels`` plain colour channels."""
    g = torch.Generator().manual_seed(7)
    W, H = 70, 52
    z = 2 + 4 * torch.rand(n, generator=g, dtype=torch.float64)
    means = torch.stack([(torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 1.3 * z,
                         (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * z, z], -1)
    scales = 0.01 * z[:, None] * torch.exp(0.5 * torch.randn(n, 3, generator=g, dtype=torch.float64))
    colors = (torch.randn(n, 4, 3, generator=g, dtype=torch.float64) * 0.5 if channels is None
              else torch.rand(n, channels, generator=g, dtype=torch.float64))
    K = torch.tensor([[[50.0, 0, W / 2], [0, 50.0, H / 2], [0, 0, 1]]], dtype=torch.float64)
    x = {"means": means, "quats": torch.randn(n, 4, generator=g, dtype=torch.float64), "scales": scales,
         "opacities": 0.05 + 0.95 * torch.rand(n, generator=g, dtype=torch.float64), "colors": colors}
    x = {k: v.to(dtype) for k, v in x.items()}
    return x | {"viewmats": torch.eye(4, dtype=dtype)[None], "Ks": K.to(dtype), "W": W, "H": H,
                "sh_degree": None if channels is not None else 1}


def _run(grads, sc: dict, cfg: RenderConfig, tile: int, mode: str, absgrad: bool, divide: bool) -> dict:
    return grads(clsplat.rasterization, sc, absgrad=absgrad, sh_degree=sc["sh_degree"], config=cfg,
                 render_mode=mode, tile_size=tile, bwd_divide=divide)


# (precision, pix, tile, channels (None: SH degree 1), render mode, absgrad, bwd_divide)
_CASES = [
    ("float32", None, 16, None, "RGB", False, False),    # the CPU default layout
    ("float32", None, 16, None, "RGB+ED", True, False),
    ("float32", None, 16, None, "RGB", False, True),
    ("float64", None, 16, None, "RGB+ED", True, False),  # 4 doubles per item
    ("float32", 1, 16, None, "RGB", True, False),        # the GPU layout
    ("float64", 1, 16, None, "RGB", False, True),
    ("float32", 4, 8, None, "RGB", False, False),
    ("float32", 8, 32, None, "RGB", False, False),
    ("float32", 1, 16, 40, "RGB", False, False),         # channel chunks, WIDE, waves
    ("float32", None, 16, 40, "RGB", True, True),
]


@pytest.mark.parametrize("precision,pix,tile,channels,mode,absgrad,divide", _CASES)
def test_tuned_equals_baseline_bitwise(precision, pix, tile, channels, mode, absgrad, divide, loss_grads):
    dtype = torch.float64 if precision == "float64" else torch.float32
    sc = _scene(channels, dtype)
    # (backward_impl="pixel": the per-Gaussian backward, PoCL's CPU default, has one build for both)
    got = {impl: _run(loss_grads, sc, RenderConfig(precision=precision, pix=pix, composite_impl=impl,
                                       backward_impl="pixel"), tile, mode,
                      absgrad, divide) for impl in ("baseline", "tuned")}
    assert float(got["baseline"]["alpha"].max()) > 0.99  # opaque pixels: early stops happen
    for k, want in got["baseline"].items():
        assert torch.equal(got["tuned"][k], want), (k, float((got["tuned"][k] - want).abs().max()))


def test_default_impl_by_device():
    rt = get_runtime()
    assert stages.composite_tuned(rt, RenderConfig()) == rt.is_cpu
    assert stages.composite_tuned(rt, RenderConfig(composite_impl="tuned"))
    assert not stages.composite_tuned(rt, RenderConfig(composite_impl="baseline"))


def test_bad_impl_is_rejected():
    with pytest.raises(ValueError, match="composite_impl"):
        RenderConfig(composite_impl="fast")


def test_the_library_exp_is_used_where_the_inline_one_differs(monkeypatch, loss_grads):
    """On a device whose library exp the inline exp does not reproduce (another PoCL build or
    CPU variant), the probe's answer makes the tuned kernels call the library's exp: they still
    give the baseline's images and gradients bit for bit."""
    rt = get_runtime()
    sc = _scene(None, torch.float32, n=400)
    want = _run(loss_grads, sc, RenderConfig(composite_impl="baseline"), 16, "RGB", False, False)
    if rt.is_pocl_cpu:
        assert rt.inline_exp_exact is not None  # the probe ran with the first tuned render
    monkeypatch.setattr(rt, "inline_exp_exact", False)
    got = _run(loss_grads, sc, RenderConfig(composite_impl="tuned"), 16, "RGB", False, False)
    for k, v in want.items():
        assert torch.equal(got[k], v), k


def test_exp_probe_answers_and_is_exact_against_itself():
    """The probe runs on the device and gives a bool; with the inline exp built out, both of its
    sides are the library's exp and it must report them equal (a spurious 'different' would send
    the tuned kernels to the slower library exp for nothing)."""
    rt = get_runtime()
    if not rt.is_pocl_cpu:
        pytest.skip("the inline exp is only built on PoCL's CPU device (elsewhere the library's is used)")
    cfg = RenderConfig()
    defines = cfg.defines(16) | {"PIX": 8, "BATCH": 32, "CHANNELS": 3, "CCHUNK": 3, "SAVE_LAST": False,
                                 "CLS_POCL_CPU": True}
    saved = rt.inline_exp_exact
    try:
        rt.inline_exp_exact = None
        exact = stages.inline_exp_exact(rt, cfg, defines)
        assert isinstance(exact, bool)
        rt.inline_exp_exact = None  # with the inline exp off both sides are the library's: exact
        assert stages.inline_exp_exact(rt, cfg, defines | {"CLS_INLINE_EXP": 0}) is True
    finally:
        rt.inline_exp_exact = saved
