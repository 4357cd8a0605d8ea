"""PGT speed: seconds per training step and per prediction, for each preset (and matcher).

A step is one sample of the base stage: synthetic street generation excluded (timed apart as
"data"), forward, rendering the target and source views through clsplat, loss, backward and the
AdamW update. A prediction is the network's forward pass for the V source views (no rendering).
Medians over ``--repeats`` after one warm-up. Run: ``python bench/experiments/pgt_speed.py --out DIR``.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch


def measure(preset, repeats: int) -> dict:
    from clsplat.models.common.data import parse_data
    from clsplat.models.pgt.data import make_sample
    from clsplat.models.pgt.model import PGT, count_parameters
    from clsplat.models.pgt.training import make_optimizer, make_sample_loss
    torch.manual_seed(0)
    model = PGT(preset)
    source = parse_data("synthetic")
    opt, _ = make_optimizer(model, preset, 100, "base")
    loss_fn = make_sample_loss(source, preset, "base", 0)
    data_t, step_t, pred_t = [], [], []
    for i in range(repeats + 1):
        t0 = time.perf_counter()
        s = make_sample(source, preset, i, "train", torch.Generator().manual_seed(i))
        t1 = time.perf_counter()
        with torch.no_grad():
            model(s.images, s.Ks, s.cam_to_world)
        t2 = time.perf_counter()
        opt.zero_grad()
        loss_fn(model, 0, i)["loss"].backward()
        opt.step()
        t3 = time.perf_counter()
        if i:  # the first is a warm-up (kernel builds)
            data_t.append(t1 - t0)
            pred_t.append(t2 - t1)
            step_t.append(t3 - t2 - (t1 - t0))  # the loss function generates its own sample
    return {"preset": preset.name, "matching": preset.matching, "height": preset.height, "width": preset.width,
            "parameters": count_parameters(model), "data_s": statistics.median(data_t),
            "prediction_s": statistics.median(pred_t), "step_s": statistics.median(step_t), "repeats": repeats}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out", required=True)
    p.add_argument("--presets", default="tiny,small,paper")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--both-matchers", action="store_true")
    args = p.parse_args()
    from clsplat.models.common.presets import get_preset
    from clsplat.models.common.train import set_threads
    set_threads(1)
    rows = []
    for name in args.presets.split(","):
        base = get_preset("pgt", name)
        variants = [base]
        if args.both_matchers:
            other = "epipolar_attention" if base.matching == "plane_sweep" else "plane_sweep"
            variants.append(base.replace(matching=other))
        for pr in variants:
            r = measure(pr, args.repeats)
            print(json.dumps(r), flush=True)
            rows.append(r)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "pgt_speed.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
