"""Scale against structure: how much of a DrivingForward depth error is the global scale? (issue 32)

For each checkpoint, on the held-out windows 0 .. ``--count``-1 of ``--split`` (default the
validation streets of ``--seed``), the depth is scored as ``eval`` scores it (AbsRel, δ<1.25, scale
ratio median(gt)/median(pred), pixels pooled) and again after per-image median scaling (each
camera image multiplied by its own median(gt)/median(pred): what is left is the map's shape, the
"ramp or structure" question). Beside it, on the same pixels: the image-blind layout control
(per-pixel median true depth of ``--layout`` training windows) and the ground prior alone
(``ground_prior_cap`` of the checkpoint's preset), each scored the same two ways.

    .venv/bin/python bench/experiments/df_depth_structure.py RUN/checkpoint.pt [...] --seed 0 \\
        --data synthetic-cache:/work/cache/df
"""
from __future__ import annotations

import argparse


def _scores(pred, gt, max_depth: float) -> list[float]:
    """[AbsRel, δ1, scale, median-scaled AbsRel, median-scaled δ1] over ``[N, H, W]`` pooled pixels."""
    import torch
    valid = torch.isfinite(gt) & (gt > 1e-3) & (gt < max_depth)
    p, g = pred.double().clamp(1e-3, max_depth), gt.double()
    rows = []
    for scaled in (False, True):
        q = p.clone()
        if scaled:
            for k in range(q.shape[0]):
                v = valid[k]
                if v.any():
                    q[k] = q[k] * g[k][v].median() / q[k][v].median()
            q = q.clamp(1e-3, max_depth)
        r = (q - g).abs()[valid] / g[valid]
        ratio = torch.maximum(q / g, g / q)[valid]
        rows += [float(r.mean()), float((ratio < 1.25).double().mean())]
    scale = float(g[valid].median() / p[valid].median())
    return [rows[0], rows[1], scale, rows[2], rows[3]]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoint", nargs="+")
    p.add_argument("--data", default="synthetic")
    p.add_argument("--seed", type=int, default=0, help="the runs' --seed (it picks the held-out streets)")
    p.add_argument("--split", choices=("val", "test"), default="val")
    p.add_argument("--count", type=int, default=8)
    p.add_argument("--layout", type=int, default=32)
    p.add_argument("--caps", type=float, nargs="*", default=[],
                   help="also score the ground prior alone capped at each of these (metres)")
    a = p.parse_args(argv)
    if a.count < 1:
        raise SystemExit("df_depth_structure: --count must be >= 1")

    import torch

    from clsplat.models.common.data import parse_data
    from clsplat.models.drivingforward.cli import load_model
    from clsplat.models.drivingforward.data import load_triplet
    from clsplat.models.drivingforward.depth import ground_prior_depth
    from clsplat.models.drivingforward.evaluation import layout_depth

    src = parse_data(a.data, seed=a.seed, default_world="varied")
    print(f"| depth | AbsRel | δ1 | scale | AbsRel median-scaled | δ1 median-scaled |\n|---|---|---|---|---|---|")
    controls_done = False
    for ck in a.checkpoint:
        model, preset = load_model(ck)
        model.eval()
        preds, gts, priors = [], [], []
        with torch.no_grad():
            for i in range(a.count):
                s = load_triplet(src, i, preset, split=a.split)
                preds.append(model.depth_net(s["images"][1], s["Ks"], s["cam_to_ego"])["depth"][:, 0])
                gts.append(s["depths"][1])
                cap = preset.ground_prior_cap if preset.ground_prior_cap is not None else preset.max_depth
                priors.append({c: ground_prior_depth(s["Ks"], s["cam_to_ego"], preset.height, preset.width, c)[:, 0]
                               for c in [cap, *a.caps]})
        P, G = torch.cat(preds), torch.cat(gts)
        if not controls_done:
            lay = layout_depth(src, preset, a.layout)
            L = lay[None].expand(a.count, *lay.shape).reshape(G.shape)
            rows = [(f"layout ({a.layout} training windows)", L)]
            rows += [(f"ground prior alone, cap {c:g} m", torch.cat([q[c] for q in priors])) for c in priors[0]]
            for name, x in rows:
                v = _scores(x, G, preset.max_depth)
                print(f"| {name} | {v[0]:.3f} | {v[1]:.3f} | {v[2]:.3f} | {v[3]:.3f} | {v[4]:.3f} |")
            controls_done = True
        v = _scores(P, G, preset.max_depth)
        print(f"| {ck} | {v[0]:.3f} | {v[1]:.3f} | {v[2]:.3f} | {v[3]:.3f} | {v[4]:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
