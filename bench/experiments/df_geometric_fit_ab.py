"""The geometric pose fit (``--pose geometric``) of this tree against another tree's, interleaved
on training windows of the varied world: CPU seconds a fit (one torch thread), medians, whether the
motions are equal bit for bit and, where not, how far apart (translation in metres, rotation in
degrees). The other tree's fit is its ``models/drivingforward/ground_motion.py``, written to a file:

    git show REV:models/drivingforward/ground_motion.py > /tmp/ground_motion_old.py
    .venv/bin/python bench/experiments/df_geometric_fit_ab.py --old /tmp/ground_motion_old.py --rounds 5 \
        [--windows 0 1 2 3] [--max-yaw-rate 30]
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import re
import statistics
import tempfile
import time
from pathlib import Path

import torch


def load_other(path: str):
    """The other tree's module, its relative imports pointed at this tree's package."""
    text = Path(path).read_text()
    text = re.sub(r"^from \.\.(\w+)\.(\w+) import", r"from clsplat.models.\1.\2 import", text, flags=re.M)
    text = re.sub(r"^from \.(\w+) import", r"from clsplat.models.drivingforward.\1 import", text, flags=re.M)
    tmp = Path(tempfile.mkdtemp()) / "ground_motion_other.py"
    tmp.write_text(text)
    spec = importlib.util.spec_from_file_location("ground_motion_other", tmp)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--old", required=True, help="another tree's ground_motion.py")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--windows", type=int, nargs="+", default=[4],
                    help="training windows of the varied world (4: 5.5 m/s)")
    ap.add_argument("--max-yaw-rate", type=float, default=0.0,
                    help="deg/s: the yaw search of geometric_max_yaw_rate (0: none)")
    args = ap.parse_args()
    if args.rounds < 1 or min(args.windows) < 0 or args.max_yaw_rate < 0:
        ap.error(f"--rounds >= 1, --windows >= 0, --max-yaw-rate >= 0: got {args.rounds}, "
                 f"{args.windows}, {args.max_yaw_rate}")
    torch.set_num_threads(1)
    from clsplat.models.common.data import parse_data
    from clsplat.models.common.presets import get_preset
    from clsplat.models.drivingforward import ground_motion as this
    from clsplat.models.drivingforward.data import load_triplet
    other = load_other(args.old)
    import math
    from clsplat.models.common.metrics import pose_errors
    from clsplat.models.drivingforward.geometric_pose import YAW_SEARCH
    preset = get_preset("drivingforward", "small").replace(height=176, width=320)
    src = parse_data("synthetic", default_world="varied")
    yaw = math.radians(args.max_yaw_rate) * 0.1                   # the varied world's 10 Hz frames
    kw = dict(search=(-3.0, 3.0, 301), keep=0.75,     # small's bound at 10 Hz (30 m/s), geometric_keep 0.75
              yaw_search=(-yaw, yaw, YAW_SEARCH) if yaw > 0 else None)
    times: dict[str, list[float]] = {"other": [], "this": []}
    for w in args.windows:
        s = load_triplet(src, w, preset, "train")
        fit_args = (s["images"][1], s["images"][0], s["Ks"], s["cam_to_ego"].double(), 10.0)
        motions = {}
        for _ in range(args.rounds):
            for name, mod in (("other", other), ("this", this)):
                c = time.process_time()
                motions[name] = mod.fit_ground_motion_direct(*fit_args, **kw)
                times[name].append(time.process_time() - c)
        d = pose_errors(motions["this"], motions["other"])
        print(f"window {w}: the same motion bit for bit: {bool(torch.equal(motions['other'], motions['this']))}; "
              f"apart by {d['t_err_m']:.2e} m, {d['r_err_deg']:.2e} deg (other's {d['t_true_m']:.3f} m)", flush=True)
    o, t = statistics.median(times["other"]), statistics.median(times["this"])
    print("CPU s a fit: other", [round(x, 2) for x in times["other"]], "this", [round(x, 2) for x in times["this"]])
    print(f"median other {o:.2f} this {t:.2f}: this / other {t / o:.2f}")


if __name__ == "__main__":
    main()
