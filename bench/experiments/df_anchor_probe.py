"""Does the road anchor's photometric term have a minimum at the reversed motion? (issue 32: on
seed 1 the flow head trained with ``pose_road_anchor`` points backwards, cos -0.8 with the truth)

For training windows ``--first .. --first + --count - 1`` (at ``--seed``), the pose network's term
under ``pose_road_anchor`` (the temporal reprojection on the road pixels, warped with the ground
prior's depth; ``temporal_loss`` as the model computes it) is evaluated with the data's ego motion
scaled by ``s`` (rotation and translation; negative ``s``: the motion reversed) in place of the
pose network. No network is involved: the depth is the rig's ground prior. A second minimum at
``s`` near -1 would let a head that starts backwards stay there.

    .venv/bin/python bench/experiments/df_anchor_probe.py --data synthetic-cache:/work/cache/df --seed 1 --count 8
    (add --no-automask for the term without the unwarped frames in its minimum)
"""
from __future__ import annotations

import argparse


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default="synthetic")
    p.add_argument("--preset", default="small")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--first", type=int, default=0)
    p.add_argument("--count", type=int, default=8)
    p.add_argument("--scales", type=float, nargs="+", default=[-1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5])
    p.add_argument("--no-automask", action="store_true",
                   help="the minimum over the warped frames only (the model's automask_steps=0)")
    a = p.parse_args(argv)

    import torch

    from clsplat.models.common.data import parse_data
    from clsplat.models.common.geometry import matrix_to_axis_angle, se3_exp
    from clsplat.models.common.presets import get_preset
    from clsplat.models.drivingforward.data import gt_ego_motion, load_triplet
    from clsplat.models.drivingforward.losses import temporal_loss
    from clsplat.models.drivingforward.model import ground_prior_depth

    preset = get_preset("drivingforward", a.preset)
    src = parse_data(a.data, seed=a.seed, default_world="varied")

    def scaled(M, s):
        aa = matrix_to_axis_angle(M[:3, :3].double())
        return se3_exp(aa * s, M[:3, 3].double() * s).float()

    print("window, motion (m): anchored term at s = " + " ".join(f"{s:+g}" for s in a.scales))
    with torch.no_grad():
        for i in range(a.first, a.first + a.count):
            smp = load_triplet(src, i, preset, "train")
            Ks, E = smp["Ks"], smp["cam_to_ego"]
            M = gt_ego_motion(smp)
            prior = ground_prior_depth(Ks, E, preset.height, preset.width, preset.ground_prior_cap)
            road = (prior < preset.ground_prior_cap).to(prior.dtype)
            noise = torch.zeros(Ks.shape[0], 2, preset.height, preset.width)
            tgt, srcs = smp["images"][1], [smp["images"][0], smp["images"][2]]
            vals = []
            for s in a.scales:
                Tc = [torch.linalg.inv(E) @ scaled(m, s) @ E for m in (M[0], M[2])]
                vals.append(float(temporal_loss(tgt, srcs, prior, Ks, Tc, noise, not a.no_automask,
                                                 preset.automask_margin, road)))
            move = float((smp["ego_to_world"][2, :3, 3] - smp["ego_to_world"][1, :3, 3]).norm())
            best = a.scales[min(range(len(vals)), key=vals.__getitem__)]
            print(f"window {i}, {move:.2f}: " + " ".join(f"{v:.4f}" for v in vals) + f"   (min at s = {best:+g})", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
