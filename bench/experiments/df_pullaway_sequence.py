"""A PandaSet-format sequence of an ego that stands, then pulls away: what a user with one recorded
sequence trains DrivingForward on (issue 32's "PandaSet-format path").

The recorded PandaSet sequence of issue 32 (a car that stands, then pulls away: 0-0.4 m per frame)
is not available on the development machine, so this makes its twin with the generator's exact
geometry: a varied street (``--street``, a seed no training, validation or test street uses) whose
ego stands still for ``--stand`` seconds and then accelerates at ``--accel`` m/s^2, six cameras at
``--height x --width``, LiDAR, ``--frames`` frames at 10 Hz, written with
:func:`clsplat.data.write_pandaset`. The model's data module splits it like any recorded sequence
(first 70 % train, next 10 % validation, last 20 % test), so the held-out frames are the moving
ones, scored against the projected LiDAR. PandaSet's cuboids hold a yaw only, as an annotator
records them: the vehicles' boxes, tilted with the street's gradient and crossfall, are written
with their heading's yaw (DrivingForward does not read boxes).

    .venv/bin/python bench/experiments/df_pullaway_sequence.py --out bench/out/df_pullaway/001
    clsplat train drivingforward --data pandaset:bench/out/df_pullaway/001 --preset small \\
        --eval-scenes 6 --out bench/out/df_pullaway/run
"""
from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path


def _yaw_only(quat):
    """wxyz quaternion of the yaw of the box's x axis (its heading), roll and pitch dropped."""
    import math

    import numpy as np

    from clsplat.data.scene import quat_to_rotmat
    x = quat_to_rotmat(np.asarray(quat, np.float64))[:, 0]
    yaw = math.atan2(x[1], x[0])
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="bench/out/df_pullaway/001", help="PandaSet-format folder to write")
    p.add_argument("--street", type=int, default=3_000_000, help="seed of the street (outside every split)")
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--stand", type=float, default=2.0, help="seconds the ego stands before it pulls away")
    p.add_argument("--accel", type=float, default=2.0, help="m/s^2 once it pulls away")
    p.add_argument("--height", type=int, default=176)
    p.add_argument("--width", type=int, default=320)
    a = p.parse_args(argv)

    from clsplat.data import write_pandaset
    from clsplat.data.synthetic import SyntheticConfig, draw_world, generate_sequence

    world = dataclasses.replace(draw_world(a.street, "varied"), speed_kind="pulling_away", v0=0.0,
                                accel=a.accel, t_accel=a.stand)
    cfg = SyntheticConfig(seed=a.street, world="varied", num_frames=a.frames, dt=0.1, height=a.height,
                          width=a.width, lidar=True)
    seq = generate_sequence(cfg, world_params=world)
    for f in seq.frames:                   # PandaSet cuboids: the yaw of each box's heading, no tilt
        f.boxes = [dataclasses.replace(b, quat=_yaw_only(b.quat)) for b in f.boxes]
    write_pandaset(seq, a.out)
    speeds = [round(world.ego_speed(f.timestamp), 3) for f in seq.frames]
    (Path(a.out) / "ego_speed.json").write_text(json.dumps(speeds))
    print(f"wrote {a.out}: {a.frames} frames, ego speed {speeds[0]} .. {speeds[-1]} m/s "
          f"(standing until t = {a.stand} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
