"""Which cross-view matcher PGT uses: plane-sweep cost volume vs epipolar attention, measured.

Both matchers sample the other views at the same D depth hypotheses along each pixel's ray; they
differ in what they learn from the samples. Each is trained from the same seed for ``--steps``
base-stage steps of the ``--preset`` (depth-supervised synthetic streets), then evaluated on
held-out streets: depth AbsRel of the coarse matching depth (u0) and after the residual head,
PSNR/SSIM of the rendered target view, and seconds per step (median over the log).

Run: ``python bench/experiments/pgt_matching.py --preset small --steps 150 --out DIR`` (writes
DIR/pgt_matching.json and one run folder per matcher).
"""
from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out", required=True)
    p.add_argument("--preset", default="small")
    p.add_argument("--steps", type=int, default=150)
    p.add_argument("--num-scenes", type=int, default=4)
    args = p.parse_args()
    from clsplat.models.common import presets as registry
    from clsplat.models.common.data import parse_data
    from clsplat.models.common.train import TrainSpec, load_checkpoint, read_log, seed_everything, set_threads, train
    from clsplat.models.pgt.evaluate import evaluate_model
    from clsplat.models.pgt.model import PGT
    from clsplat.models.pgt.training import make_optimizer, make_sample_loss
    set_threads(1)
    base = registry.get_preset("pgt", args.preset)
    rows = []
    for matching in ("plane_sweep", "epipolar_attention"):
        preset = base.replace(name=f"{base.name}-{matching}", matching=matching)
        registry.register("pgt", preset)
        run = Path(args.out) / matching
        seed_everything(0)
        model = PGT(preset)
        opt, sched = make_optimizer(model, preset, args.steps, "base")
        source = parse_data("synthetic")
        spec = TrainSpec(out_dir=run, steps=args.steps, seed=0, grad_clip=preset.grad_clip, progress=False,
                         checkpoint_every=max(args.steps, 1), resume=(run / "checkpoint.pt").is_file())
        train(model, opt, spec, preset, "pgt", make_sample_loss(source, preset, "base", 0), scheduler=sched)
        model.load_state_dict(load_checkpoint(run / "checkpoint.pt", "pgt", preset)["model"])
        res = evaluate_model(model, source, preset, [1.0], args.num_scenes, repeats=1)
        log = read_log(run / "log.jsonl")
        m = res["metrics"]
        row = {"matching": matching, "steps": args.steps, "step_s": statistics.median(r["time_s"] for r in log),
               "prediction_s": m["seconds_per_prediction"], "psnr": m["all"]["psnr"], "ssim": m["all"]["ssim"],
               "abs_rel_coarse": m["depth_without_residual"]["abs_rel"],
               "abs_rel_refined": m["all"]["abs_rel"],
               "delta1_coarse": m["depth_without_residual"]["delta1"],
               "final_depth_loss": statistics.mean(r["depth"] for r in log[-20:]),
               "parameters": sum(t.numel() for t in model.parameters())}
        print(json.dumps(row), flush=True)
        rows.append(row)
    Path(args.out, "pgt_matching.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
