"""Can DrivingForward's depth network fit one street's structure at all? (issue 32, depth half)

A capacity-and-optimiser check, not a result: the networks (seeded, random initialisation) train on
ONE training window (``--index``) for ``--steps`` steps with the data's ego motion given (as
``--pose dataset`` trains: the same loss, optimiser, warm-up and jitter as ``clsplat train``), and
every ``--every`` steps the depth of that same window is scored against its true depth: AbsRel,
δ<1.25, scale ratio, and AbsRel / δ1 after per-image median scaling (the map's shape alone). If
even the training window stays a ramp, the block is the network or its optimiser (capacity,
learning rate, the decoder's path from the 1/8 fused feature), not generalisation; if it fits the
window, the block is what 300 windows teach.

    .venv/bin/python bench/experiments/df_depth_overfit.py --data synthetic-cache:/work/cache/df \\
        --steps 150 --set w_smooth=0.01 [--set depth_skips=True] [--set lr=1e-3]
"""
from __future__ import annotations

import argparse
import dataclasses


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default="synthetic")
    p.add_argument("--preset", default="small")
    p.add_argument("--set", action="append", default=None, metavar="FIELD=VALUE")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--index", type=int, default=41, help="the training window fitted (41: a moving street)")
    p.add_argument("--steps", type=int, default=150)
    p.add_argument("--every", type=int, default=25)
    a = p.parse_args(argv)
    if a.steps < 1 or a.every < 1:
        raise SystemExit("df_depth_overfit: --steps and --every must be >= 1")

    import torch

    from clsplat.models.common.data import parse_data
    from clsplat.models.common.presets import apply_sets, get_preset
    from clsplat.models.common.train import sample_generator
    from clsplat.models.drivingforward.data import colour_jitter, gt_ego_motion, load_triplet
    from clsplat.models.drivingforward.model import DrivingForward
    from clsplat.models.drivingforward.training import make_optimizer, make_scheduler

    import df_depth_structure as st     # bench/experiments: the same scoring

    torch.set_num_threads(1)            # as --threads 1: PoCL renders on the other core
    preset = apply_sets(get_preset("drivingforward", a.preset), a.set, pose_source="dataset")
    torch.manual_seed(a.seed)
    model = DrivingForward(preset)
    src = parse_data(a.data, seed=a.seed, default_world="varied")
    s = load_triplet(src, a.index, preset, "train")
    M = gt_ego_motion(s)
    gt = s["depths"][1]
    opt = make_optimizer(model, preset)
    sched = make_scheduler(opt, preset)
    changed = {f.name: getattr(preset, f.name) for f in dataclasses.fields(preset)
               if getattr(preset, f.name) != getattr(get_preset("drivingforward", a.preset), f.name)}
    move = float((s["ego_to_world"][2, :3, 3] - s["ego_to_world"][1, :3, 3]).norm())
    print(f"window {a.index} (moves {move:.2f} m), seed {a.seed}, changes {changed}")

    def score(step: int, rec: dict) -> None:
        model.eval()
        with torch.no_grad():
            d = model.depth_net(s["images"][1], s["Ks"], s["cam_to_ego"])["depth"][:, 0]
        model.train()
        v = st._scores(d, gt, preset.max_depth)
        extra = " ".join(f"{k} {rec[k]:.4f}" for k in ("reproj", "spatial", "smooth") if k in rec)
        print(f"step {step:4d}: AbsRel {v[0]:.3f} δ1 {v[1]:.3f} scale {v[2]:.3f} | median-scaled AbsRel {v[3]:.3f} "
              f"δ1 {v[4]:.3f} | {extra}", flush=True)

    score(0, {})
    for step in range(a.steps):
        g = sample_generator(a.seed, step)
        net = colour_jitter(s["images"], g, preset.jitter)
        noise = torch.randn(s["Ks"].shape[0], 2, preset.height, preset.width, generator=g) * preset.automask_noise
        terms = model.training_losses(s["images"], net, s["Ks"], s["cam_to_ego"], noise, None, step, [M[0], M[2]])
        opt.zero_grad(set_to_none=True)
        terms["loss"].backward()
        opt.step()
        if sched is not None:
            sched.step()
        if (step + 1) % a.every == 0:
            score(step + 1, {k: float(v.detach()) for k, v in terms.items() if v.numel() == 1})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
