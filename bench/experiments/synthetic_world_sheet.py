"""Contact sheet of the varied synthetic world (issue 32 item 1), and its generation cost.

Makes ``bench/figures/synthetic_world_sheet.png``: 12 varied streets (seeds 9000-9011, a range
that no train / validation / test split uses), each as its CAM_FRONT image at t = 0 (176 x 320)
beside a bird's-eye panel (the street's ground semantics in street-aligned world coordinates
around the ego, buildings, vehicles, the ego's path over 0-3 s with its position at t = 0),
captioned with the street's drawn parameters: speed kind and speed at t = 0, curvature radius,
lane change, gradient, vertical curvature, crossfall, road half-width, vehicle counts, sun.

    .venv/bin/python bench/experiments/synthetic_world_sheet.py
    .venv/bin/python bench/experiments/synthetic_world_sheet.py --timing   # classic against varied

``--timing`` prints the CPU time (the process's, robust to a loaded machine; wall time beside it)
of ``generate_sequence`` (median of seeds 0-2) for the classic and
the varied world at 6 cameras x 3 frames, 64 x 112, no LiDAR (DrivingForward's samples) and
6 cameras x 10 frames, 176 x 320 with LiDAR (the default street), one process, one thread.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402

from clsplat.data.synthetic import generate_sequence  # noqa: E402
from clsplat.data.synthetic.textures import _ground_albedo  # noqa: E402

SEEDS = range(9000, 9012)
OUT = Path(__file__).resolve().parents[1] / "figures" / "synthetic_world_sheet.png"


def caption(w, seq) -> str:
    v = w.ego_speed(0.0)
    kind = w.speed_kind.replace("_", " ")
    curve = "straight" if w.curvature == 0 else f"R {1 / abs(w.curvature):.0f} m {'left' if w.curvature > 0 else 'right'}"
    lc = "no lane change" if not w.lane_change else \
        f"lane change {'L' if w.lane_to > w.lane_from else 'R'} at s {w.lc_s_start:+.0f} m"
    n_mov = sum(1 for v_ in seq.metadata["scene"].vehicles if v_.speed > 0)
    return (f"seed {w.seed}: {kind}, {v:.1f} m/s at t=0, {w.ego_speed(0.2):.1f} at 0.2\n"
            f"{curve}, {lc}\n"
            f"grade {100 * w.grade:+.1f} %, vcurv {1e4 * w.vcurv:+.1f}e-4/m, crossfall {100 * w.crossfall:+.1f} %\n"
            f"road half {w.road_half:.1f} m, parked {w.num_parked}, moving {n_mov}/{w.num_moving}, "
            f"sun {w.sun_azimuth_deg:.0f}/{w.sun_elevation_deg:.0f} deg")


def bev(ax, w, seq) -> None:
    """Bird's-eye panel: ground classes on a grid around the ego, boxes and the ego's path."""
    E0 = seq.frames[0].ego_to_world
    cx, cy = E0[0, 3], E0[1, 3]
    half = 45.0
    xs = np.linspace(cx - half, cx + half, 181)
    ys = np.linspace(cy - half, cy + half, 181)
    X, Y = np.meshgrid(xs, ys)
    s, l = w.to_street(X.ravel(), Y.ravel(), seq.metadata["scene"].s_mid)
    alb, _ = _ground_albedo(s, l, w.seed, 0.0, w.road_half, w.lane_width, w.sidewalk_out)
    ax.imshow(alb.reshape(X.shape + (3,)), origin="lower", extent=(xs[0], xs[-1], ys[0], ys[-1]))
    scene = seq.metadata["scene"]
    for b in scene.static:
        if b.kind not in ("facade", "canopy"):
            continue
        c = (np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]]) * b.half[:2]) @ b.T[:2, :2].T + b.T[:2, 3]
        ax.fill(c[:, 0], c[:, 1], color=b.color if b.kind == "facade" else (0.2, 0.45, 0.15), alpha=0.8, lw=0)
    for box in seq.frames[0].boxes:
        from clsplat.data.scene import quat_to_rotmat
        R = quat_to_rotmat(box.quat)
        c = (np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]]) * box.size[:2] / 2) @ R[:2, :2].T + box.center[:2]
        ax.plot(c[:, 0], c[:, 1], color="red" if box.track_id in scene.moving_ids else "black", lw=0.8)
    path = np.array([w.ego_pose(t)[:3, 3] for t in np.linspace(-1.0, 3.0, 41)])
    ax.plot(path[:, 0], path[:, 1], color="cyan", lw=1.0)
    ax.plot([cx], [cy], marker="o", color="cyan", ms=3)
    fwd = E0[:2, 0]
    ax.arrow(cx, cy, 6 * fwd[0], 6 * fwd[1], color="cyan", width=0.6, length_includes_head=True)
    ax.set_xlim(xs[0], xs[-1])
    ax.set_ylim(ys[0], ys[-1])
    ax.set_xticks([])
    ax.set_yticks([])


def sheet(out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(6, 4, figsize=(16, 17.5), gridspec_kw={"width_ratios": [1.82, 1, 1.82, 1]})
    for i, seed in enumerate(SEEDS):
        t0 = time.perf_counter()
        seq = generate_sequence(height=176, width=320, num_frames=1, seed=seed, world="varied", lidar=False,
                                cameras=("CAM_FRONT",))
        w = seq.metadata["world"]
        print(f"seed {seed}: {time.perf_counter() - t0:.1f} s", flush=True)
        r, c = divmod(i, 2)
        ax = axes[r, 2 * c]
        ax.imshow(seq.frames[0].images["CAM_FRONT"])
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(caption(w, seq), fontsize=7.5, loc="left")
        bev(axes[r, 2 * c + 1], w, seq)
    fig.suptitle("Varied synthetic world (SyntheticConfig(world='varied')): CAM_FRONT at t = 0 and a 90 m "
                 "bird's-eye panel (ego path over -1..3 s in cyan, moving vehicles red)", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.985))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=72)
    print(f"wrote {out}")


def timing() -> None:
    cases = [("6 cams x 3 frames, 64x112, no LiDAR", dict(height=64, width=112, num_frames=3, lidar=False)),
             ("6 cams x 10 frames, 176x320, LiDAR", dict(height=176, width=320, num_frames=10, lidar=True))]
    for name, kw in cases:
        for world in ("classic", "varied"):
            times, cpu = [], []
            for seed in (0, 1, 2):
                t0, c0 = time.perf_counter(), time.process_time()
                generate_sequence(seed=seed, world=world, **kw)
                times.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
            print(f"{name}, {world}: median CPU {np.median(cpu):.2f} s (seeds 0-2: "
                  f"{', '.join(f'{t:.2f}' for t in cpu)}), wall {np.median(times):.2f} s", flush=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--timing", action="store_true", help="time classic against varied generation instead")
    p.add_argument("--out", default=str(OUT), help="figure path (default: %(default)s)")
    a = p.parse_args()
    if a.timing:
        timing()
    else:
        sheet(Path(a.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
