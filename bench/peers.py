"""``clsplat bench peers``: clsplat against other CPU splatting renderers on identical inputs.

    clsplat bench peers [--opensplat DIR] [--scenes 10k,100k,1m,A,B] [--repeats 3]
        [--torch-max-n 10000] [--build-dir DIR] [--out DIR]

Peers, each run interleaved with the others in every round (forward, then backward of one fixed
weighted sum of the image), medians over ``--repeats`` rounds after one warm-up:

* ``clsplat``: :func:`clsplat.rasterization` on the OpenCL device (torch on one thread: PoCL has
  the cores).
* ``opensplat``: OpenSplat's CPU rasterizer (``rasterizer/gsplat-cpu/gsplat_cpu.cpp`` of the source
  tree given with ``--opensplat``), compiled here once with torch's extension builder, driven the
  way OpenSplat's model drives it: its torch projection and SH functions, then its rasterizer's
  forward and backward (autograd through the torch parts). This module's own glue (the binding and
  the per-camera calls) adds: a principal point in the projection matrix (OpenSplat's is centred)
  and culling of Gaussians behind the near plane (OpenSplat projects them too; with several
  cameras that would be garbage). Torch runs on every core for it.
* ``torch``: :func:`clsplat.reference.rasterization`, the pure-torch mirror of gsplat's
  ``_torch_impl`` (float32), on scenes of at most ``--torch-max-n`` Gaussians.

A peer that is not available is skipped, saying why (no ``--opensplat`` tree, a build error).
Before timing, each peer's image and gradients are compared with clsplat's: the largest absolute
image difference and, per parameter, |g_peer - g_clsplat| / |g_clsplat| (2-norms). OpenSplat's are
also given with its two differences fixed (``image_max_abs_fixed``, ``grad_rel_fixed``): its backward
accumulates x y / 2 for d sigma / d b where sigma = (a x^2 + c y^2) / 2 + b x y, which makes its
scale and rotation gradients disagree by up to 100 % (doubled there), and its depth sort is not
stable (ties broken by Gaussian id there, as clsplat breaks them); fixed, they agree to float
rounding and the 3-sigma box's cut tail (OpenSplat stops at 3 sigma, clsplat where alpha falls
below 1/255).

Scenes: ``tiny`` (300 Gaussians at 96x64, for tests), ``10k``, ``100k``, ``1m`` (random, SH 3,
640x352, :func:`clsplat.bench.scenes.random_frustum_scene`), ``A`` and ``B`` (the bench scenes).

Writes ``peers.json`` and ``peers.md`` into ``--out``.
"""
from __future__ import annotations

import json
import os
import shlex
import statistics
import sys
import time
from pathlib import Path

import torch

from clsplat.argparser import ArgumentParser

from .scenes import random_frustum_scene, render_args, scene_a, scene_b

__all__ = ["SCENES", "build_opensplat", "main", "run"]

PARAMS = ("means", "quats", "scales", "opacities", "colors")
SCENES = {"tiny": lambda: random_frustum_scene(300, 96, 64, name="random 300 at 96x64"),
          "10k": lambda: random_frustum_scene(10_000, name="random 10k"),
          "100k": lambda: random_frustum_scene(100_000, name="random 100k"),
          "1m": lambda: random_frustum_scene(1_000_000, name="random 1M"),
          "A": lambda: scene_a(), "B": lambda: scene_b()}
NEAR = 0.01                     # clsplat's near plane, applied to OpenSplat's inputs by the glue
OPENSPLAT_SOURCE = Path("rasterizer") / "gsplat-cpu" / "gsplat_cpu.cpp"

