"""Does DrivingForward's depth objective favour the true depth over a ramp? (issue 32, depth half)

For training streets ``--first .. --first + --count - 1`` of the varied world, with the data's ego
motion given (as ``--pose dataset`` trains), the depth-dependent loss terms of one sample are
evaluated at candidate depth maps instead of the network's:

* ``gt``: the true depth (sky at the mapping's far limit), and ``gt x s`` for ``--scales``;
* ``gt-blur``: the true disparity box-blurred over ``--blur`` pixels (the same scale, no edges);
* ``layout``: the image-blind layout control (per-pixel median true depth of ``--layout`` training
  streets), the map a depth network that ignores the image converges to;
* ``prior``: the ground prior (the untrained ``small`` network's depth, ``ground_prior_cap``).

Columns: AbsRel of the candidate against the truth; the reprojection (auto-masked minimum), the
spatial term, the second- and first-order edge-aware smoothness; and the preset's weighted sum of
the three (``reproj + w_spatial spatial + w_smooth smooth``). If the ramp (``layout``, ``gt-blur``)
scores below ``gt`` in the weighted sum, the objective itself prefers the ramp, whatever the
network; if only the smoothness term makes it so, its weight is what pins the depth.

    .venv/bin/python bench/experiments/df_depth_objective_probe.py --data synthetic-cache:/work/cache/df --count 8
"""
from __future__ import annotations

import argparse
import dataclasses


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default="synthetic", help="--data spec (default: the varied world)")
    p.add_argument("--preset", default="small")
    p.add_argument("--first", type=int, default=40, help="first training street (40+: not behind the layout)")
    p.add_argument("--count", type=int, default=8)
    p.add_argument("--layout", type=int, default=32, help="training streets behind the layout control")
    p.add_argument("--blur", type=int, default=9, help="box size (pixels) of gt-blur")
    p.add_argument("--scales", type=float, nargs="+", default=[0.8, 1.25])
    p.add_argument("--ramp-scales", type=float, nargs="*", default=[],
                   help="also the layout and the prior times each of these (which scale does a ramp prefer?)")
    p.add_argument("--cap", type=float, default=None, help="the prior's cap (default: the preset's ground_prior_cap)")
    p.add_argument("--automask", type=int, default=1, help="1: monodepth2's auto-mask (the preset's), 0: off")
    p.add_argument("--w-smooth", type=float, nargs="+", default=[1.0, 0.3, 0.1, 0.03, 0.01, 0.001],
                   help="smoothness weights to re-weigh the same terms with (last table)")
    a = p.parse_args(argv)

    import torch
    import torch.nn.functional as F

    from clsplat.models.common.data import parse_data
    from clsplat.models.common.presets import get_preset
    from clsplat.models.drivingforward.cli import DEFAULT_WORLD
    from clsplat.models.drivingforward.data import gt_ego_motion, load_triplet
    from clsplat.models.drivingforward.depth import ground_prior_depth
    from clsplat.models.drivingforward.evaluation import layout_depth
    from clsplat.models.drivingforward.losses import smoothness_loss
    from clsplat.models.drivingforward.model import DrivingForward

    torch.manual_seed(0)
    preset = dataclasses.replace(get_preset("drivingforward", a.preset), pose_source="dataset")
    model = DrivingForward(preset)
    src = parse_data(a.data, default_world=DEFAULT_WORLD)
    lay = layout_depth(src, preset, a.layout)[:, None]                       # [V, 1, H, W]
    sums: dict[str, list[float]] = {}
    with torch.no_grad():
        for i in range(a.first, a.first + a.count):
            smp = load_triplet(src, i, preset, "train")
            Ks, E = smp["Ks"], smp["cam_to_ego"]
            M = gt_ego_motion(smp)
            Mg = [M[0].float(), M[2].float()]
            Tc = [torch.linalg.inv(E) @ m @ E for m in Mg]
            fx = Ks[:, 0, 0].view(-1, 1, 1, 1)
            lo, hi = preset.min_depth * fx / preset.focal_ref, preset.max_depth * fx / preset.focal_ref
            gt = torch.nan_to_num(smp["depths"][1][:, None].float(), nan=float("inf"), posinf=float("inf"))
            gt = torch.minimum(torch.maximum(gt, lo), hi)
            disp = F.avg_pool2d(F.pad(1.0 / gt, [a.blur // 2] * 4, mode="replicate"), a.blur, 1)
            cands = {"gt": gt, **{f"gt x{s:g}": gt * s for s in a.scales}, "gt-blur": 1.0 / disp,
                     "layout": torch.minimum(torch.maximum(lay, lo), hi),
                     "prior": ground_prior_depth(Ks, E, preset.height, preset.width, a.cap or preset.ground_prior_cap)}
            for r in a.ramp_scales:
                cands[f"layout x{r:g}"] = cands["layout"] * r
                cands[f"prior x{r:g}"] = cands["prior"] * r
            tgt, srcs = smp["images"][1], [smp["images"][0], smp["images"][2]]
            noise = torch.zeros(E.shape[0], 2, preset.height, preset.width)
            valid = torch.isfinite(smp["depths"][1][:, None]) & (smp["depths"][1][:, None] < preset.max_depth)
            for name, d in cands.items():
                t = model.photometric_terms(tgt, srcs, d, d, Ks, E, Tc, Mg, noise, bool(a.automask))
                s2 = float(smoothness_loss(d, tgt, 2))
                s1 = float(smoothness_loss(d, tgt, 1))
                sp = float(t.get("spatial", 0.0))
                sm = s2 if preset.smooth_order == 2 else s1
                tot = float(t["reproj"]) + preset.w_spatial * sp + preset.w_smooth * sm
                absrel = float(((d - gt).abs() / gt)[valid].mean())
                sums.setdefault(name, []).append([absrel, float(t["reproj"]), sp, s2, s1, tot])
            move = float((smp["ego_to_world"][2, :3, 3] - smp["ego_to_world"][1, :3, 3]).norm())
            print(f"street {i} moves {move:.2f} m: " + "  ".join(
                f"{k} {v[-1][5]:.4f}" for k, v in sums.items()), flush=True)
    print(f"\nmean over {a.count} streets (weights: w_spatial {preset.w_spatial}, w_smooth {preset.w_smooth}, "
          f"smooth_order {preset.smooth_order}; automask {bool(a.automask)})")
    print(f"{'depth':10s} {'AbsRel':>7s} {'reproj':>8s} {'spatial':>8s} {'smooth2':>8s} {'smooth1':>8s} {'weighted':>9s}")
    for k, rows in sums.items():
        m = torch.tensor(rows).mean(0).tolist()
        print(f"{k:10s} {m[0]:7.3f} {m[1]:8.4f} {m[2]:8.4f} {m[3]:8.4f} {m[4]:8.4f} {m[5]:9.4f}")
    # the same terms re-weighed: reproj + w_spatial spatial + w smooth (the preset's order)
    col = 3 if preset.smooth_order == 2 else 4
    print(f"\nweighted sum against w_smooth (order {preset.smooth_order}); lowest marked *")
    print(f"{'w_smooth':>9s} " + " ".join(f"{k:>9s}" for k in sums))
    for w in a.w_smooth:
        vals = [(lambda m: m[1] + preset.w_spatial * m[2] + w * m[col])(torch.tensor(r).mean(0).tolist())
                for r in sums.values()]
        best = min(range(len(vals)), key=vals.__getitem__)
        print(f"{w:9g} " + " ".join(f"{v:8.4f}{'*' if j == best else ' '}" for j, v in enumerate(vals)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
