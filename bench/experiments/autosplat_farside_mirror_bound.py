"""What a perfect mirror prior would score on the side-on far-side views (issue 33), from the
generator alone (no model): for every side-on view of a street (``viewsets._far_side_views``,
``far_side_view='side-on'``), the generator's near side filmed from the camera mirrored across the
vehicle's box and flipped left-right, against the generator's far side; PSNR pooled over the pixels
where both show the vehicle, lit (what the cameras film) and as unlit albedo ("identical" when equal).

    .venv/bin/python bench/experiments/autosplat_farside_mirror_bound.py --world divided --seed 0 1 2 3 4 5
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from types import SimpleNamespace

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402

RIG = ["CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT"]


def mirror_bound(world: str, seed: int, scale: float) -> dict[str, float]:
    """``{"lit": PSNR, "unlit": PSNR}`` (dB; inf when identical) of the near side mirrored onto the far side."""
    from clsplat.data.synthetic import SyntheticConfig, generate_sequence
    from clsplat.data.synthetic.views import mirror_across_box
    from clsplat.models.autosplat import viewsets as vs
    from clsplat.models.autosplat.data import SYNTHETIC_DT, DYNAMIC_THRESHOLD_M
    H, W = max(8, round(176 * scale)), max(8, round(320 * scale))
    seq = generate_sequence(SyntheticConfig(height=H, width=W, num_frames=16, seed=seed, dt=SYNTHETIC_DT, world=world,
                                            lidar=False))
    sc = seq.metadata["scene"]
    run = SimpleNamespace(data=SimpleNamespace(seq=seq, cameras=RIG, height=H, width=W, train_frames=[]),
                          preset=SimpleNamespace(dynamic_threshold=DYNAMIC_THRESHOLD_M))
    acc = {"lit": [0.0, 0], "unlit": [0.0, 0]}
    for f, t, c2w, idx in vs._far_side_views(run, "side-on"):
        K = seq.camera(RIG[idx[0]]).K
        ts = seq.frames[f].timestamp
        near_c2w = mirror_across_box(c2w[0], vs._exact_box(seq, f, t).box_to_world)
        for key, lit in (("lit", True), ("unlit", False)):
            far = sc.render(K, c2w[0], W, H, ts, lighting=lit)
            near = sc.render(K, near_c2w, W, H, ts, lighting=lit)
            m = (far.instance == t) & (near.instance[:, ::-1] == t)
            if m.sum() < vs.MIN_OBJECT_PIXELS:
                continue
            acc[key][0] += float(((far.rgb - near.rgb[:, ::-1]) ** 2)[m].sum())
            acc[key][1] += 3 * int(m.sum())
    return {k: (float("inf") if e == 0 else float(-10 * np.log10(e / n))) for k, (e, n) in acc.items() if n}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--world", default="divided", choices=("straight", "divided"))
    p.add_argument("--seed", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--scale", type=float, default=0.5, help="image scale of the 176 x 320 rig (default 0.5, demo's)")
    a = p.parse_args(argv)
    for seed in a.seed:
        r = mirror_bound(a.world, seed, a.scale)
        fmt = lambda v: "identical" if v == float("inf") else f"{v:.2f} dB"  # noqa: E731
        print(f"{a.world} {seed}: near side mirrored onto the far side, vehicle pixels: lit {fmt(r.get('lit'))}, "
              f"unlit albedo {fmt(r.get('unlit'))}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
