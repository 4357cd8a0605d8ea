"""Why crawling windows read as standing under ``--pose geometric`` (issue 32): the direct fit's cost
along the true motion, per window, under rendering and pixel-selection variants.

For each window (frames t -> t+1, read at ``--size``) and each ``--supersample`` s (the generator's
rays per pixel side, area averaged), prints the fit's own cost (mean absolute grey residual
truncated at tau over the ground prior's pixels within the cap, a pixel moved out of view counts
tau; :func:`~clsplat.models.drivingforward.ground_motion.fit_ground_motion_direct`) at 0, 0.25, ...,
1.5 x the true ego motion (the whole 6-dof twist scaled; ``--translation-only``: its translation with
no rotation, the line the fit's 1-D search walks), the fit's answer and its error, and the
CPU seconds of rendering the triplet. Variants of the cost (H3, pixel selection; the fit itself is
unchanged unless ``--fit-variants``): ``trim``: the lowest 75 % of the truncated residuals only;
``cap10``: ground within 10 m only. H2's floor: the cost of frame t against itself resampled by a
half-pixel shift (x and y, averaged), no ground truth; ``ratio0`` = cost(0) / floor.

Ground truth is read only to score (the true twist for the cost curve, the error); nothing is fitted
to it. Development windows only (train / val), never test streets.

    .venv/bin/python bench/experiments/df_slow_window_probe.py --split val --windows 19 27 36 --supersample 1 2 3
    .venv/bin/python bench/experiments/df_slow_window_probe.py --split train --windows 6 7 12 --supersample 1 2
"""
from __future__ import annotations

import argparse
import json
import time

