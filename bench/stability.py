"""Stability report: the stiff and extreme catalogue of DESIGN.md §5 at increasing severity.

Each case is a small scene (a field of ordinary Gaussians plus the extreme ones) on a 64x48
camera. It is rendered in float32 and float64 by clsplat; reported: max abs error of the
float32 render (colour and alpha) against the float64 one, NaN/Inf counts in both, and the
float32 wall time (median); for the gradients of a fixed random linear loss, the relative L2
error of float32 against float64 (whole scene, worst parameter, the extreme Gaussians alone)
and NaN/Inf counts. Invalid input (NaN/Inf, zero quaternions) must raise ValueError;
the message is recorded.
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import torch

import clsplat

__all__ = ["cases", "run"]

W, H = 64, 48
F = 50.0


def _base(n: int = 64, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    z = 3 + 5 * torch.rand(n, generator=g, dtype=torch.float64)
    x = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * z * W / F
    y = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * z * H / F
    return {"means": torch.stack([x, y, z], -1), "quats": torch.randn(n, 4, generator=g, dtype=torch.float64),
            "scales": 0.05 * torch.exp(0.3 * torch.randn(n, 3, generator=g, dtype=torch.float64)),
            "opacities": 0.2 + 0.6 * torch.rand(n, generator=g, dtype=torch.float64),
            "colors": torch.rand(n, 3, generator=g, dtype=torch.float64)}


def _add(sc: dict, means, quats, scales, opac, colors) -> dict:
    means = torch.as_tensor(means, dtype=torch.float64).reshape(-1, 3)
    k = means.shape[0]
    f = lambda v, shape: torch.as_tensor(v, dtype=torch.float64).expand(*shape).clone()  # noqa: E731
    parts = {"means": f(means, (k, 3)), "quats": f(quats, (k, 4)), "scales": f(scales, (k, 3)),
             "opacities": f(opac, (k,)), "colors": f(colors, (k, 3))}
    return {key: torch.cat([sc[key], parts[key]]) for key in sc}


def _rot_y(deg: float) -> list[float]:
    a = math.radians(deg) / 2
    return [math.cos(a), 0.0, math.sin(a), 0.0]


def cases() -> list[tuple[str, str, dict]]:
    """(category, severity label, scene) triples."""
    out = []
    I = [1.0, 0.0, 0.0, 0.0]  # noqa: E741
    c0 = torch.tensor([[0.0, 0.0, 5.0]])
    for r in (1e2, 1e4, 1e6):
        out.append(("needle", f"axis ratio {r:.0e}", _add(_base(), c0.expand(8, 3) + torch.linspace(-1, 1, 8)[:, None] * torch.tensor([1.0, 0, 0]),
                                                          torch.randn(8, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64),
                                                          [0.3, 0.3 / r, 0.3 / r], 0.9, [1.0, 0.2, 0.2])))
    for ang in (80.0, 89.0, 89.99, 90.0):
        out.append(("grazing", f"{ang} deg from face-on", _add(_base(), c0, _rot_y(ang), [0.5, 0.5, 1e-7], 0.9, [0.1, 0.9, 0.1])))
    for eps in (1e-1, 1e-3, 1e-6):
        out.append(("near plane", f"z = near*(1+{eps:g})", _add(_base(), [[0.0, 0.0, 0.01 * (1 + eps)]], I, [0.05] * 3, 0.9, [1.0, 1.0, 0.0])))
    for k in (2.0, 10.0, 1e3):
        out.append(("off-axis", f"x/z = {k:g}", _add(_base(), [[k * 5.0, 0.0, 5.0]], I, [0.5 * k] * 3, 0.9, [0.0, 1.0, 1.0])))
    for k in (1.0, 10.0, 1e3):
        out.append(("huge", f"{k:g}x image", _add(_base(), c0, I, [k * 5.0 * W / F] * 3, 0.5, [0.5, 0.5, 1.0])))
    for s in (1e-2, 1e-4, 1e-8):
        n = 32
        m = torch.stack([torch.linspace(-2, 2, n), torch.zeros(n), torch.full((n,), 5.0)], -1).double()
        out.append(("sub-pixel", f"sigma {s:g} px", _add(_base(), m, I, [s * 5.0 / F] * 3, 0.9, [1.0, 0.0, 1.0])))
    for k in (10, 100, 1000):
        m = c0.expand(k, 3) + torch.arange(k)[:, None].double() * torch.tensor([0.0, 0.0, 1e-3])
        out.append(("opaque stack", f"{k} x opacity 0.999", _add(_base(), m, I, [0.1] * 3, 0.999,
                                                                 torch.rand(k, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64))))
    for k in (10, 100, 1000):
        m = c0.expand(k, 3) + torch.randn(k, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * torch.tensor([0.3, 0.3, 0.0])
        out.append(("equal depths", f"{k} at z=5", _add(_base(), m, I, [0.1] * 3, 0.7,
                                                        torch.rand(k, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64))))
    for z in (-1e-3, -1.0, -1e3):
        out.append(("behind camera", f"z = {z:g}", _add(_base(), [[0.0, 0.0, z]], I, [abs(z)] * 3, 0.9, [1.0, 0.0, 0.0])))
    for v in (1e-39, 1e-42, 1e-45):
        out.append(("denormal opacity", f"{v:g}", _add(_base(), c0, I, [0.3] * 3, v, [1.0, 1.0, 1.0])))
        out.append(("denormal colour", f"{v:g}", _add(_base(), c0, I, [0.3] * 3, 0.9, [v, v, v])))
    for k in (1, 2, 3):
        out.append(("zero scales", f"{k} axes zero", _add(_base(), c0, I, [0.0] * k + [0.3] * (3 - k), 0.9, [0.2, 0.2, 0.9])))
    return out


def invalid_cases() -> list[tuple[str, str, dict]]:
    out = []
    for key, v in (("means", float("nan")), ("means", float("inf")), ("scales", float("inf")),
                   ("opacities", float("nan")), ("colors", float("nan")), ("quats", float("nan"))):
        sc = _base()
        sc[key][0] = v
        out.append(("NaN/Inf input", f"{key} = {v}", sc))
    sc = _base()
    sc["quats"][0] = 0.0
    out.append(("zero quaternion", "quats[0] = 0", sc))
    return out


def _render(sc: dict, precision: str, device=None):
    dt = torch.float64 if precision == "float64" else torch.float32
    vm = torch.eye(4, dtype=dt)[None]
    K = torch.tensor([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]], dtype=dt)[None]
    c = {k: v.to(dt) for k, v in sc.items()}
    out, alpha, _ = clsplat.rasterization(c["means"], c["quats"], c["scales"], c["opacities"], c["colors"],
                                          vm, K, W, H, precision=precision, device=device)
    return torch.cat([out, alpha], -1).double()


GRAD_PARAMS = ("means", "quats", "scales", "opacities", "colors")


def _grads(sc: dict, precision: str, device=None) -> dict[str, torch.Tensor]:
    """Gradients of sum(render * w) + sum(alpha * wa) (fixed random weights), float64 copies."""
    dt = torch.float64 if precision == "float64" else torch.float32
    vm = torch.eye(4, dtype=dt)[None]
    K = torch.tensor([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]], dtype=dt)[None]
    p = {k: sc[k].to(dt).clone().requires_grad_() for k in GRAD_PARAMS}
    out, alpha, _ = clsplat.rasterization(p["means"], p["quats"], p["scales"], p["opacities"], p["colors"],
                                          vm, K, W, H, precision=precision, device=device)
    g = torch.Generator().manual_seed(1)
    w = torch.rand(out.shape, generator=g, dtype=torch.float64).to(dt)
    wa = torch.rand(alpha.shape, generator=g, dtype=torch.float64).to(dt)
    ((out * w).sum() + (alpha * wa).sum()).backward()
    return {k: (v.grad if v.grad is not None else torch.zeros_like(v)).detach().double() for k, v in p.items()}


def grad_check(sc: dict, device=None, n_base: int = 64) -> dict:
    """Relative L2 error of the float32 gradients against float64 (all parameters together and
    the worst parameter; also over the extreme Gaussians alone, rows ``n_base:``), NaN/Inf
    counts of both; the comparison is over entries finite in both."""
    g32, g64 = _grads(sc, "float32", device), _grads(sc, "float64", device)
    num2 = den2 = en2 = ed2 = 0.0
    per = {}
    for k in GRAD_PARAMS:
        ok = torch.isfinite(g32[k][n_base:]) & torch.isfinite(g64[k][n_base:])
        en2 += float(((g32[k][n_base:] - g64[k][n_base:])[ok]).norm() ** 2)
        ed2 += float((g64[k][n_base:][ok]).norm() ** 2)
        ok = torch.isfinite(g32[k]) & torch.isfinite(g64[k])
        d = float(((g32[k] - g64[k])[ok]).norm() ** 2)
        r = float((g64[k][ok]).norm() ** 2)
        num2, den2 = num2 + d, den2 + r
        per[k] = math.sqrt(d / r) if r > 0 else (0.0 if d == 0 else float("inf"))
    return {"grad_rel_l2": math.sqrt(num2 / den2) if den2 > 0 else 0.0,
            "grad_rel_l2_extreme": math.sqrt(en2 / ed2) if ed2 > 0 else (0.0 if en2 == 0 else float("inf")),
            "grad_norm_extreme_f64": math.sqrt(ed2),
            "grad_rel_l2_worst_param": max(per.items(), key=lambda kv: kv[1]),
            "grad_rel_l2_per_param": per,
            "grad_nonfinite_f32": int(sum((~torch.isfinite(g32[k])).sum() for k in GRAD_PARAMS)),
            "grad_nonfinite_f64": int(sum((~torch.isfinite(g64[k])).sum() for k in GRAD_PARAMS))}


def run(out_dir, device=None, quick: bool = False, repeats: int = 3) -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    repeats = 1 if quick else max(1, repeats)
    cs = cases()
    if quick:  # the mildest and the most severe of each category
        seen: dict[str, list] = {}
        for c in cs:
            seen.setdefault(c[0], []).append(c)
        cs = [v[0] for v in seen.values()] + [v[-1] for v in seen.values() if len(v) > 1]
    rows = []
    for cat, sev, sc in cs:
        row = {"category": cat, "severity": sev, "n_gaussians": int(sc["means"].shape[0])}
        try:
            ref = _render(sc, "float64", device)
            times = []
            for _ in range(repeats + 1):
                t0 = time.perf_counter()
                img = _render(sc, "float32", device)
                times.append((time.perf_counter() - t0) * 1e3)
            finite = torch.isfinite(img) & torch.isfinite(ref)
            d = (img - ref).abs()[finite]
            row.update({"max_abs_err": float(d.max()) if d.numel() else 0.0,
                        "nonfinite_f32": int((~torch.isfinite(img)).sum()),
                        "nonfinite_f64": int((~torch.isfinite(ref)).sum()),
                        "mean_alpha": float(ref[..., -1].mean()),
                        "time_ms": sorted(times[1:])[len(times[1:]) // 2], "outcome": "rendered"})
            try:
                row.update(grad_check(sc, device))
            except Exception as exc:  # noqa: BLE001 - recorded, not fatal
                row["grad_error"] = f"{type(exc).__name__}: {exc}"[:160]
        except ValueError as exc:
            row.update({"outcome": "ValueError", "message": str(exc)[:160]})
        except Exception as exc:  # noqa: BLE001 - recorded as a failure
            row.update({"outcome": f"FAILED {type(exc).__name__}", "message": str(exc)[:160]})
        rows.append(row)
    for cat, sev, sc in invalid_cases():
        row = {"category": cat, "severity": sev, "n_gaussians": int(sc["means"].shape[0])}
        try:
            _render(sc, "float32", device)
            row["outcome"] = "ACCEPTED (expected ValueError)"
        except ValueError as exc:
            row.update({"outcome": "ValueError", "message": str(exc)[:160]})
        rows.append(row)
    res = {"device": clsplat.get_runtime(device).name, "quick": quick, "image": [W, H], "rows": rows}
    (out / "stability.json").write_text(json.dumps(res, indent=1))
    (out / "stability.md").write_text(markdown(res))
    return res


def markdown(res: dict) -> str:
    L = ["## Stability (DESIGN.md §5)", "",
         f"{res['image'][0]}x{res['image'][1]} camera, 64 ordinary Gaussians plus the extreme ones. Error: max abs "
         "of the float32 render (RGB and alpha) against the float64 render, over finite pixels. Gradient "
         "error: relative L2 of the float32 gradients of sum(render w) + sum(alpha wa) (fixed random w, wa) "
         "wrt means, quats, scales, opacities and colours against the float64 gradients of the same engine, all "
         "parameters together (worst single parameter in brackets; a parameter whose float64 gradient is ~0 "
         "inflates its own figure), and over the extreme Gaussians' own gradients alone (rows after the 64 ordinary ones; "
         "0 when their float64 gradient is exactly 0, e.g. culled); NaN/Inf: counts in the gradients.", "",
         "| category | severity | N | outcome | max abs err f32 vs f64 | NaN/Inf f32 | NaN/Inf f64 | grad rel L2 f32 vs f64 "
         "(worst param) | grad rel L2, extreme Gaussians | grad NaN/Inf f32 | grad NaN/Inf f64 | mean alpha | f32 ms |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        if r["outcome"] == "rendered":
            if "grad_rel_l2" in r:
                wk, wv = r["grad_rel_l2_worst_param"]
                gs = (f"{r['grad_rel_l2']:.2e} ({wk} {wv:.1e}) | {r['grad_rel_l2_extreme']:.2e} | {r['grad_nonfinite_f32']} | "
                      f"{r['grad_nonfinite_f64']}")
            else:
                gs = f"{r.get('grad_error', '-')[:60].replace('|', '/')} | - | - | -"
            L.append(f"| {r['category']} | {r['severity']} | {r['n_gaussians']} | rendered | {r['max_abs_err']:.2e} | "
                     f"{r['nonfinite_f32']} | {r['nonfinite_f64']} | {gs} | {r['mean_alpha']:.3f} | {r['time_ms']:.1f} |")
        else:
            msg = r.get("message", "").replace("|", "/")
            L.append(f"| {r['category']} | {r['severity']} | {r['n_gaussians']} | {r['outcome']}: {msg[:90]} | - | - | - | - | - | - | - | - | - |")
    return "\n".join(L) + "\n"