# The binding: OpenSplat's functions as a Python module; the forward's per-pixel Gaussian lists
# (a raw ``new[]`` array) travel to the backward in a capsule that frees them.
_BINDING = r"""
#include <torch/extension.h>
#include "bindings.h"

namespace py = pybind11;

static void free_lists(void *p) { delete[] static_cast<std::vector<int32_t> *>(p); }

py::tuple forward(int width, int height, torch::Tensor xys, torch::Tensor conics, torch::Tensor colors,
                  torch::Tensor opacities, torch::Tensor background, torch::Tensor cov2d,
                  torch::Tensor depths) {
    auto r = rasterize_forward_tensor_cpu(width, height, xys, conics, colors, opacities, background,
                                          cov2d, depths);
    return py::make_tuple(std::get<0>(r), std::get<1>(r), py::capsule(std::get<2>(r), free_lists));
}

py::tuple backward(int height, int width, torch::Tensor xys, torch::Tensor conics, torch::Tensor colors,
                   torch::Tensor opacities, torch::Tensor background, torch::Tensor cov2d,
                   torch::Tensor depths, torch::Tensor final_ts, py::capsule lists,
                   torch::Tensor v_out, torch::Tensor v_alpha) {
    const std::vector<int32_t> *px = lists;
    auto r = rasterize_backward_tensor_cpu(height, width, xys, conics, colors, opacities, background,
                                           cov2d, depths, final_ts, px, v_out, v_alpha);
    return py::make_tuple(std::get<0>(r), std::get<1>(r), std::get<2>(r), std::get<3>(r));
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.def("project", &project_gaussians_forward_tensor_cpu);
    m.def("sh", &compute_sh_forward_tensor_cpu);
    m.def("forward", &forward);
    m.def("backward", &backward);
}
"""


def build_opensplat(tree: str | Path, build_dir: str | Path) -> object:
    """Compile OpenSplat's CPU rasterizer from source ``tree`` (cached in ``build_dir``).

    Raises ``FileNotFoundError`` naming the missing file when ``tree`` is not an OpenSplat tree.
    """
    from torch.utils import cpp_extension

    src = Path(tree) / OPENSPLAT_SOURCE
    if not src.is_file():
        raise FileNotFoundError(f"--opensplat: {src} not found (expected an OpenSplat source tree)")
    build = Path(build_dir)
    build.mkdir(parents=True, exist_ok=True)
    binding = build / "opensplat_binding.cpp"
    if not binding.is_file() or binding.read_text() != _BINDING:
        binding.write_text(_BINDING)
    return cpp_extension.load(name="clsplat_peer_opensplat", sources=[str(binding), str(src.resolve())],
                              extra_include_paths=[str(src.parent.resolve())], extra_cflags=["-O3"],
                              build_directory=str(build), verbose=False)


class _OpenSplatRaster(torch.autograd.Function):
    """OpenSplat's rasterizer as an autograd function: [N,2] xys, [N,3] conics, [N,3] colours,
    [N,1] opacities (float32, contiguous) -> [H,W,3] image."""

    @staticmethod
    def forward(ctx, xys, conics, colors, opacities, cov2d, depths, lib, width, height, fixed):
        bg = torch.zeros(3)
        img, final_t, lists = lib.forward(width, height, xys, conics, colors, opacities, bg, cov2d, depths)
        ctx.save_for_backward(xys, conics, colors, opacities, cov2d, depths, final_t)
        ctx.lists, ctx.lib, ctx.size, ctx.fixed = lists, lib, (width, height), fixed
        return img

    @staticmethod
    def backward(ctx, v_img):
        xys, conics, colors, opacities, cov2d, depths, final_t = ctx.saved_tensors
        width, height = ctx.size
        v_xy, v_conic, v_col, v_op = ctx.lib.backward(
            height, width, xys, conics, colors, opacities, torch.zeros(3), cov2d, depths, final_t,
            ctx.lists, v_img.contiguous(), torch.zeros(height, width))
        if ctx.fixed:     # d sigma / d b = x y, where OpenSplat accumulates x y / 2
            v_conic = v_conic * torch.tensor([1.0, 2.0, 1.0])
        return v_xy, v_conic, v_col, v_op, None, None, None, None, None, None


