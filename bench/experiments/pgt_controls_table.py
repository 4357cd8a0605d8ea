"""Tables of issue 33's EcoSplat controls from ``clsplat eval pgt`` folders (bench/notes/ecosplat_controls.md).

Reads ROOT/eval_{val,test}_s{0,1,2}/budget.json (and ROOT/eval_val_abl_*/ for the validation
choices) and prints PSNR per method and κ per seed, the paired per-street differences (learned
selection minus each row, from ``psnr_per_sample``) and the validation-choice rows.

    .venv/bin/python bench/experiments/pgt_controls_table.py /tmp/h33
"""
import json, sys, statistics
from pathlib import Path
B = Path(sys.argv[1] if len(sys.argv) > 1 else ".")
order = ["finetuned", "random@finetuned", "grid@finetuned", "opacity@finetuned", "dedup@finetuned",
         "random", "grid", "opacity", "dedup"]
for split in ("val", "test"):
    runs = {s: json.loads((B / f"eval_{split}_s{s}" / "budget.json").read_text())
            for s in (0, 1, 2) if (B / f"eval_{split}_s{s}" / "budget.json").is_file()}
    if not runs:
        continue
    kappas = sorted({r["budget"] for rows in runs.values() for r in rows}, reverse=True)
    print(f"\n{split}: seeds {sorted(runs)}")
    print("| method | " + " | ".join(f"κ {k:g}" for k in kappas) + " |")
    print("|---|" + "---|" * len(kappas))
    for m in order:
        cells = []
        for k in kappas:
            v = [next(r["psnr"] for r in rows if r["method"] == m and r["budget"] == k) for rows in runs.values()
                 if any(r["method"] == m and r["budget"] == k for r in rows)]
            cells.append(" / ".join(f"{x:.2f}" for x in v) + (f" (mean {statistics.mean(v):.2f})" if len(v) > 1 else ""))
        print(f"| {m} | " + " | ".join(cells) + " |")

print("\nPaired per-street differences (finetuned minus X), dB: mean [min, max] over streets")
for split in ("val", "test"):
    for s in (0, 1, 2):
        f = B / f"eval_{split}_s{s}" / "budget.json"
        if not f.is_file():
            continue
        rows = {(r["method"], r["budget"]): r for r in json.loads(f.read_text())}
        for k in (0.1, 0.05):
            if ("finetuned", k) not in rows:
                continue
            ft = rows[("finetuned", k)]["psnr_per_sample"]
            parts = []
            for m in ("random@finetuned", "grid@finetuned", "opacity@finetuned", "dedup@finetuned", "random", "grid", "opacity", "dedup"):
                d = [a - b for a, b in zip(ft, rows[(m, k)]["psnr_per_sample"])]
                parts.append(f"{m} {statistics.mean(d):+.2f} [{min(d):+.2f}, {max(d):+.2f}]")
            one = rows[("finetuned", 1.0)]["psnr_per_sample"]
            d = [a - b for a, b in zip(ft, one)]
            parts.append(f"vs finetuned k=1 {statistics.mean(d):+.2f} [{min(d):+.2f}, {max(d):+.2f}]")
            base1 = rows[("random", 1.0)]["psnr_per_sample"]
            parts.append(f"finetuned k=1 minus base k=1 {statistics.mean([a-b for a,b in zip(one, base1)]):+.2f}")
            print(f"{split} seed {s} κ {k}: " + "; ".join(parts))

print("\nValidation choices (seed 0): finetuned PSNR at κ 1 / 0.1 / 0.05, and minus the best naive row on its own finetuned parameters")
for name, d in (("small, 100 steps (reference)", "eval_val_s0"), ("kappa_decoder=0", "eval_val_abl_kd0"),
                ("kappa_film=False", "eval_val_abl_nofilm"), ("200 steps", "eval_val_abl_steps200")):
    f = B / d / "budget.json"
    if not f.is_file():
        continue
    rows = {(r["method"], r["budget"]): r["psnr"] for r in json.loads(f.read_text())}
    cells = []
    for k in (1.0, 0.1, 0.05):
        ft = rows[("finetuned", k)]
        best = max(rows[(m, k)] for m in ("random@finetuned", "grid@finetuned", "opacity@finetuned", "dedup@finetuned"))
        base = max(rows[(m, k)] for m in ("random", "grid", "opacity", "dedup"))
        cells.append(f"{ft:.2f} (sel {ft - best:+.2f}, vs base {ft - base:+.2f})")
    print(f"| {name} | " + " | ".join(cells) + " |")
