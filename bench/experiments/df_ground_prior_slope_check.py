"""Does the flat-ground prior hold on the varied world's sloped and cambered streets? (issue 32)

For each validation window, :func:`ground_prior_depth` (camera height and extrinsics, the ego
frame's z = 0 taken as the road) is compared with the generator's true depth on pixels it labels
road within ``--range`` metres: ``|prior - true| / true``, its median and 90th percentile per
window, summarised over flat and sloped streets (``draw_world(...).flat``). Ground truth on both
sides: a diagnostic of the prior, never an input to anything.

    .venv/bin/python bench/experiments/df_ground_prior_slope_check.py --data synthetic-cache:/work/cache/df --val 40
"""
from __future__ import annotations

import argparse


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default="synthetic", help="--data spec of synthetic streets (default: the varied world)")
    p.add_argument("--preset", default="small")
    p.add_argument("--val", type=int, default=40, help="validation windows")
    p.add_argument("--range", type=float, default=20.0, help="metres: road pixels nearer than this count")
    a = p.parse_args(argv)
    if a.val < 1 or not a.range > 0:
        p.error(f"--val / --range: expected a positive count and distance, got {a.val} / {a.range}")

    import numpy as np
    import torch

    import clsplat.models.drivingforward  # noqa: F401  (registers the presets)
    from clsplat.data.synthetic import draw_world
    from clsplat.models.common.data import VAL_SEED_OFFSET, parse_data
    from clsplat.models.common.presets import get_preset
    from clsplat.models.drivingforward.data import load_triplet
    from clsplat.models.drivingforward.depth import ground_prior_depth

    preset = get_preset("drivingforward", a.preset)
    src = parse_data(a.data, default_world="varied")
    if not src.synthetic_streets:
        p.error("--data: synthetic streets only (the check reads the generator's world parameters)")
    rows = []
    for i in range(a.val):
        s = load_triplet(src, i, preset, "val")
        seq = src.sequence(i, num_frames=3, height=preset.height, width=preset.width, split="val",
                           dt=preset.scenes_dt, supersample=preset.supersample)
        sem = torch.from_numpy(np.stack([seq.frames[1].semantics[n] for n in seq.camera_names]).astype(np.int64))
        D = s["depths"][1].double()                                                     # [V, H, W]
        Zg = ground_prior_depth(s["Ks"].double(), s["cam_to_ego"].double(), preset.height, preset.width, 1e4)[:, 0]
        road = (sem == 0) & torch.isfinite(D) & (D < a.range)
        rel = ((Zg - D) / D)[road].abs()
        w = draw_world(src.seed + i + VAL_SEED_OFFSET, src.world)
        rows.append((w.flat, w.max_slope, float(rel.median()), float(rel.quantile(0.9))))
    for lab, sel in (("flat", [r for r in rows if r[0]]), ("sloped", [r for r in rows if not r[0]])):
        if not sel:
            print(f"{lab}: no windows")
            continue
        m = np.array([r[2:] for r in sel])
        print(f"{lab}: {len(sel)} windows, max slope {max(r[1] for r in sel):.3f}; |prior - true| / true on road "
              f"< {a.range:g} m: median of window medians {100 * np.median(m[:, 0]):.2f} %, worst window median "
              f"{100 * m[:, 0].max():.2f} %, worst window p90 {100 * m[:, 1].max():.2f} %")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