def _opengl_projection(K: torch.Tensor, width: int, height: int, near: float = 0.001,
                       far: float = 1000.0) -> torch.Tensor:
    """OpenSplat's perspective matrix for intrinsics ``K`` [3,3], with its principal point."""
    P = torch.zeros(4, 4)
    P[0, 0], P[1, 1] = 2 * K[0, 0] / width, 2 * K[1, 1] / height
    P[0, 2], P[1, 2] = 2 * K[0, 2] / width - 1, 2 * K[1, 2] / height - 1
    P[2, 2], P[2, 3] = (far + near) / (far - near), -far * near / (far - near)
    P[3, 2] = 1.0
    return P


def opensplat_render(lib, p: dict, scene: dict, fixed: bool = False) -> torch.Tensor:
    """[C,H,W,3] images of ``scene`` with parameters ``p`` through OpenSplat's CPU pipeline.

    ``fixed`` (the diagnosis of its disagreements, never timed) doubles the gradient of the
    conic's off-diagonal, which OpenSplat's backward accumulates halved, and breaks depth ties by
    Gaussian id as clsplat does (its ``std::sort`` is not stable: a level camera sees a flat
    road's Gaussians of one image row at one depth)."""
    W, H, deg = scene["width"], scene["height"], scene["sh_degree"]
    out = []
    for viewmat, K in zip(scene["viewmats"], scene["Ks"]):
        z = p["means"].detach() @ viewmat[2, :3] + viewmat[2, 3]
        keep = torch.nonzero(z > NEAR).squeeze(1)
        means, scales, quats = p["means"][keep], p["scales"][keep], p["quats"][keep]
        projmat = _opengl_projection(K, W, H) @ viewmat
        xys, _, conics, cov2d, _ = lib.project(
            keep.numel(), means, scales, 1.0, quats, viewmat, projmat, float(K[0, 0]), float(K[1, 1]),
            float(K[0, 2]), float(K[1, 2]), H, W, NEAR)
        colors = p["colors"][keep]
        if deg is not None:
            centre = -viewmat[:3, :3].T @ viewmat[:3, 3]
            dirs = torch.nn.functional.normalize(means - centre, dim=-1)
            colors = lib.sh(keep.numel(), deg, deg, dirs, colors)
            colors = torch.clamp_min(colors + 0.5, 0.0)
        depths = z[keep].contiguous()
        if fixed:             # the rank of (depth, id): no ties left for std::sort to break
            depths = torch.empty_like(depths)
            depths[torch.sort(z[keep], stable=True).indices] = torch.arange(keep.numel(), dtype=depths.dtype)
        out.append(_OpenSplatRaster.apply(xys.contiguous(), conics.contiguous(), colors.contiguous(),
                                          p["opacities"][keep][:, None].contiguous(), cov2d.detach().contiguous(),
                                          depths, lib, W, H, fixed))
    return torch.stack(out)


def clsplat_render(p: dict, scene: dict) -> torch.Tensor:
    import clsplat

    args = render_args(scene)
    args.update(p)
    return clsplat.rasterization(**args)[0]


def torch_render(p: dict, scene: dict) -> torch.Tensor:
    from clsplat import reference

    args = render_args(scene)
    args.update(p)
    return reference.rasterization(**args)[0]


def _leaves(scene: dict) -> dict:
    return {k: scene[k].clone().requires_grad_() for k in PARAMS}


def _time(render, scene: dict, weights: torch.Tensor, threads: int) -> tuple[float, float, torch.Tensor, dict]:
    """One forward + backward: (fwd ms, bwd ms, image, gradients)."""
    torch.set_num_threads(threads)
    p = _leaves(scene)
    t0 = time.perf_counter()
    img = render(p, scene)
    t1 = time.perf_counter()
    (img * weights).sum().backward()
    t2 = time.perf_counter()
    return 1e3 * (t1 - t0), 1e3 * (t2 - t1), img.detach(), {k: v.grad for k, v in p.items()}


