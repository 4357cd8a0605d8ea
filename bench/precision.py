"""Work-precision diagram (DESIGN.md §6, project issue 5, forward part).

Every accuracy knob of :class:`clsplat.RenderConfig` (and SH truncation and pruning, which act
on the input) is one point: render error against the float64 default-config render of the
same scene (max abs error, RMSE, PSNR with peak 1, over every colour channel and alpha) and
time (median device ms of all kernels; wall ms too). The Pareto front is over (best-of-repeats kernel ms, RMSE): on a
shared, noisy machine the minimum is the steadier estimate of a configuration's cost.

Gradient columns: :data:`GRADIENT_METRIC` is called with (scene, config, reference grads) and
returns the relative L2 error of the gradients, or None. It is active once a render through
:func:`clsplat.rasterization` has a ``grad_fn`` (the backward pass has landed).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

import clsplat
from clsplat.config import RenderConfig

from . import scenes as S
from .figure import save_figure

__all__ = ["knob_points", "run", "autograd_available", "gradients", "pareto_front"]

GRAD_PARAMS = ("means", "quats", "scales", "opacities", "colors")


def autograd_available(device=None) -> bool:
    """True when clsplat.rasterization records a graph (backward implemented)."""
    sc = S.random_frustum_scene(20, 32, 24, None, 0)
    m = sc["means"].clone().requires_grad_()
    try:
        out, _, _ = clsplat.rasterization(m, sc["quats"], sc["scales"], sc["opacities"], sc["colors"],
                                          sc["viewmats"], sc["Ks"], 32, 24, device=device)
    except Exception:  # noqa: BLE001 - any failure means: not usable for gradients
        return False
    return out.grad_fn is not None


def gradients(scene: dict, cfg: RenderConfig, device=None, seed: int = 1) -> dict[str, torch.Tensor]:
    """Gradients of sum(render * w) (w fixed random weights) wrt the Gaussian parameters."""
    dt = cfg.dtype
    p = {k: scene[k].detach().to(dt).clone().requires_grad_() for k in GRAD_PARAMS}
    out, alpha, _ = clsplat.rasterization(p["means"], p["quats"], p["scales"], p["opacities"], p["colors"],
                                          scene["viewmats"].to(dt), scene["Ks"].to(dt), scene["width"],
                                          scene["height"], sh_degree=scene["sh_degree"], config=cfg,
                                          device=device)
    g = torch.Generator().manual_seed(seed)
    w = torch.rand(out.shape, generator=g, dtype=torch.float64).to(dt)
    wa = torch.rand(alpha.shape, generator=g, dtype=torch.float64).to(dt)
    ((out * w).sum() + (alpha * wa).sum()).backward()
    return {k: (v.grad if v.grad is not None else torch.zeros_like(v)).detach().double() for k, v in p.items()}


def grad_rel_l2(scene: dict, cfg: RenderConfig, ref: dict, device=None) -> dict[str, float]:
    g = gradients(scene, cfg, device)
    out, num2, den2 = {}, 0.0, 0.0
    for k in ref:
        gk = g[k]
        if gk.shape != ref[k].shape:  # truncated SH: the dropped coefficients get no gradient
            gk = torch.cat([gk, torch.zeros(ref[k].shape[0], ref[k].shape[1] - gk.shape[1], *gk.shape[2:],
                                            dtype=gk.dtype)], 1)
        out[k] = float((gk - ref[k]).norm() / ref[k].norm().clamp_min(1e-300))
        num2 = num2 + float((gk - ref[k]).norm() ** 2)
        den2 = den2 + float(ref[k].norm() ** 2)
    # Per-parameter errors blow up where the reference gradient is ~0 (e.g. quats of isotropic
    # Gaussians); "all" is the relative L2 error over all parameters together.
    out["all"] = math.sqrt(num2 / den2) if den2 > 0 else 0.0
    return out


#: pluggable gradient metric: (scene, cfg, reference grads, device) -> {param: rel L2} or None
GRADIENT_METRIC = grad_rel_l2


def knob_points(scene: dict, quick: bool = False) -> list[dict]:
    """The points: {"knob", "value", "config", optional "sh_degree", optional "budget"}."""
    d = RenderConfig()
    pts = [{"knob": "precision", "value": "float64", "config": d.with_(precision="float64")},
           {"knob": "precision", "value": "float32", "config": d}]
    for a in ((2 / 255, 8 / 255) if quick else (0.25 / 255, 0.5 / 255, 2 / 255, 4 / 255, 8 / 255, 16 / 255)):
        pts.append({"knob": "alpha_min", "value": a, "config": d.with_(alpha_min=a)})
    for t in ((1e-2,) if quick else (1e-6, 1e-5, 1e-3, 1e-2, 3e-2, 1e-1)):
        pts.append({"knob": "t_min", "value": t, "config": d.with_(t_min=t)})
    for r in ("opacity", "4sigma"):
        pts.append({"knob": "radius_rule", "value": r, "config": d.with_(radius_rule=r)})
    pts.append({"knob": "fast_math", "value": True, "config": d.with_(fast_math=True)})
    if scene["sh_degree"] is not None:
        for deg in range(scene["sh_degree"]):
            pts.append({"knob": "sh_degree", "value": deg, "config": d, "sh_degree": deg})
    for frac in ((0.5,) if quick else (0.75, 0.5, 0.25, 0.1)):
        pts.append({"knob": "prune_budget", "value": frac, "config": d, "budget": frac})
    return pts


def importance(scene: dict, device=None) -> torch.Tensor:
    """opacity x screen footprint (sum over cameras of pi rx ry, from the float64 projection)."""
    _, _, meta = clsplat.rasterization(**S.render_args(scene), precision="float64", device=device)
    r = meta["radii"].double()
    return scene["opacities"].double() * (math.pi * r[..., 0] * r[..., 1]).sum(0)


def _apply(scene: dict, pt: dict, imp: torch.Tensor | None) -> dict:
    sc = dict(scene)
    if "sh_degree" in pt:
        deg = pt["sh_degree"]
        sc["sh_degree"] = deg
        sc["colors"] = scene["colors"][:, :(deg + 1) ** 2].contiguous()
    if "budget" in pt:
        k = max(1, int(round(pt["budget"] * scene["means"].shape[0])))
        keep = torch.sort(torch.topk(imp, k).indices).values
        for key in ("means", "quats", "scales", "opacities", "colors"):
            sc[key] = scene[key][keep].contiguous()
    return sc


def _image(st) -> torch.Tensor:
    """[C,H,W,CH+1]: composited channels and alpha, float64."""
    return torch.cat([st.render.double(), st.alpha.double()], -1)


def _errors(img: torch.Tensor, ref: torch.Tensor) -> dict:
    d = (img - ref).abs()
    mse = float((d ** 2).mean())
    return {"max_abs": float(d.max()), "rmse": math.sqrt(mse),
            "psnr": (10 * math.log10(1 / mse)) if mse > 0 else float("inf"),
            "nonfinite": int((~torch.isfinite(img)).sum())}


def pareto_front(points: list[dict], x: str = "kernel_ms_min", y: str = "rmse") -> list[int]:
    """Indices of the points not dominated in (x, y), both minimised."""
    idx = sorted(range(len(points)), key=lambda i: (points[i][x], points[i][y]))
    front, best = [], float("inf")
    for i in idx:
        if points[i][y] < best:
            front.append(i)
            best = points[i][y]
    return front


def run_scene(scene: dict, repeats: int, device=None, quick: bool = False, with_grads: bool = False) -> list[dict]:
    """Errors from one render per point; times from ``repeats`` rounds that visit every point
    once per round (round-robin), so that load from other processes hits all points alike."""
    from .stages import _inputs, run_forward
    from .timing import event_ms

    rt = clsplat.get_runtime(device)
    ref_cfg = RenderConfig(precision="float64")
    ref = _image(run_forward(rt, ref_cfg, scene))
    rt.finish()
    ref_grads = gradients(scene, ref_cfg, device) if with_grads else None
    pts = [{"knob": "precision", "value": "float64 (reference)", "config": ref_cfg, "_ref": True}] + knob_points(scene, quick)[1:]
    imp = importance(scene, device) if any("budget" in p for p in pts) else None
    jobs = []
    for pt in pts:
        sc = _apply(scene, pt, imp)
        x = _inputs(sc, pt["config"])
        st = run_forward(rt, pt["config"], sc, inputs=x)  # first call: builds, and the image
        jobs.append((pt, sc, x, _image(st)))
        rt.finish()
    times = [[] for _ in jobs]
    comp = [[] for _ in jobs]
    for _ in range(repeats):
        for i, (pt, sc, x, _) in enumerate(jobs):
            ev: list = []
            run_forward(rt, pt["config"], sc, ev, x)
            rt.queue.finish()
            times[i].append(sum(event_ms(e) for _, e in ev))
            comp[i].append(sum(event_ms(e) for n, e in ev if n == "composite"))
            rt.finish()
    default_img = next(img for pt, _, _, img in jobs if pt["knob"] == "precision" and pt["value"] == "float32")
    rows = []
    for i, (pt, sc, x, img) in enumerate(jobs):
        cfg = pt["config"]
        row = {"scene": scene["name"], "knob": pt["knob"], "value": "float64" if pt.get("_ref") else pt["value"],
               "precision": cfg.precision, "n_gaussians": int(sc["means"].shape[0]),
               "kernel_ms": float(np.median(times[i])), "kernel_ms_min": float(np.min(times[i])),
               "kernel_ms_max": float(np.max(times[i])), "composite_ms": float(np.median(comp[i])),
               **_errors(img, ref), "grad_rel_l2": None,
               "max_abs_vs_default": float((img - default_img).abs().max())}
        if with_grads and GRADIENT_METRIC is not None and "budget" not in pt:
            try:
                row["grad_rel_l2"] = GRADIENT_METRIC(sc, cfg, ref_grads, device)
            except Exception as exc:  # noqa: BLE001 - recorded, not fatal
                row["grad_rel_l2"] = {"error": f"{type(exc).__name__}: {exc}"[:200]}
        rows.append(row)
    for i in pareto_front(rows):
        rows[i]["pareto"] = True
    return rows


TOL = 1 / 255


def faster_within_tolerance(rows: list[dict], tol: float = TOL) -> dict:
    """Settings faster than the float32 default (median and best-of-repeats kernel ms) whose max
    image error is below ``tol``, against the float64 reference and against the default render."""
    d = next(r for r in rows if r["knob"] == "precision" and r["value"] == "float32")
    out = {"default_kernel_ms": d["kernel_ms"], "default_kernel_ms_min": d["kernel_ms_min"],
           "default_max_abs_vs_f64": d["max_abs"], "tolerance": tol, "vs_f64": [], "vs_default": []}
    for r in rows:
        if r is d or r["knob"] == "precision":
            continue
        faster = r["kernel_ms"] < d["kernel_ms"] and r["kernel_ms_min"] < d["kernel_ms_min"]
        if not faster:
            continue
        item = {"knob": r["knob"], "value": r["value"], "saving_median_pct": 100 * (1 - r["kernel_ms"] / d["kernel_ms"]),
                "saving_min_pct": 100 * (1 - r["kernel_ms_min"] / d["kernel_ms_min"]),
                "max_abs": r["max_abs"], "max_abs_vs_default": r["max_abs_vs_default"]}
        if r["max_abs"] < tol:
            out["vs_f64"].append(item)
        if r["max_abs_vs_default"] < tol:
            out["vs_default"].append(item)
    return out


def plot(rows_by_scene: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(rows_by_scene), figsize=(6.5 * len(rows_by_scene), 5), squeeze=False)
    colors = {"precision": "k", "alpha_min": "tab:blue", "t_min": "tab:orange", "radius_rule": "tab:green",
              "fast_math": "tab:red", "sh_degree": "tab:purple", "prune_budget": "tab:brown"}
    for ax, (name, rows) in zip(axes[0], rows_by_scene.items()):
        floor = 1e-12
        for knob, col in colors.items():
            sel = [r for r in rows if r["knob"] == knob]
            if sel:
                ax.scatter([r["kernel_ms_min"] for r in sel], [max(r["rmse"], floor) for r in sel], c=col, label=knob, s=28)
                for r in sel:
                    ax.annotate(str(r["value"])[:6], (r["kernel_ms_min"], max(r["rmse"], floor)), fontsize=6,
                                xytext=(3, 2), textcoords="offset points")
        front = sorted((r for r in rows if r.get("pareto")), key=lambda r: r["kernel_ms_min"])
        ax.step([r["kernel_ms_min"] for r in front], [max(r["rmse"], floor) for r in front], where="post",
                color="gray", ls="--", lw=1, label="Pareto front")
        ax.scatter([r["kernel_ms_min"] for r in front], [max(r["rmse"], floor) for r in front], s=90,
                   facecolors="none", edgecolors="gray")
        ax.set_yscale("log")
        ax.set_xlabel("device time of all kernels, ms (best of repeats)")
        ax.set_ylabel("RMSE vs float64 default render (floor 1e-12)")
        ax.set_title(name, fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    save_figure(fig, path, dpi=110)


def markdown(res: dict) -> str:
    L = ["## Work-precision (forward)", "",
         f"Error against the float64 default-config render (colour channels and alpha); time = device ms "
         f"of all kernels over {res['repeats']} repeats (min and median); Pareto front over (min ms, RMSE); "
         "pruning keeps the Gaussians of highest opacity x footprint (pi rx ry summed over cameras). Gradient metric: "
         + ("relative L2 error vs float64 gradients." if res["with_grads"] else
            "not measured (clsplat.rasterization has no grad_fn yet)."), ""]
    for name, rows in res["scenes"].items():
        L += [f"### {name}", "", "| knob | value | N | kernel ms min | kernel ms median | composite ms median | max abs err | RMSE | PSNR dB | grad rel L2 (all params) | Pareto |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            g = r["grad_rel_l2"]
            gs = "-" if g is None else (f"{g['all']:.2e}" if isinstance(g, dict) and "all" in g else "err")
            v = f"{r['value']:.4g}" if isinstance(r["value"], float) else str(r["value"])
            L.append(f"| {r['knob']} | {v} | "
                     f"{r['n_gaussians']} | {r['kernel_ms_min']:.1f} | {r['kernel_ms']:.1f} | {r['composite_ms']:.1f} | {r['max_abs']:.2e} | "
                     f"{r['rmse']:.2e} | {r['psnr']:.1f} | {gs} | {'*' if r.get('pareto') else ''} |")
        L.append("")
        f = faster_within_tolerance(rows)

        def lst(items, key):
            def val(v):
                return f"{v:.4g}" if isinstance(v, float) else str(v)
            return "; ".join(f"{i['knob']}={val(i['value'])} (-{i['saving_median_pct']:.0f}% median, "
                             f"-{i['saving_min_pct']:.0f}% best; max err {i[key]:.1e})" for i in items)
        L.append(f"**Faster than the float32 default with max image error < 1/255?** Faster = lower median and lower "
                 f"best-of-repeats kernel ms than the default ({f['default_kernel_ms']:.1f} / {f['default_kernel_ms_min']:.1f} ms); "
                 "savings under ~10% are within noise.")
        L.append("")
        if f["default_max_abs_vs_f64"] >= TOL:
            L.append(f"* Against the float64 reference: none can be, the float32 default itself has max error "
                     f"{f['default_max_abs_vs_f64']:.2e} >= 1/255 (early-stop flips between precisions)."
                     + (f" Faster settings that stay within 1/255 of the float32 default render: {lst(f['vs_default'], 'max_abs_vs_default')}."
                        if f["vs_default"] else " No faster setting stays within 1/255 of the float32 default render either."))
        else:
            L.append("* Against the float64 reference: " + (lst(f["vs_f64"], "max_abs") if f["vs_f64"] else
                                                             "**none** (no setting is both faster and within 1/255)") + ".")
            L.append("* Against the float32 default render: " + (lst(f["vs_default"], "max_abs_vs_default") if f["vs_default"]
                                                                  else "none") + ".")
        L.append("")
    return "\n".join(L) + "\n"


def run(out_dir, device=None, quick: bool = False, repeats: int = 3) -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if quick:
        repeats = min(repeats, 1)
        scs = [S.scene_a(n=1500, width=96, height=64), S.scene_b(height=24, width=40)]
    else:
        scs = [S.scene_a(), S.scene_b()]
    with_grads = autograd_available(device)
    res = {"device": clsplat.get_runtime(device).name, "quick": quick, "repeats": repeats,
           "with_grads": with_grads, "scenes": {}, "faster_within_1_255": {}}
    for sc in scs:
        res["scenes"][sc["name"]] = run_scene(sc, repeats, device, quick, with_grads)
        res["faster_within_1_255"][sc["name"]] = faster_within_tolerance(res["scenes"][sc["name"]])
    (out / "precision.json").write_text(json.dumps(res, indent=1, default=str))
    (out / "precision.md").write_text(markdown(res))
    plot(res["scenes"], out / "precision.png")
    return res
