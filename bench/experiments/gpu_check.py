"""The engine on a GPU's own OpenCL driver: accuracy, determinism and kernel times in one short run.

    python bench/experiments/gpu_check.py --out DIR [--scenes 10k,A,B] [--repeats 5]

The GPU layout (per-pixel backward, reduce launches, work-groups of the device's size) runs on
PoCL's CPU device and Oclgrind in the tests; this script is what to run where a GPU is at hand
(the device machine: ``bench/experiments/gpu_check.sh``). Nothing depends on it. On the default
device (``CLSPLAT_DEVICE`` or the first GPU), per scene (:data:`bench.peers.SCENES`, SH 3):

* **accuracy**: float32 against float64 on the same device (image max abs and each parameter's
  gradient 2-norm error relative to float64's, as ``clsplat bench peers`` states them), both
  ``packed`` layouts; for scenes of at most ``--torch-max-n`` Gaussians also float64 against
  :func:`clsplat.reference.rasterization` (the pure-torch mirror, float64 on the CPU);
* **determinism**: two float32 forward + backward calls, bitwise equal images and gradients;
* **time**: ``--repeats`` forward + backward calls after two warm-ups, wall medians, and each
  kernel's device time (OpenCL profiling events) summed per stage, medians.

``--set FIELD=VALUE`` gives every render that :class:`clsplat.RenderConfig` field (e.g.
``backward_impl=gaussian``, ``sort_impl=tiles``).

Writes ``gpu_check.json`` and ``gpu_check.md`` into ``--out``, printing the table as it goes.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

import clsplat  # noqa: I100  (before torch: clsplat.threads)
import torch
from clsplat import reference
from clsplat.runtime import describe_devices, get_runtime

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.peers import PARAMS, SCENES  # noqa: E402
from bench.scenes import render_args  # noqa: E402
from bench.timing import event_ms  # noqa: E402


def _render(scene: dict, dtype: torch.dtype, packed: bool, fields: dict, events: list | None = None,
            ref: bool = False) -> tuple[torch.Tensor, dict]:
    """One forward + backward of a fixed weighted sum of the image: (image, gradients)."""
    args = render_args(scene)
    leaves = {k: args[k].detach().to(dtype).clone().requires_grad_() for k in PARAMS}
    args.update(leaves)
    args["viewmats"], args["Ks"] = args["viewmats"].to(dtype), args["Ks"].to(dtype)
    if ref:
        img = reference.rasterization(**args)[0]
    else:
        img = clsplat.rasterization(**args, packed=packed, events=events, config=_config(dtype, fields))[0]
    w = torch.linspace(0.5, 1.5, img.numel(), dtype=img.dtype).reshape(img.shape)
    (img * w).sum().backward()
    return img.detach(), {k: v.grad for k, v in leaves.items()}


def _config(dtype: torch.dtype, fields: dict) -> clsplat.RenderConfig | None:
    """The RenderConfig of ``fields`` (``--set``) in ``dtype``'s precision; None: the default."""
    if not fields:
        return None
    return clsplat.RenderConfig(precision="float64" if dtype == torch.float64 else "float32", **fields)


def _agreement(img, grads, ref_img, ref_grads) -> dict:
    floor = 1e-5 * max(float(ref_grads[k].norm()) for k in PARAMS)
    return {"image_max_abs": float((img.double() - ref_img.double()).abs().max()),
            "grad_rel": {k: float((grads[k].double() - ref_grads[k].double()).norm())
                         / max(float(ref_grads[k].norm()), floor, 1e-30) for k in PARAMS}}