def _agreement(img, grads, ref_img, ref_grads) -> dict:
    """Largest image difference, and each gradient's 2-norm error relative to clsplat's, floored
    at 1e-5 of the largest gradient norm (isotropic Gaussians have a rotation gradient that is 0
    in exact arithmetic: rounding's 1e-7 against an exact 0 is not a disagreement)."""
    floor = 1e-5 * max(float(ref_grads[k].norm()) for k in PARAMS)
    rel = {k: float((grads[k] - ref_grads[k]).norm()) / max(float(ref_grads[k].norm()), floor, 1e-30)
           for k in PARAMS}
    return {"image_max_abs": float((img - ref_img).abs().max()), "grad_rel": rel}


def run(scene_names: list[str], repeats: int, opensplat: str | None, build_dir: str,
        torch_max_n: int) -> dict:
    """Time every available peer on every scene (see the module doc); returns the report dict."""
    cores = os.cpu_count() or 1
    peers = {"clsplat": (clsplat_render, 1, None)}
    skipped = {}
    if opensplat is None:
        skipped["opensplat"] = "no --opensplat source tree given"
    else:
        try:
            lib = build_opensplat(opensplat, build_dir)
            peers["opensplat"] = (lambda p, s: opensplat_render(lib, p, s), cores,
                                  lambda p, s: opensplat_render(lib, p, s, fixed=True))
        except Exception as e:      # a peer that does not build is skipped, with its reason
            skipped["opensplat"] = f"build failed: {str(e).strip().splitlines()[-1][:200]}"
    peers["torch"] = (torch_render, cores, None)
    for name, why in skipped.items():
        print(f"peers: {name} skipped ({why})", flush=True)
    threads = torch.get_num_threads()
    try:
        rows = [_scene_row(sname, peers, repeats, torch_max_n) for sname in scene_names]
    finally:
        torch.set_num_threads(threads)
    return {"rows": rows, "skipped": skipped, "repeats": repeats, "cores": cores,
            "threads": {k: v[1] for k, v in peers.items()}}


def _scene_row(sname: str, peers: dict, repeats: int, torch_max_n: int) -> dict:
    """One scene's interleaved rounds over ``peers`` (name -> (render, torch threads, the render
    with OpenSplat's off-diagonal gradient fixed or None))."""
    scene = SCENES[sname]()
    n = int(scene["means"].shape[0])
    active = {k: v for k, v in peers.items() if k != "torch" or n <= torch_max_n}
    g = torch.Generator().manual_seed(1)
    C = int(scene["viewmats"].shape[0])
    weights = torch.rand(C, scene["height"], scene["width"], 3, generator=g)
    times = {k: {"fwd": [], "bwd": []} for k in active}
    checks = {}
    for r in range(repeats + 1):        # round 0 warms up (builds, caches) and checks agreement
        for name, (render, threads, fixed) in active.items():
            f, b, img, grads = _time(render, scene, weights, threads)
            if r == 0:
                checks[name] = (img, grads)
                if fixed is not None:
                    checks[name + ", fixed"] = _time(fixed, scene, weights, threads)[2:]
            else:
                times[name]["fwd"].append(f)
                times[name]["bwd"].append(b)
    torch.set_num_threads(1)
    ref_img, ref_grads = checks["clsplat"]
    row = {"scene": scene["name"], "key": sname, "n": n, "peers": {}}
    for name in active:
        fwd, bwd = statistics.median(times[name]["fwd"]), statistics.median(times[name]["bwd"])
        row["peers"][name] = {"fwd_ms": fwd, "bwd_ms": bwd, "fwd_all": times[name]["fwd"],
                              "bwd_all": times[name]["bwd"],
                              **({} if name == "clsplat" else _agreement(*checks[name], ref_img, ref_grads))}
        if name + ", fixed" in checks:
            fix = _agreement(*checks[name + ", fixed"], ref_img, ref_grads)
            row["peers"][name]["image_max_abs_fixed"] = fix["image_max_abs"]
            row["peers"][name]["grad_rel_fixed"] = fix["grad_rel"]
    cl = row["peers"]["clsplat"]
    for name in active:
        if name != "clsplat":
            q = row["peers"][name]
            q["ratio_total"] = (cl["fwd_ms"] + cl["bwd_ms"]) / (q["fwd_ms"] + q["bwd_ms"])
            q["ratio_bwd"] = cl["bwd_ms"] / q["bwd_ms"]
    print(markdown_row(row), flush=True)
    return row


