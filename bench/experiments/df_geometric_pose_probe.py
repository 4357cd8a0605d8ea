"""The pose source "geometric" alone, on any ``--data`` (issue 32): each window's camera-0 motion t ->
t+1 as the fit measures it from the images (:mod:`clsplat.models.drivingforward.geometric_pose`),
against the data's, per window and per speed bin (median % in the moving bins, mean metres
standing, and the tail: the 90th percentile and the largest error; the rotation error in degrees
beside it), beside the constant-motion control when ``--control N`` training windows are given.
``--split train`` reads the windows a ``--pose geometric`` run trains its depth on: a median hides the
few windows whose wrong motion the depth is taught with. ``--true-depth``: the same fit with the
generator's depth in place of the calibrated ground plane (an upper bound: how much of the error is
the plane's).
No training: the fit has no weights, so this is what ``--pose geometric`` reports, at the cost of
the fits alone (~3 CPU s a fit at 176x320).

    .venv/bin/python bench/experiments/df_geometric_pose_probe.py --data pandaset:DIR --split test
    .venv/bin/python bench/experiments/df_geometric_pose_probe.py --data synthetic-cache:DIR --split val \\
        --windows 40 --size 176 320 --control 10
"""
from __future__ import annotations

import argparse
import json


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="--data spec (synthetic: the varied world)")
    p.add_argument("--preset", default="small")
    p.add_argument("--split", default="val", choices=("train", "val", "test"))
    p.add_argument("--windows", type=int, default=None, help="windows 0..N-1 (default: all a recording has; 40 synthetic)")
    p.add_argument("--start", type=int, default=0, help="first window")
    p.add_argument("--size", type=int, nargs=2, metavar=("H", "W"), default=None,
                   help="geometric_size (default: the preset's, else its own size)")
    p.add_argument("--keep", type=float, default=None, help="geometric_keep (default: the preset's)")
    p.add_argument("--max-yaw-rate", type=float, default=None, help="geometric_max_yaw_rate, deg/s (default: the preset's)")
    p.add_argument("--search", type=int, default=None, help="geometric_search, the forward grid's count (default: the preset's)")
    p.add_argument("--true-depth", action="store_true",
                   help="an upper bound: the fit places the ground pixels with the data's own depth, not the "
                        "calibrated plane (synthetic data)")
    p.add_argument("--control", type=int, default=0, metavar="N",
                   help="constant-motion control: camera 0's mean true motion over N training windows")
    p.add_argument("--json", default=None, help="write per-window results here")
    a = p.parse_args(argv)
    if a.true_depth and not a.data.startswith("synthetic"):
        p.error(f"--true-depth: {a.data!r} has no depth maps (synthetic data only)")
    if a.windows is not None and a.windows < 1:
        p.error(f"--windows: expected an int >= 1, got {a.windows}")
    if a.start < 0 or a.control < 0:
        p.error("--start / --control: expected ints >= 0")

    import numpy as np
    import torch

    from clsplat.data.synthetic import SPEED_BINS, speed_bin
    from clsplat.models.common.data import parse_data
    from clsplat.models.common.metrics import pose_errors
    from clsplat.models.common.presets import get_preset
    from clsplat.models.drivingforward.data import camera0_motion, ego_speed, load_triplet
    from clsplat.models.drivingforward.geometric_pose import load_window_motions

    torch.set_num_threads(1)
    try:
        preset = get_preset("drivingforward", a.preset)
        if a.size is not None:
            preset = preset.replace(geometric_size=tuple(a.size))
        if a.keep is not None:
            preset = preset.replace(geometric_keep=a.keep)
        if a.max_yaw_rate is not None:
            preset = preset.replace(geometric_max_yaw_rate=a.max_yaw_rate)
        if a.search is not None:
            preset = preset.replace(geometric_search=a.search)
        src = parse_data(a.data, default_world="varied")
    except ValueError as e:
        p.error(str(e))
    if a.windows is not None:
        n = a.windows
    elif src.synthetic_streets:
        n = 40
    else:                       # every window of the recording's split (windows cycle past the last)
        n = len(src._window_starts(len(src.full_sequence().frames), 3, a.split)) - a.start
    control = None
    if a.control:
        Ts = [camera0_motion(load_triplet(src, i, preset, "train")) for i in range(a.control)]
        control = torch.stack(Ts).mean(0)                           # translation averaged; rotation near I
        U, _, Vt = torch.linalg.svd(control[:3, :3])
        control[:3, :3] = U @ Vt
    rows = []
    for i in range(a.start, a.start + n):
        try:
            s = load_triplet(src, i, preset, a.split)
        except (ValueError, IndexError) as e:
            print(f"window {i}: {e}; stopping")
            break
        T_true = camera0_motion(s)
        M_prev, M = (m.double() for m in load_window_motions(src, i, preset, a.split, None, s, a.true_depth))
        E0 = s["cam_to_ego"][0].double()
        err = pose_errors(torch.linalg.inv(E0) @ M @ E0, T_true)
        # the fit's own check, no truth: t -> t+1 against the inverse of t -> t-1 (equal at constant
        # velocity; a car brakes or turns by far less over one frame than a bad fit is off)
        cons = pose_errors(M, torch.linalg.inv(M_prev))
        row = {"window": i, "speed": ego_speed(s), "t_true_m": err["t_true_m"], "t_pred_m": err["t_pred_m"],
               "t_err_m": err["t_err_m"], "t_err_pct": err["t_err_pct"], "r_err_deg": err["r_err_deg"],
               "consistency_m": cons["t_err_m"], "consistency_deg": cons["r_err_deg"]}
        if control is not None:
            c = pose_errors(control.to(T_true.dtype), T_true)
            row.update({"control_t_err_m": c["t_err_m"], "control_t_err_pct": c["t_err_pct"]})
        rows.append(row)
        pct = "-" if row["t_err_pct"] is None else f"{row['t_err_pct']:.1f} %"
        print(f"window {i}: {row['speed']:.2f} m/s, true {row['t_true_m']:.3f} m, fit {row['t_pred_m']:.3f} m, "
              f"error {row['t_err_m']:.3f} m ({pct}), rotation {row['r_err_deg']:.3f} deg", flush=True)
    print(f"\n{a.data} ({a.split}), fit at {preset.geometric_size or (preset.height, preset.width)}:")
    for name in SPEED_BINS:
        b = [r for r in rows if speed_bin(r["speed"]) == name]
        if not b:
            print(f"  {name:9s} no windows")
            continue
        key = "t_err_m" if name == "standing" else "t_err_pct"
        fit = np.median([r[key] for r in b if r[key] is not None]) if name != "standing" else \
            np.mean([r[key] for r in b])
        unit = "m" if name == "standing" else "%"
        errs = [r[key] for r in b if r[key] is not None]
        rot = [r["r_err_deg"] for r in b]
        line = (f"  {name:9s} n {len(b):2d}  fit {fit:.3f} {unit} (p90 {np.percentile(errs, 90):.3f}, "
                f"max {max(errs):.3f}; rotation median / max {np.median(rot):.3f} / {max(rot):.3f} deg)")
        if control is not None:
            ck = "control_" + key
            c = np.median([r[ck] for r in b if r[ck] is not None]) if name != "standing" else np.mean([r[ck] for r in b])
            line += f"  constant motion {c:.3f} {unit}"
        print(line + f"  (> 10 %: {sum(1 for r in b if name != 'standing' and r['t_err_pct'] > 10)})")
    mov = [r for r in rows if r["t_err_pct"] is not None and speed_bin(r["speed"]) != "standing"]
    if len(mov) >= 3:               # does the fit's own check find its bad windows?
        rank = lambda v: np.argsort(np.argsort(np.asarray(v)))
        for name, k in (("translation", "consistency_m"), ("rotation", "consistency_deg")):
            rho = float(np.corrcoef(rank([r[k] for r in mov]), rank([r["t_err_pct"] for r in mov]))[0, 1])
            print(f"  forward/backward consistency ({name}) against the error, moving windows: Spearman {rho:.2f}")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"args": vars(a), "windows": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