def check_scene(name: str, repeats: int, torch_max_n: int, fields: dict) -> dict:
    scene = SCENES[name]()
    n = scene["means"].shape[0]
    row: dict = {"scene": name, "N": n, "size": f"{scene['width']}x{scene['height']}"}
    t0 = time.perf_counter()
    img64, g64 = _render(scene, torch.float64, False, fields)
    row["float64_s"] = time.perf_counter() - t0
    for packed in (False, True):
        img32, g32 = _render(scene, torch.float32, packed, fields)
        row[f"f32_vs_f64_{'packed' if packed else 'unpacked'}"] = _agreement(img32, g32, img64, g64)
    if n <= torch_max_n:
        imgr, gr = _render(scene, torch.float64, False, fields, ref=True)
        row["f64_vs_torch_reference"] = _agreement(img64, g64, imgr, gr)
    a_img, a_g = _render(scene, torch.float32, True, fields)
    b_img, b_g = _render(scene, torch.float32, True, fields)
    row["bitwise_repeatable"] = bool(torch.equal(a_img, b_img) and all(torch.equal(a_g[k], b_g[k]) for k in PARAMS))
    fw, bw, kern = [], [], defaultdict(list)
    args = render_args(scene)
    leaves = {k: args[k].detach().float().clone().requires_grad_() for k in PARAMS}
    args.update(leaves)
    for i in range(2 + repeats):
        ev: list = []
        s0 = time.perf_counter()
        img = clsplat.rasterization(**args, packed=True, events=ev, config=_config(torch.float32, fields))[0]
        s1 = time.perf_counter()
        img.sum().backward()
        s2 = time.perf_counter()
        for v in leaves.values():
            v.grad = None
        if i >= 2:
            fw.append(1e3 * (s1 - s0))
            bw.append(1e3 * (s2 - s1))
            per = defaultdict(float)
            for stage, e in ev:
                per[stage] += event_ms(e)
            for stage, v in per.items():
                kern[stage].append(v)
    row["fwd_ms"], row["bwd_ms"] = statistics.median(fw), statistics.median(bw)
    row["kernels_ms"] = {k: statistics.median(v) for k, v in kern.items()}
    return row


def markdown(rows: list[dict], devices: str) -> str:
    out = ["```", devices, "```", "",
           "| scene | f32 vs f64 image max abs (unpacked / packed) | worst grad rel (unpacked / packed) "
           "| f64 vs torch reference: image / worst grad | bitwise repeatable | fwd / bwd ms | kernels ms |",
           "|---|---|---|---|---|---|---|"]
    for r in rows:
        u, p = r["f32_vs_f64_unpacked"], r["f32_vs_f64_packed"]
        ref = r.get("f64_vs_torch_reference")
        refs = (f"{ref['image_max_abs']:.1e} / {max(ref['grad_rel'].values()):.1e}" if ref else "–")
        kern = ", ".join(f"{k} {v:.2f}" for k, v in r["kernels_ms"].items())
        out.append(f"| {r['scene']} ({r['N']}, {r['size']}) | {u['image_max_abs']:.1e} / {p['image_max_abs']:.1e} "
                   f"| {max(u['grad_rel'].values()):.1e} / {max(p['grad_rel'].values()):.1e} | {refs} "
                   f"| {r['bitwise_repeatable']} | {r['fwd_ms']:.2f} / {r['bwd_ms']:.2f} | {kern} |")
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--scenes", default="10k,A,B")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--torch-max-n", type=int, default=10_000)
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="a RenderConfig field for every render, e.g. backward_impl=gaussian")
    a = ap.parse_args(argv)
    fields: dict = {}
    for spec in a.set:
        field, sep, value = spec.partition("=")
        if not sep:
            ap.error(f"--set: expected FIELD=VALUE, got {spec!r}")
        fields[field] = int(value) if value.isdigit() else value
    try:
        _config(torch.float32, fields)
    except (TypeError, ValueError) as e:
        ap.error(f"--set: {e}")
    names = [s for s in a.scenes.split(",") if s]
    bad = [s for s in names if s not in SCENES]
    if bad:
        ap.error(f"--scenes: unknown {bad}, expected of {sorted(SCENES)}")
    devices = describe_devices()
    print(devices, flush=True)
    rt = get_runtime()
    print(f"runtime: {rt.name}; config {fields or 'default'}", flush=True)
    a.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in names:
        t0 = time.perf_counter()
        try:
            rows.append(check_scene(name, a.repeats, a.torch_max_n, fields))
        except Exception as e:  # a failing scene is recorded, the others still run
            rows.append({"scene": name, "error": f"{type(e).__name__}: {e}"[:2000]})
        print(json.dumps(rows[-1]), f"({time.perf_counter() - t0:.1f} s)", flush=True)
        (a.out / "gpu_check.json").write_text(json.dumps({"device": rt.name, "devices": devices,
                                                           "config": fields, "rows": rows}, indent=1) + "\n")
    ok = [r for r in rows if "error" not in r]
    (a.out / "gpu_check.md").write_text(markdown(ok, devices))
    print(markdown(ok, devices))
    return 0 if len(ok) == len(rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
