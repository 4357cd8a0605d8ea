"""Which way does a trained DrivingForward pose network point? (issue 32: on validation seed 1 the
anchored flow head's error is about |pred| + |true|, i.e. it points away from the motion)

For held-out windows, the pose network's camera-0 translation t -> t+1 (camera frame, metres) is
printed beside the data's, with their cosine and the norm ratio; a mean cosine near -1 says the
network learned the motion reversed, near 0 sideways, near +1 the right way.

    .venv/bin/python bench/experiments/df_pose_direction.py --checkpoint RUN/checkpoint.pt \\
        --data synthetic-cache:/work/cache/df --seed S --split val --count 8
"""
from __future__ import annotations

import argparse


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--data", default="synthetic")
    p.add_argument("--seed", type=int, default=0, help="the run's --seed (it picks the held-out streets)")
    p.add_argument("--split", choices=("train", "val", "test"), default="val")
    p.add_argument("--count", type=int, default=8, help="windows from 0")
    a = p.parse_args(argv)
    if a.count < 1:
        raise SystemExit("df_pose_direction: --count must be >= 1")

    import torch

    from clsplat.models.common.data import parse_data
    from clsplat.models.drivingforward.cli import load_model
    from clsplat.models.drivingforward.data import load_triplet
    from clsplat.models.drivingforward.evaluation import camera0_motion

    model, preset = load_model(a.checkpoint)
    model.eval()
    src = parse_data(a.data, seed=a.seed, default_world="varied")
    cos_all = []
    with torch.no_grad():
        for i in range(a.count):
            s = load_triplet(src, i, preset, split=a.split)
            T = model.pose_net(s["images"][1], s["images"][2], s["Ks"], s["cam_to_ego"])
            g = camera0_motion(s).to(T.dtype)
            tp, tg = T.reshape(-1, 4, 4)[0, :3, 3], g.reshape(-1, 4, 4)[0, :3, 3]
            n_p, n_g = float(tp.norm()), float(tg.norm())
            cos = float(tp @ tg / (n_p * n_g)) if n_p > 1e-6 and n_g > 1e-6 else float("nan")
            if n_g > 0.05:
                cos_all.append(cos)
            print(f"window {i}: pred ({tp[0]:+.3f}, {tp[1]:+.3f}, {tp[2]:+.3f}) m, true ({tg[0]:+.3f}, {tg[1]:+.3f}, "
                  f"{tg[2]:+.3f}) m, cos {cos:+.2f}, |pred|/|true| {n_p / max(n_g, 1e-9):.2f}")
    if cos_all:
        print(f"moving windows: {len(cos_all)}, mean cos {sum(cos_all) / len(cos_all):+.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