def markdown_row(row: dict) -> str:
    cl = row["peers"]["clsplat"]
    cells = [row["scene"], f"{cl['fwd_ms']:.0f} / {cl['bwd_ms']:.0f}"]
    for name in ("opensplat", "torch"):
        q = row["peers"].get(name)
        if q is None:
            cells += ["–", "–", "–"]
            continue
        agree = f"{q['image_max_abs']:.1e} / {max(q['grad_rel'].values()):.1e}"
        if "grad_rel_fixed" in q:
            agree += f" ({q['image_max_abs_fixed']:.1e} / {max(q['grad_rel_fixed'].values()):.1e} fixed)"
        cells += [f"{q['fwd_ms']:.0f} / {q['bwd_ms']:.0f}",
                  f"**{q['ratio_total']:.3f}** / {q['ratio_bwd']:.3f}", agree]
    return "| " + " | ".join(cells) + " |"


def markdown(res: dict, command: str) -> str:
    head = ("| scene | clsplat fwd / bwd ms | OpenSplat fwd / bwd ms | clsplat ÷ OpenSplat total / bwd "
            "| vs OpenSplat: image max abs / worst grad rel | torch reference fwd / bwd ms "
            "| clsplat ÷ torch total / bwd | vs torch: image / grad |\n|" + "---|" * 8)
    lines = [f"`{command}`", "", f"Medians of {res['repeats']} interleaved rounds; threads: "
             + ", ".join(f"{k} {v}" for k, v in res["threads"].items()) + ".", ""]
    lines += [f"Skipped: {k} ({v})." for k, v in res["skipped"].items()]
    return "\n".join(lines + ["", head] + [markdown_row(r) for r in res["rows"]]) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="clsplat bench peers", description=__doc__.split("\n")[0])
    p.add_argument("--opensplat", default=None, help="an OpenSplat source tree (its rasterizer/gsplat-cpu)")
    p.add_argument("--scenes", default="10k,100k,1m,A,B", help="comma list of " + ",".join(SCENES))
    p.add_argument("--repeats", type=int, default=3, help="timed rounds after the warm-up")
    p.add_argument("--torch-max-n", type=int, default=10_000, help="largest scene the torch reference runs")
    p.add_argument("--build-dir", default=str(Path.home() / ".cache" / "clsplat" / "peers"),
                   help="where the OpenSplat binding is compiled (cached)")
    p.add_argument("--out", default="bench_out", help="output folder (created)")
    a = p.parse_args(argv)
    names = [s for s in a.scenes.split(",") if s]
    bad = [s for s in names if s not in SCENES]
    if bad or not names:
        p.error(f"--scenes: unknown {bad or a.scenes!r}; choose from {','.join(SCENES)}")
    if a.repeats < 1:
        p.error("--repeats must be >= 1")
    if a.torch_max_n < 0:
        p.error("--torch-max-n must be >= 0 (0: no torch peer)")
    if a.opensplat is not None and not (Path(a.opensplat) / OPENSPLAT_SOURCE).is_file():
        p.error(f"--opensplat: {Path(a.opensplat) / OPENSPLAT_SOURCE} not found (expected an OpenSplat source tree)")
    res = run(names, a.repeats, a.opensplat, a.build_dir, a.torch_max_n)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    command = "clsplat bench peers " + shlex.join(argv if argv is not None else sys.argv[1:])
    (out / "peers.json").write_text(json.dumps({**res, "command": command}, indent=1))
    (out / "peers.md").write_text(markdown(res, command))
    print(f"wrote {out / 'peers.json'}, {out / 'peers.md'}")
    return 0
