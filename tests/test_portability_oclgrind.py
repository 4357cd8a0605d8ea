"""A second OpenCL implementation: tiny scenes forward and backward on Oclgrind, against PoCL.

Oclgrind (Debian ``oclgrind``) simulates a strict OpenCL 1.2 device. Each case runs in a
subprocess whose only OpenCL platform is Oclgrind (an ICD folder holding one ``.icd`` file,
named by ``OCL_ICD_VENDORS``), with its data-race checker on, in the CPU layout (vectors of
pixels per work-item; kernels/order.cl's passes over 3 chunks, one a work-group, counters
chunk-major) and in the GPU layout (one pixel per work-item; the passes over 3 chunks in one
work-group, counters bin-major), tile 16 and 32, float32 and float64; Oclgrind's device counts
as a CPU, so these run the tuned compositing kernels, and two more cases the baseline ones
(``RenderConfig(composite_impl="baseline")``, the GPU default; the CPU one with the default
chunks, i.e. order_small at this size), two more the baseline sort (``sort_impl="tiles"``:
serial segment sort; bitonic sort in local memory). Images and every
gradient must match PoCL's, and no report may name a clsplat kernel (pyopencl's own scan has
a read-write race of its own; see README). The uninitialised-memory checker runs the whole
forward and the compositing backward on both host-memory paths, with the scan done on the
host (the checker cannot run pyopencl's scan); Oclgrind 21.10's checker itself segfaults on
reduce_slots, sh_colors_bwd and project_bwd, so the slot reduction is done in torch there and
the backward stops at the screen-space gradients.

The module needs the ``oclgrind`` package: ``.ci/run`` installs it with apt where it can;
``pytest -m oclgrind`` runs only this target. Without it the cases skip, saying why.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

import clsplat

pytestmark = [pytest.mark.oclgrind, pytest.mark.slow]   # each case spawns an interpreter on the simulator

_ICD_LIBS = ("/usr/lib/oclgrind/liboclgrind-rt-icd.so",
             "/usr/lib/x86_64-linux-gnu/liboclgrind-rt-icd.so")
_ICD = next((p for p in _ICD_LIBS if os.path.exists(p)), None)
# pyopencl's scan kernels (GenericScanKernel): the only kernels allowed in a report.
_PYOPENCL_SCAN = {"scan_lev1", "scan_lev2", "final_update"}

_SCRIPT = textwrap.dedent('''
    import os, sys, torch
    import clsplat
    prec, layout, tile, out, mode = sys.argv[1:6]
    tile = int(tile)
    dt = torch.float64 if prec == "float64" else torch.float32
    g = torch.Generator().manual_seed(3)
    N, W, H = 10, 36, 20   # 3x2 partial tiles at tile 16, 2x1 at tile 32
    xs = [torch.cat([(torch.rand(N, 2, generator=g) - 0.5) * 1.5, 2 + torch.rand(N, 1, generator=g)], 1),
          torch.randn(N, 4, generator=g) + 0.1, 0.05 + 0.2 * torch.rand(N, 3, generator=g),
          0.3 + 0.6 * torch.rand(N, generator=g), torch.randn(N, 4, 3, generator=g) * 0.5]
    xs = [x.to(dt).requires_grad_() for x in xs]
    vm = torch.eye(4, dtype=dt)[None].requires_grad_()
    K = torch.tensor([[[36.0, 0, W / 2], [0, 36, H / 2], [0, 0, 1]]], dtype=dt)
    if layout == "gpu":  # 3 chunks: the multi-chunk passes of kernels/order.cl, N being tiny
        cfg = clsplat.RenderConfig(pix=1, sort_layout="bitonic", sort_local=8, sort_chunks=3)
    elif layout == "gpu-tiles":
        cfg = clsplat.RenderConfig(pix=1, sort_layout="bitonic", sort_local=8, sort_impl="tiles")
    elif layout == "cpu-tiles":
        cfg = clsplat.RenderConfig(sort_layout="serial", sort_impl="tiles")
    elif layout == "gpu-baseline":  # Oclgrind counts as a CPU: the tuned kernels are its default
        cfg = clsplat.RenderConfig(pix=1, sort_layout="bitonic", sort_local=8, composite_impl="baseline")
    elif layout == "cpu-baseline":
        cfg = clsplat.RenderConfig(sort_layout="serial", composite_impl="baseline")
    elif layout == "cpu":  # 3 chunks: the chunked passes (the baseline case runs order_small)
        cfg = clsplat.RenderConfig(sort_layout="serial", sort_chunks=3)
    else:
        cfg = clsplat.RenderConfig()
    if mode == "uninit":  # the checker crashes on reduce_slots: sum the slots in torch
        from clsplat import stages
        def reduce_slots(rt, cfg, rects, offs, slots, channels, *, geom, color, absgrad, events=None):
            r = rects.host().reshape(-1, 4).to(torch.int64)
            n = (r[:, 2] - r[:, 0]) * (r[:, 3] - r[:, 1])
            s = slots.host()
            seg = torch.repeat_interleave(torch.arange(len(n)), n)
            tot = torch.zeros(len(n), s.shape[1], dtype=s.dtype).index_add_(0, seg, s[:len(seg)])
            C, N = rects.tensor.shape[:2]
            z = lambda *sh: torch.zeros(C, N, *sh, dtype=s.dtype)
            res = {"v_means2d": z(2), "v_conics": z(3), "v_opacities": z(), "absgrad": z(2),
                   "v_feats": z(channels)}
            k = 0
            if geom:
                res["v_means2d"], res["v_conics"] = tot[:, 0:2].reshape(C, N, 2), tot[:, 2:5].reshape(C, N, 3)
                res["v_opacities"] = tot[:, 5].reshape(C, N)
                k = 6
                if absgrad:
                    res["absgrad"], k = tot[:, 6:8].reshape(C, N, 2), 8
            if color:
                res["v_feats"] = tot[:, k:k + channels].reshape(C, N, channels)
            return {key: rt.array(v.contiguous()) for key, v in res.items()}
        stages.reduce_slots = reduce_slots
    r, a, meta = clsplat.rasterization(*xs, vm, K, W, H, sh_degree=1, tile_size=tile,
                                       render_mode="RGB+ED", config=cfg, absgrad=True)
    w = torch.linspace(-1, 1, r.numel(), dtype=dt).reshape(r.shape)
    loss = (r * w).sum() + a.square().sum()
    if mode == "uninit":  # stop at the screen-space gradients: sh_bwd and project_bwd crash it
        v_means2d, = torch.autograd.grad(loss, [meta["means2d"]])
        torch.save({"render": r.detach(), "alpha": a.detach(), "means2d": v_means2d}, out)
        sys.exit(0)
    meta["means2d"].retain_grad()
    loss.backward()
    res = {"render": r.detach(), "alpha": a.detach(), "viewmats": vm.grad,
           "means2d": meta["means2d"].grad, "absgrad": meta["means2d"].absgrad,
           "radii": meta["radii"], "isect_offsets": meta["isect_offsets"],
           "flatten_ids": meta["flatten_ids"]}
    for name, x in zip(("means", "quats", "scales", "opacities", "sh"), xs):
        res[name] = x.grad
    torch.save(res, out)
''')


def _oclgrind_env(tmp_path: Path, **extra: str) -> dict:
    icd_dir = tmp_path / "icd"
    icd_dir.mkdir(exist_ok=True)
    assert _ICD is not None, f"CLSPLAT_REQUIRE_OCLGRIND=1 but no Oclgrind ICD library in {_ICD_LIBS}"
    (icd_dir / "oclgrind.icd").write_text(_ICD + "\n")
    env = dict(os.environ, OCL_ICD_VENDORS=str(icd_dir), CLSPLAT_DEVICE="oclgrind",
               OCL_ICD_FILENAMES="", PYTHONUNBUFFERED="1")
    env.update(extra)
    return env


def _run(tmp_path: Path, env: dict, *args: str) -> tuple[dict, str]:
    out = tmp_path / ("res_" + "_".join(args[:3]) + ".pt")
    p = subprocess.run([sys.executable, "-c", _SCRIPT, *args[:3], str(out), *args[3:]],
                       env=env, capture_output=True, text=True, timeout=300)
    log = p.stdout + p.stderr
    assert p.returncode == 0, f"rc={p.returncode}\n{log[-3000:]}"
    return torch.load(out), log


def _reported_kernels(log: str) -> set[str]:
    return set(re.findall(r"^\s*Kernel:\s*(\w+)", log, re.MULTILINE))


def _compare(got: dict, want: dict, precision: str) -> None:
    rtol, atol = (1e-9, 1e-11) if precision == "float64" else (2e-4, 2e-5)
    for k, g in got.items():
        w = want[k]
        assert g is not None and g.shape == w.shape, k
        if not g.is_floating_point():
            assert torch.equal(g, w), k
            continue
        scale = float(w.abs().max()) or 1.0
        err = float((g - w).abs().max())
        assert err <= atol * scale + rtol * scale, f"{k}: max |Oclgrind - PoCL| = {err:.3g} (scale {scale:.3g})"


# .ci/run sets CLSPLAT_REQUIRE_OCLGRIND=1 once oclgrind is installed: there a missing runtime is a
# failure, not a skip that would hide it
_REQUIRED = os.environ.get("CLSPLAT_REQUIRE_OCLGRIND") == "1"
needs_oclgrind = pytest.mark.skipif(
    _ICD is None and not _REQUIRED, reason="oclgrind is not installed (apt-get install oclgrind); see README")

_CASES = [("float32", "cpu", 16), ("float64", "cpu", 16),
          ("float32", "gpu", 16), ("float32", "gpu", 32),
          ("float64", "gpu", 16), ("float64", "gpu", 32),
          ("float32", "cpu-baseline", 16), ("float32", "gpu-baseline", 16),
          ("float32", "cpu-tiles", 16), ("float32", "gpu-tiles", 16)]


@pytest.fixture(scope="module")
def pocl_results(tmp_path_factory):
    """The same scenes on PoCL (its default layout: tile 32 with one pixel per item would
    need groups of 1024, over the 256 the tests allow)."""
    d = tmp_path_factory.mktemp("pocl")
    env = dict(os.environ, CLSPLAT_DEVICE="pocl")
    cache = {}

    def get(precision: str, tile: int) -> dict:
        if (precision, tile) not in cache:
            cache[precision, tile] = _run(d, env, precision, "default", str(tile), "full")[0]
        return cache[precision, tile]
    return get


@needs_oclgrind
@pytest.mark.parametrize("precision,layout,tile", _CASES)
def test_oclgrind_matches_pocl_with_race_checker(tmp_path, pocl_results, precision, layout, tile):
    env = _oclgrind_env(tmp_path, OCLGRIND_DATA_RACES="1")
    got, log = _run(tmp_path, env, precision, layout, str(tile), "full")
    bad = _reported_kernels(log) - _PYOPENCL_SCAN
    assert not bad, f"Oclgrind reports errors in clsplat kernels {sorted(bad)}:\n{log[-4000:]}"
    _compare(got, pocl_results(precision, tile), precision)


@needs_oclgrind
@pytest.mark.parametrize("host_memory", ["share", "copy"])
def test_oclgrind_uninitialised_memory_checker(tmp_path, pocl_results, host_memory):
    """Oclgrind's uninitialised-value checker over project, sh, bin, sort, composite and
    composite_bwd, on the zero-copy path (map/unmap) and on the copy path of discrete GPUs."""
    env = _oclgrind_env(tmp_path, OCLGRIND_UNINITIALIZED="1", CLSPLAT_HOST_SCAN="1",
                        CLSPLAT_HOST_MEMORY=host_memory)
    got, log = _run(tmp_path, env, "float32", "gpu", "16", "uninit")
    kernels = _reported_kernels(log)
    assert not kernels, f"uninitialised values in {sorted(kernels)}:\n{log[-4000:]}"
    _compare(got, pocl_results("float32", 16), "float32")


def test_oclgrind_marker_registered(pytestconfig):
    """``pytest -m oclgrind`` selects this module (the marker is declared in setup.cfg)."""
    assert any(m.startswith("oclgrind") for m in pytestconfig.getini("markers"))
