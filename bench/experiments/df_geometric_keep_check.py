"""``geometric_keep`` against the plain fit on the same windows (issue 32): camera 0's t -> t+1 motion
as :func:`~clsplat.models.drivingforward.geometric_pose.window_motions` fits it (same search, cap and
bound), once per ``--keep`` value on the same rendered frames, scored as
``df_geometric_pose_probe.py`` scores it (median % per moving speed bin, mean metres standing,
windows > 10 % off). Also, per window, H2's no-ground-truth standing test: ``ratio0`` = the fit's
cost at zero motion over a floor the window gives itself (frame t against itself read half a pixel
away, x and y averaged), to report its distribution for standing and moving windows.

Ground truth only scores. Development splits only (train / val); never test streets.

    .venv/bin/python bench/experiments/df_geometric_keep_check.py --split val --start 80 --windows 40 \\
        --keep 1 0.75 --json OUT.json
"""
from __future__ import annotations

import argparse
import json
import time


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default="synthetic")
    p.add_argument("--split", default="val", choices=("train", "val"))
    p.add_argument("--start", type=int, default=0)
    p.add_argument("--windows", type=int, default=40)
    p.add_argument("--size", type=int, nargs=2, default=[176, 320])
    p.add_argument("--keep", type=float, nargs="+", default=[1.0, 0.75])
    p.add_argument("--json", default=None)
    a = p.parse_args(argv)
    if a.windows < 1 or a.start < 0:
        p.error("--windows / --start: expected ints >= 1 / >= 0")

    import dataclasses

    import numpy as np
    import torch

    from clsplat.data.synthetic import SPEED_BINS, speed_bin
    from clsplat.models.common.data import parse_data
    from clsplat.models.common.metrics import pose_errors
    from clsplat.models.common.presets import get_preset
    from clsplat.models.drivingforward.data import camera0_motion, ego_speed, load_triplet
    from clsplat.models.drivingforward.depth import ground_prior_depth
    from clsplat.models.drivingforward.geometric_pose import GROUND_CAP_DEFAULT
    from clsplat.models.drivingforward.ground_motion import _sample, fit_ground_motion_direct, ground_points

    torch.set_num_threads(1)
    dt = torch.float64
    H, W = a.size
    preset = get_preset("drivingforward", "small").replace(geometric_size=(H, W))
    cap = preset.ground_prior_cap if preset.ground_prior_cap is not None else GROUND_CAP_DEFAULT
    src = parse_data(a.data, default_world="varied")
    rows = []
    for i in range(a.start, a.start + a.windows):
        s = load_triplet(src, i, dataclasses.replace(preset, height=H, width=W), a.split)
        E, K = s["cam_to_ego"].double(), s["Ks"].double()
        V = E.shape[0]
        T_true = camera0_motion(s)
        E0 = E[0]
        bound = preset.geometric_max_speed * abs(float(s["timestamps"][2] - s["timestamps"][1]))
        row = {"window": i, "speed": ego_speed(s), "t_true_m": float(T_true[:3, 3].norm()), "fits": {}}
        for keep in a.keep:
            c0 = time.process_time()
            M = fit_ground_motion_direct(s["images"][1], s["images"][2], s["Ks"], E, cap,
                                         search=(-bound, bound, preset.geometric_search), keep=keep)
            err = pose_errors(torch.linalg.inv(E0) @ M.double() @ E0, T_true)
            row["fits"][f"{keep:g}"] = {"t_pred_m": err["t_pred_m"], "t_err_m": err["t_err_m"],
                                        "t_err_pct": err["t_err_pct"], "cpu_s": time.process_time() - c0}
        # H2: cost at zero motion against the window's own half-pixel floor (the fit's truncation)
        g1 = s["images"][1].double().mean(1, keepdim=True)
        g2 = s["images"][2].double().mean(1, keepdim=True)
        Z = ground_prior_depth(K, E, H, W, cap)
        prior = (Z < cap).reshape(V, -1)
        uv, _ = ground_points(K, Z)
        A = g1.reshape(V, -1)
        c0_ = float((g2.reshape(V, -1) - A).abs().clamp(max=0.05)[prior].mean())
        fl = []
        for d in ((0.5, 0.0), (0.0, 0.5)):
            v, inside = _sample(g1, uv + torch.tensor(d, dtype=dt)[None, :, None])
            fl.append(float((v[:, 0] - A).abs().clamp(max=0.05)[prior & inside].mean()))
        row.update({"cost0": c0_, "floor": sum(fl) / 2, "ratio0": c0_ / (sum(fl) / 2)})
        rows.append(row)
        fits = "  ".join(f"keep {k}: {f['t_pred_m']:.3f} m ({f['t_err_pct'] or 0:.1f} %, {f['cpu_s']:.1f} s)"
                         for k, f in row["fits"].items())
        print(f"window {i}: {row['speed']:.2f} m/s true {row['t_true_m']:.3f} m | {fits} | ratio0 "
              f"{row['ratio0']:.2f}", flush=True)
    print(f"\n{a.data} ({a.split}) windows {a.start}-{a.start + a.windows - 1}, fit at {H}x{W}:")
    for keep in (f"{k:g}" for k in a.keep):
        parts = []
        for name in SPEED_BINS:
            b = [r for r in rows if speed_bin(r["speed"]) == name]
            if not b:
                parts.append(f"{name} -")
            elif name == "standing":
                parts.append(f"standing {np.mean([r['fits'][keep]['t_err_m'] for r in b]):.3f} m (n {len(b)})")
            else:
                e = [r["fits"][keep]["t_err_pct"] for r in b]
                parts.append(f"{name} {np.median(e):.1f} % (n {len(b)}, > 10 %: {sum(x > 10 for x in e)})")
        print(f"  keep {keep}: " + "; ".join(parts))
    st = sorted(r["ratio0"] for r in rows if speed_bin(r["speed"]) == "standing")
    mv = sorted(r["ratio0"] for r in rows if speed_bin(r["speed"]) != "standing")
    print(f"  ratio0 standing: {[round(x, 2) for x in st]}\n  ratio0 moving: {[round(x, 2) for x in mv]}")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"args": vars(a), "windows": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
