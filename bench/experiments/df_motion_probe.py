"""Does DrivingForward's photometric objective favour the true motion? (issue 32)

For training streets ``--first .. --first + --count - 1`` of the varied world, the loss of one
sample is evaluated with the data's ego motion scaled by ``s`` (rotation angle and translation
both times ``s``) in place of the pose network, for an untrained ``small`` model (its depth is the
ground prior). A minimum at ``s = 1`` means the objective points at the true motion even before
the depth has learned anything, so a pose network that stays at zero motion fails in its
optimisation, not in its objective. Columns: reprojection / render / total loss.

    .venv/bin/python bench/experiments/df_motion_probe.py --data synthetic --first 20 --count 4
"""
from __future__ import annotations

import argparse
import dataclasses


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default="synthetic", help="--data spec (default: the varied world)")
    p.add_argument("--preset", default="small")
    p.add_argument("--first", type=int, default=20)
    p.add_argument("--count", type=int, default=4)
    p.add_argument("--scales", type=float, nargs="+", default=[0.0, 0.25, 0.5, 1.0, 1.5, 2.0])
    a = p.parse_args(argv)

    import torch

    from clsplat.models.common.data import parse_data
    from clsplat.models.common.geometry import matrix_to_axis_angle, se3_exp
    from clsplat.models.common.presets import get_preset
    from clsplat.models.drivingforward.cli import DEFAULT_WORLD
    from clsplat.models.drivingforward.data import gt_ego_motion, load_triplet
    from clsplat.models.drivingforward.model import DrivingForward

    torch.manual_seed(0)
    preset = dataclasses.replace(get_preset("drivingforward", a.preset), pose_source="dataset")
    model = DrivingForward(preset)
    src = parse_data(a.data, default_world=DEFAULT_WORLD)

    def scaled(M, s):
        aa = matrix_to_axis_angle(M[:3, :3].double())
        return se3_exp(aa * s, M[:3, 3].double() * s).float()

    with torch.no_grad():
        for i in range(a.first, a.first + a.count):
            smp = load_triplet(src, i, preset, "train")
            M = gt_ego_motion(smp)
            noise = torch.zeros(smp["Ks"].shape[0], 2, preset.height, preset.width)
            cells = []
            for s in a.scales:
                t = model.training_losses(smp["images"], smp["images"], smp["Ks"], smp["cam_to_ego"], noise, None,
                                          None, [scaled(M[0], s), scaled(M[2], s)])
                cells.append(f"x{s:g}: {float(t['reproj']):.4f}/{float(t['render']):.4f}/{float(t['loss']):.4f}")
            move = float((smp["ego_to_world"][2, :3, 3] - smp["ego_to_world"][1, :3, 3]).norm())
            print(f"street {i} moves {move:.2f} m:  " + "  ".join(cells), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
