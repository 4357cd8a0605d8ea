"""Backward pass: per-stage device time, backward/forward ratio, training steps/s, gradient-slot
memory and the specialisation gains of project issue 5 (item 2).

* :func:`time_backward`: ``repeats + 1`` forward+backward passes on a fresh
  :class:`~clsplat.runtime.Runtime` (first call apart, as in :func:`.stages.time_forward`);
  every parameter (means, quats, scales, opacities, colours/SH) requires grad; the loss is
  ``sum(render * w) + sum(alpha * wa)`` with fixed random weights. Per stage the device ms
  from profiling events (forward stages and the backward stages ``composite_bwd``, ``reduce``,
  ``sh_bwd``, ``project_bwd``), the backward/forward ratio of the kernel totals (medians) and
  the wall time of ``loss.backward()``.
* :func:`training_steps`: full training steps (forward, L1 loss against a fixed target,
  backward, ``torch.optim.Adam`` step on means, quats, log-scales, logit-opacities and
  colours/SH) per second, wall clock, first step apart.
* :func:`slot_memory`: bytes per intersection of the backward's gradient slots
  (``clsplat.stages.slot_width(channels, geom, color, absgrad) x sizeof(REAL)``) and the
  total for the scene's intersections.
* :func:`specialisation`: the general kernel against three specialisations, same run,
  round-robin (each variant once per round), medians: colours without SH vs SH degree 3;
  render_mode "RGB" vs "RGB+ED"; frozen parameters (only colours, only means require grad)
  vs all parameters.
"""
from __future__ import annotations

import time
from collections import defaultdict

import numpy as np
import torch

import clsplat
from clsplat import stages as engine
from clsplat.config import RenderConfig
from clsplat.runtime import Runtime, get_runtime

from .timing import event_ms, summarise

__all__ = ["BWD_STAGES", "time_backward", "training_steps", "slot_memory", "specialisation"]

BWD_STAGES = ("composite_bwd", "reduce", "sh_bwd", "project_bwd")
PARAMS = ("means", "quats", "scales", "opacities", "colors")


def _leaves(scene: dict, cfg: RenderConfig, grad=PARAMS) -> dict:
    return {k: scene[k].detach().to(cfg.dtype).clone().requires_grad_(k in grad) for k in PARAMS}