SCALES = (0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default="synthetic")
    p.add_argument("--split", default="val", choices=("train", "val"))
    p.add_argument("--windows", type=int, nargs="+", required=True)
    p.add_argument("--supersample", type=int, nargs="+", default=[1])
    p.add_argument("--size", type=int, nargs=2, default=[176, 320])
    p.add_argument("--cap", type=float, default=20.0)
    p.add_argument("--tau", type=float, default=0.05)
    p.add_argument("--no-fit", action="store_true", help="cost curves only (no fit)")
    p.add_argument("--grid2d", action="store_true",
                   help="also the plain and trimmed costs' argmin over forward translation x yaw (0.05 m x 0.25 deg "
                        "over +-3 m x +-2 deg): whether a search that steps the yaw finds the truth")
    p.add_argument("--translation-only", action="store_true",
                   help="the curve scales the true translation with no rotation (what the fit's 1-D search sees)")
    p.add_argument("--keep", type=float, nargs="+", default=[1.0],
                   help="the fit's search keeps this share of the lowest residuals (one fit per value)")
    p.add_argument("--json", default=None)
    a = p.parse_args(argv)

    import dataclasses

    import torch

    from clsplat.models.common.data import parse_data
    from clsplat.models.common.geometry import matrix_to_axis_angle
    from clsplat.models.common.metrics import pose_errors
    from clsplat.models.common.presets import get_preset
    from clsplat.models.drivingforward.data import ego_speed, gt_ego_motion, load_triplet
    from clsplat.models.drivingforward.depth import ground_prior_depth
    from clsplat.models.drivingforward.ground_motion import (_sample, fit_ground_motion_direct, ground_points,
                                                              plane_flow)

    torch.set_num_threads(1)
    dt = torch.float64
    H, W = a.size
    src = parse_data(a.data, default_world="varied")
    base = get_preset("drivingforward", "small")
    rows = []
    for i in a.windows:
        for ss in a.supersample:
            q = dataclasses.replace(base, height=H, width=W, supersample=ss)
            c0 = time.process_time()
            s = load_triplet(src, i, q, a.split)
            render_s = time.process_time() - c0
            E, K = s["cam_to_ego"].double(), s["Ks"].double()
            V = E.shape[0]
            g1 = s["images"][1].double().mean(1, keepdim=True)
            g2 = s["images"][2].double().mean(1, keepdim=True)
            Z = ground_prior_depth(K, E, H, W, a.cap)
            prior = (Z < a.cap).reshape(V, -1)
            near = (Z < 10.0).reshape(V, -1)
            uv, X = ground_points(K, Z)
            A = g1.reshape(V, -1)
            M = gt_ego_motion(s)[2].double()
            th_true = torch.cat([matrix_to_axis_angle(M[:3, :3]), M[:3, 3]])
            if a.translation_only:
                th_true[:3] = 0

            def costs(th):
                v, inside = _sample(g2, uv + plane_flow(th, K, E, uv, X))
                e = torch.where(inside, (v[:, 0] - A).abs().clamp(max=a.tau), torch.full_like(A, a.tau))
                ep = e[prior]
                k = int(0.75 * ep.numel())
                return {"plain": float(ep.mean()), "trim": float(ep.sort().values[:k].mean()),
                        "cap10": float(e[near].mean())}

            curve = {f"{sc:g}": costs(th_true * sc) for sc in SCALES}
            if a.grid2d:
                best = {"plain": (float("inf"), 0.0, 0.0), "trim": (float("inf"), 0.0, 0.0)}
                for tx in torch.arange(-3.0, 3.0 + 1e-9, 0.05, dtype=dt):
                    for wz in torch.arange(-2.0, 2.0 + 1e-9, 0.25, dtype=dt):
                        th = torch.zeros(6, dtype=dt)
                        th[2], th[3] = wz * torch.pi / 180, tx
                        c = costs(th)
                        for key in best:
                            if c[key] < best[key][0]:
                                best[key] = (c[key], float(tx), float(wz))
                grid2d = {k: {"cost": v[0], "tx": v[1], "wz_deg": v[2]} for k, v in best.items()}
                print(f"  grid2d: true tx {float(M[0, 3]):+.3f} wz {float(th_true[2]) * 180 / torch.pi:+.2f} deg | "
                      + " | ".join(f"{k} argmin tx {v['tx']:+.2f} wz {v['wz_deg']:+.2f}" for k, v in grid2d.items()),
                      flush=True)
            # H2's floor: frame t against itself read half a pixel away (x, then y), no ground truth
            fl = []
            for d in ((0.5, 0.0), (0.0, 0.5)):
                v, inside = _sample(g1, uv + torch.tensor(d, dtype=dt)[None, :, None])
                fl.append(float((v[:, 0] - A).abs().clamp(max=a.tau)[prior & inside].mean()))
            floor = sum(fl) / 2
            row = {"window": i, "split": a.split, "supersample": ss, "speed": ego_speed(s),
                   "t_true_m": float(M[:3, 3].norm()), "render_cpu_s": render_s, "curve": curve,
                   "floor": floor, "ratio0": curve["0"]["plain"] / floor}
            fits = []
            for keep in ([] if a.no_fit else a.keep):
                c1 = time.process_time()
                bound = 30.0 * float(s["timestamps"][2] - s["timestamps"][1])
                Mf = fit_ground_motion_direct(s["images"][1], s["images"][2], s["Ks"], E, a.cap,
                                              search=(-bound, bound, 301), keep=keep)
                err = pose_errors(Mf, M)
                fits.append({"keep": keep, "fit_t_m": err["t_pred_m"], "fit_err_pct": err["t_err_pct"],
                             "fit_err_m": err["t_err_m"], "fit_cpu_s": time.process_time() - c1})
            row["fits"] = fits
            rows.append(row)
            cv = "  ".join(f"{k}:{v['plain']:.5f}" for k, v in curve.items())
            tr = "  ".join(f"{k}:{v['trim']:.5f}" for k, v in curve.items())
            c10 = "  ".join(f"{k}:{v['cap10']:.5f}" for k, v in curve.items())
            fit = "".join(f" fit(keep {f['keep']:g}) {f['fit_t_m']:.3f} m ({f['fit_err_pct'] or 0:.1f} %, "
                          f"{f['fit_cpu_s']:.1f} CPU s)" for f in fits)
            print(f"{a.split} {i} ss{ss}: {row['speed']:.2f} m/s true {row['t_true_m']:.3f} m{fit}; render "
                  f"{render_s:.1f} CPU s; floor {floor:.5f} ratio0 {row['ratio0']:.2f}\n  plain {cv}\n  trim  {tr}\n"
                  f"  cap10 {c10}", flush=True)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"args": vars(a), "rows": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