def _weights(scene: dict, cfg: RenderConfig, channels: int, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    C, H, W = int(scene["viewmats"].shape[0]), scene["height"], scene["width"]
    w = torch.rand((C, H, W, channels), generator=g, dtype=torch.float64).to(cfg.dtype)
    wa = torch.rand((C, H, W, 1), generator=g, dtype=torch.float64).to(cfg.dtype)
    return w, wa


def fwd_bwd(rt, cfg, scene: dict, p: dict, w, wa, events=None, render_mode: str = "RGB"):
    """One forward + backward; returns (forward wall ms, backward wall ms, meta)."""
    t0 = time.perf_counter()
    out, alpha, meta = clsplat.rasterization(
        p["means"], p["quats"], p["scales"], p["opacities"], p["colors"],
        scene["viewmats"].to(cfg.dtype), scene["Ks"].to(cfg.dtype), scene["width"], scene["height"],
        sh_degree=scene["sh_degree"], device=rt, config=cfg, events=events, render_mode=render_mode)
    rt.queue.finish()
    t1 = time.perf_counter()
    ((out * w).sum() + (alpha * wa).sum()).backward()
    rt.queue.finish()
    t2 = time.perf_counter()
    for v in p.values():
        v.grad = None
    return (t1 - t0) * 1e3, (t2 - t1) * 1e3, meta


def time_backward(scene: dict, repeats: int = 5, device=None, cfg: RenderConfig | None = None) -> dict:
    """Per-stage device ms of forward and backward with every parameter requiring grad."""
    cfg = cfg or RenderConfig()
    rt = Runtime(get_runtime(device).device)
    p = _leaves(scene, cfg)
    w, wa = _weights(scene, cfg, 3)
    runs, fw, bw, meta = [], [], [], None
    for _ in range(repeats + 1):
        ev: list = []
        f_ms, b_ms, meta = fwd_bwd(rt, cfg, scene, p, w, wa, ev)
        per = defaultdict(float)
        for name, e in ev:
            per[name] += event_ms(e)
        runs.append(dict(per))
        fw.append(f_ms)
        bw.append(b_ms)
        rt.finish()
    warm = runs[1:]
    names = sorted({n for r in runs for n in r})
    bnames = [n for n in BWD_STAGES if n in names] + sorted(
        n for n in names if n.endswith("_bwd") and n not in BWD_STAGES)
    fnames = [n for n in names if n not in bnames]
    ftot = [sum(r.get(n, 0.0) for n in fnames) for r in warm]
    btot = [sum(r.get(n, 0.0) for n in bnames) for r in warm]
    res = {
        "scene": scene["name"], "n_gaussians": int(scene["means"].shape[0]), "repeats": repeats,
        "precision": cfg.precision, "intersections": int(meta["flatten_ids"].numel()),
        "backward_stages_ms": {n: summarise([r.get(n, 0.0) for r in warm]) for n in bnames},
        "forward_stages_ms": {n: summarise([r.get(n, 0.0) for r in warm]) for n in fnames},
        "first_call_ms": {n: runs[0].get(n, 0.0) for n in names},
        "forward_kernel_total_ms": summarise(ftot),
        "backward_kernel_total_ms": summarise(btot),
        "forward_wall_ms": summarise(fw[1:]), "backward_wall_ms": summarise(bw[1:]),
        "first_call_wall_ms": {"forward": fw[0], "backward": bw[0]},
    }
    res["first_call_ms"]["backward_kernel_total"] = sum(runs[0].get(n, 0.0) for n in bnames)
    fm, bm = res["forward_kernel_total_ms"]["median"], res["backward_kernel_total_ms"]["median"]
    res["bwd_fwd_ratio_kernels"] = bm / fm if fm > 0 else float("nan")
    res["bwd_fwd_ratio_per_repeat"] = [b / f for b, f in zip(btot, ftot) if f > 0]
    res["bwd_fwd_ratio_wall"] = res["backward_wall_ms"]["median"] / res["forward_wall_ms"]["median"]
    res["bwd_fwd_target"] = 2.5
    res["slot_memory"] = slot_memory(scene, res["intersections"], cfg)
    rt.finish()
    return res


def slot_memory(scene: dict, intersections: int, cfg: RenderConfig | None = None,
                channels: int = 3) -> dict:
    """Gradient-slot bytes per intersection (all parameters, no absgrad) and in total."""
    cfg = cfg or RenderConfig()
    real = torch.empty((), dtype=cfg.dtype).element_size()
    G = engine.slot_width(channels, True, True, False)
    variants = {
        "all params": G,
        "all params + absgrad": engine.slot_width(channels, True, True, True),
        "all params, RGB+ED": engine.slot_width(channels + 1, True, True, False),
        "colours only": engine.slot_width(channels, False, True, False),
        "geometry only": engine.slot_width(channels, True, False, False),
    }
    return {"sizeof_real": real, "slot_width": G, "bytes_per_intersection": G * real,
            "intersections": intersections, "total_bytes": G * real * intersections,
            "total_MiB": G * real * intersections / 2 ** 20,
            "variants_bytes_per_intersection": {k: v * real for k, v in variants.items()}}


def training_steps(scene: dict, steps: int = 5, device=None, cfg: RenderConfig | None = None,
                   lr: float = 1e-3) -> dict:
    """Full training steps per second: forward, L1 loss, backward, Adam step (wall clock)."""
    cfg = cfg or RenderConfig()
    rt = get_runtime(device)
    dt = cfg.dtype
    params = {
        "means": scene["means"].detach().to(dt).clone(),
        "quats": scene["quats"].detach().to(dt).clone(),
        "log_scales": scene["scales"].detach().to(dt).clamp_min(1e-12).log().clone(),
        "logit_opacities": torch.logit(scene["opacities"].detach().to(dt).clamp(1e-4, 1 - 1e-4)).clone(),
        "colors": scene["colors"].detach().to(dt).clone(),
    }
    for v in params.values():
        v.requires_grad_()
    opt = torch.optim.Adam(list(params.values()), lr=lr)
    g = torch.Generator().manual_seed(2)
    C, H, W = int(scene["viewmats"].shape[0]), scene["height"], scene["width"]
    target = torch.rand((C, H, W, 3), generator=g, dtype=torch.float64).to(dt)
    vm, Ks = scene["viewmats"].to(dt), scene["Ks"].to(dt)
    times = []
    for _ in range(steps + 1):
        t0 = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        out, _, _ = clsplat.rasterization(
            params["means"], params["quats"], params["log_scales"].exp(),
            torch.sigmoid(params["logit_opacities"]), params["colors"], vm, Ks, W, H,
            sh_degree=scene["sh_degree"], device=rt, config=cfg)
        loss = (out - target).abs().mean()
        loss.backward()
        opt.step()
        times.append((time.perf_counter() - t0) * 1e3)
    rt.finish()
    s = summarise(times[1:])
    return {"scene": scene["name"], "steps": steps, "step_ms": s, "first_step_ms": times[0],
            "steps_per_s": 1e3 / s["median"], "steps_per_s_best": 1e3 / s["min"],
            "optimiser": f"torch.optim.Adam(lr={lr}) on means, quats, log-scales, logit-opacities, colours/SH",
            "loss": "L1 vs fixed random target"}


def _sh_to_rgb(scene: dict) -> dict:
    sc = dict(scene)
    sc["colors"] = (0.2820947917738781 * scene["colors"][:, 0] + 0.5).clamp(0, 1).contiguous()
    sc["sh_degree"] = None
    return sc


def specialisation(scene: dict, repeats: int = 5, device=None, cfg: RenderConfig | None = None) -> dict:
    """General vs specialised variants, forward+backward device ms, round-robin, medians.

    Cases (baseline = the general variant, ratio = specialised / general, < 1 is a gain):
    ``no_sh``: colours [N,3] vs SH degree 3 (scene must have SH); ``no_depth``: render_mode
    "RGB" vs "RGB+ED"; ``frozen_colours_only`` / ``frozen_means_only``: only colours / only
    means require grad vs every parameter.
    """
    cfg = cfg or RenderConfig()
    rt = get_runtime(device)
    gen = "all grads, RGB" + (f", SH{scene['sh_degree']}" if scene["sh_degree"] is not None else "")
    variants = {gen: (scene, PARAMS, "RGB")}
    if scene["sh_degree"] is not None:
        variants["all grads, colours [N,3], RGB"] = (_sh_to_rgb(scene), PARAMS, "RGB")
    variants[gen.replace("RGB", "RGB+ED")] = (scene, PARAMS, "RGB+ED")
    variants["only colours grad"] = (scene, ("colors",), "RGB")
    variants["only means grad"] = (scene, ("means",), "RGB")
    jobs = {}
    for name, (sc, grad, mode) in variants.items():
        p = _leaves(sc, cfg, grad)
        w, wa = _weights(sc, cfg, 4 if mode == "RGB+ED" else 3)
        fwd_bwd(rt, cfg, sc, p, w, wa, [], mode)  # first call apart (builds)
        rt.finish()
        jobs[name] = (sc, p, w, wa, mode)
    fwd = {n: [] for n in jobs}
    bwd = {n: [] for n in jobs}
    tot = {n: [] for n in jobs}
    for _ in range(repeats):
        for name, (sc, p, w, wa, mode) in jobs.items():
            ev: list = []
            fwd_bwd(rt, cfg, sc, p, w, wa, ev, mode)
            f = sum(event_ms(e) for n, e in ev if n not in BWD_STAGES and not n.endswith("_bwd"))
            b = sum(event_ms(e) for n, e in ev if n in BWD_STAGES or n.endswith("_bwd"))
            fwd[name].append(f)
            bwd[name].append(b)
            tot[name].append(f + b)
            rt.finish()
    med = {n: {"forward_ms": float(np.median(fwd[n])), "backward_ms": float(np.median(bwd[n])),
               "total_ms": float(np.median(tot[n])), "total_ms_min": float(np.min(tot[n])),
               "total_ms_max": float(np.max(tot[n]))} for n in jobs}
    cases = []

    def case(key, special, general, what):
        s, g = med[special], med[general]
        cases.append({"case": key, "specialised": special, "general": general, "what": what,
                      "ratio_total": s["total_ms"] / g["total_ms"],
                      "ratio_forward": s["forward_ms"] / g["forward_ms"],
                      "ratio_backward": (s["backward_ms"] / g["backward_ms"]) if g["backward_ms"] > 0 else None})

    if scene["sh_degree"] is not None:
        case("no_sh", "all grads, colours [N,3], RGB", gen, "colours [N,3] vs SH degree 3")
    case("no_depth", gen, gen.replace("RGB", "RGB+ED"), 'render_mode "RGB" vs "RGB+ED"')
    case("frozen_colours_only", "only colours grad", gen, "only colours require grad vs all")
    case("frozen_means_only", "only means grad", gen, "only means require grad vs all")
    return {"scene": scene["name"], "repeats": repeats, "variants": med, "cases": cases,
            "timing": "device ms of all kernels, forward + backward, round-robin medians"}


def markdown(res: dict) -> str:
    """Backward, training-step, slot-memory and specialisation sections of the stages report."""
    L = ["### Backward pass", "",
         "Forward + backward with every parameter requiring grad (means, quats, scales, opacities, colours/SH), "
         "loss sum(render w) + sum(alpha wa) with fixed random weights; device ms from profiling events, "
         f"median [min-max] over {next(iter(res['backward'].values()))['repeats'] if res['backward'] else '-'} "
         "repeats, first call apart (fresh runtime: program builds and JIT). The forward here records the graph "
         "(keeps per-pixel last indices), so it can differ slightly from the no-grad forward above.", "",
         "| stage | " + " | ".join(f"scene {k}: first call ms | median ms | min-max ms | spread %" for k in res["backward"]) + " |",
         "|---|" + "---|---|---|---|" * len(res["backward"])]
    names = []
    for r in res["backward"].values():
        names += [n for n in r["backward_stages_ms"] if n not in names]
    for n in names:
        cells = []
        for r in res["backward"].values():
            s = r["backward_stages_ms"].get(n)
            cells.append("- | - | - | -" if s is None else
                         f"{r['first_call_ms'].get(n, 0):.2f} | {s['median']:.2f} | {s['min']:.2f}-{s['max']:.2f} | {s['spread_pct']:.0f}")
        L.append(f"| {n} | " + " | ".join(cells) + " |")
    for label, key, first in (("**backward kernels total**", "backward_kernel_total_ms", "backward_kernel_total"),
                              ("forward kernels total (same passes)", "forward_kernel_total_ms", None),
                              ("backward wall (loss.backward())", "backward_wall_ms", "wall_b"),
                              ("forward wall", "forward_wall_ms", "wall_f")):
        cells = []
        for r in res["backward"].values():
            s = r[key]
            fc = (r["first_call_ms"].get(first) if first == "backward_kernel_total" else
                  r["first_call_wall_ms"]["backward"] if first == "wall_b" else
                  r["first_call_wall_ms"]["forward"] if first == "wall_f" else None)
            cells.append(f"{'-' if fc is None else f'{fc:.1f}'} | {s['median']:.1f} | {s['min']:.1f}-{s['max']:.1f} | {s['spread_pct']:.0f}")
        L.append(f"| {label} | " + " | ".join(cells) + " |")
    L.append("")
    for k, r in res["backward"].items():
        rr = r["bwd_fwd_ratio_per_repeat"]
        met = "met" if r["bwd_fwd_ratio_kernels"] <= r["bwd_fwd_target"] else "NOT met"
        L.append(f"* Scene {k}: backward/forward = **{r['bwd_fwd_ratio_kernels']:.2f}x** (device kernels, medians; "
                 f"per repeat {min(rr):.2f}-{max(rr):.2f}; wall {r['bwd_fwd_ratio_wall']:.2f}x); target <= "
                 f"{r['bwd_fwd_target']}x: {met}.")
    L.append("")
    L += ["### Training step", "",
          "One full step: forward, L1 loss against a fixed random target, backward, torch.optim.Adam step on "
          "means, quats, log-scales, logit-opacities and colours/SH (wall clock, first step apart).", "",
          "| scene | step ms median [min-max] | steps/s (median) | steps/s (fastest step) | first step ms |",
          "|---|---|---|---|---|"]
    for k, t in res["training"].items():
        s = t["step_ms"]
        L.append(f"| {k} | {s['median']:.0f} [{s['min']:.0f}-{s['max']:.0f}] | **{t['steps_per_s']:.2f}** | "
                 f"{t['steps_per_s_best']:.2f} | {t['first_step_ms']:.0f} |")
    L.append("")
    L += ["### Gradient-slot memory per intersection", "",
          "The backward's compositing kernel writes one slot row per (tile, Gaussian) intersection; bytes = "
          "`clsplat.stages.slot_width(channels, geom, color, absgrad)` x sizeof(REAL).", "",
          "| scene | intersections | REAL bytes | slot width | bytes / intersection | total slot memory | "
          "variants (bytes / intersection) |", "|---|---|---|---|---|---|---|"]
    for k, r in res["backward"].items():
        m = r["slot_memory"]
        var = ", ".join(f"{n} {b}" for n, b in m["variants_bytes_per_intersection"].items())
        L.append(f"| {k} | {m['intersections']} | {m['sizeof_real']} | {m['slot_width']} | **{m['bytes_per_intersection']}** | "
                 f"{m['total_MiB']:.1f} MiB | {var} |")
    L.append("")
    L += ["### Specialisation gains (issue 5, item 2)", "",
          "Forward + backward device ms of all kernels, each variant once per round (round-robin), medians over "
          "the rounds; ratio = specialised / general (< 1: the specialisation saves time). Differences under "
          "~10% are within this machine's noise.", ""]
    for k, sp in res["specialisation"].items():
        L += [f"Scene {k} ({sp['repeats']} rounds):", "",
              "| variant | forward ms | backward ms | total ms | total min-max |", "|---|---|---|---|---|"]
        for n, v in sp["variants"].items():
            L.append(f"| {n} | {v['forward_ms']:.1f} | {v['backward_ms']:.1f} | {v['total_ms']:.1f} | "
                     f"{v['total_ms_min']:.1f}-{v['total_ms_max']:.1f} |")
        L += ["", "| case | specialised / general, total | forward | backward |", "|---|---|---|---|"]
        for c in sp["cases"]:
            rb = "-" if c["ratio_backward"] is None else f"{c['ratio_backward']:.2f}"
            L.append(f"| {c['what']} | **{c['ratio_total']:.2f}** | {c['ratio_forward']:.2f} | {rb} |")
        L.append("")
    return "\n".join(L) + "\n"
