"""Tables of issue 33's EcoSplat controls from ``clsplat eval pgt`` folders (bench/notes/ecosplat_controls.md).

Reads ROOT/{PREFIX}{val,test}_s{0,1,2}/budget.json (``--prefix``, default ``eval_``: the 100-step
budget stage; ``eval400_``: small's 400-step one) and ROOT/eval_val_abl_*/ for the validation
choices, and prints

* PSNR per method and κ, seed by seed;
* the issue's comparisons seed by seed with mean ± sd over seeds (learned selection minus the best
  naive selection on the same finetuned parameters, minus the best naive pruning of the base
  model, κ 0.05 minus the finetuned model's own κ 1), the best row picked per seed;
* the paired per-street differences (learned selection minus each row, from ``psnr_per_sample``);
* the validation-choice rows.

    .venv/bin/python bench/experiments/pgt_controls_table.py /tmp/h33 [--prefix eval400_] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

ORDER = ["finetuned", "random@finetuned", "grid@finetuned", "opacity@finetuned", "dedup@finetuned",
         "random", "grid", "opacity", "dedup"]
NAIVE_FT = ("random@finetuned", "grid@finetuned", "opacity@finetuned", "dedup@finetuned")
NAIVE_BASE = ("random", "grid", "opacity", "dedup")
SEEDS = (0, 1, 2)


def load(root: Path, prefix: str, split: str) -> dict[int, dict[tuple[str, float], dict]]:
    """{seed: {(method, κ): row of budget.json}} for the folders that exist."""
    out = {}
    for s in SEEDS:
        f = root / f"{prefix}{split}_s{s}" / "budget.json"
        if f.is_file():
            out[s] = {(r["method"], r["budget"]): r for r in json.loads(f.read_text())}
    return out


def mean_sd(v: list[float]) -> str:
    if len(v) < 2:
        return f"{v[0]:+.2f}" if v else "-"
    return f"{statistics.mean(v):+.2f} ± {statistics.stdev(v):.2f}"


def comparisons(runs: dict[int, dict]) -> dict[str, dict]:
    """{comparison: {"per_seed": [(seed, diff, best row)], "mean": m, "sd": sd}} for κ 0.1 and 0.05."""
    res: dict[str, dict] = {}
    for k in (0.1, 0.05):
        for name, pool in ((f"learned - best naive @finetuned, κ {k:g}", NAIVE_FT),
                           (f"learned - best naive base, κ {k:g}", NAIVE_BASE)):
            per = []
            for s, rows in runs.items():
                if ("finetuned", k) not in rows:
                    continue
                best = max(pool, key=lambda m: rows[(m, k)]["psnr"])
                per.append((s, rows[("finetuned", k)]["psnr"] - rows[(best, k)]["psnr"], best))
            res[name] = {"per_seed": per}
    for k in (0.1, 0.05):
        per = [(s, rows[("finetuned", k)]["psnr"] - rows[("finetuned", 1.0)]["psnr"], "finetuned κ 1")
               for s, rows in runs.items() if ("finetuned", k) in rows]
        res[f"κ {k:g} - finetuned κ 1"] = {"per_seed": per}
    per = [(s, rows[("finetuned", 1.0)]["psnr"] - rows[("random", 1.0)]["psnr"], "base κ 1")
           for s, rows in runs.items() if ("finetuned", 1.0) in rows]
    res["finetuned κ 1 - base κ 1"] = {"per_seed": per}
    for r in res.values():
        v = [d for _, d, _ in r["per_seed"]]
        r["mean"] = statistics.mean(v) if v else None
        r["sd"] = statistics.stdev(v) if len(v) > 1 else None
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("root", type=Path, help="folder holding the eval folders")
    ap.add_argument("--prefix", default="eval_", help="eval folders' prefix (eval_ or eval400_)")
    ap.add_argument("--json", type=Path, default=None, help="write the comparisons (both splits) here")
    a = ap.parse_args(argv)
    if not a.root.is_dir():
        print(f"error: root: {a.root} is not a folder", file=sys.stderr)
        return 2
    summary: dict = {}
    for split in ("val", "test"):
        runs = load(a.root, a.prefix, split)
        if not runs:
            continue
        kappas = sorted({k for rows in runs.values() for _, k in rows}, reverse=True)
        print(f"\n{split}: seeds {sorted(runs)}")
        print("| method | " + " | ".join(f"κ {k:g}" for k in kappas) + " |")
        print("|---|" + "---|" * len(kappas))
        for m in ORDER:
            cells = []
            for k in kappas:
                v = [rows[(m, k)]["psnr"] for rows in runs.values() if (m, k) in rows]
                cells.append(" / ".join(f"{x:.2f}" for x in v)
                             + (f" (mean {statistics.mean(v):.2f})" if len(v) > 1 else ""))
            print(f"| {m} | " + " | ".join(cells) + " |")
        comp = comparisons(runs)
        summary[split] = {"seeds": sorted(runs), "comparisons": comp,
                          "psnr": {f"{m}@{k:g}": {str(s): rows[(m, k)]["psnr"] for s, rows in runs.items()
                                                  if (m, k) in rows} for m in ORDER for k in kappas}}
        print(f"\n{split}: the issue's comparisons, per seed ({' / '.join(str(s) for s in runs)}), mean ± sd")
        print("| comparison | per seed (best row) | mean ± sd |")
        print("|---|---|---|")
        for name, r in comp.items():
            cells = " / ".join(f"{d:+.2f} ({b})" for _, d, b in r["per_seed"])
            print(f"| {name} | {cells} | {mean_sd([d for _, d, _ in r['per_seed']])} |")

    print("\nPaired per-street differences (finetuned minus X), dB: mean [min, max] over streets")
    for split in ("val", "test"):
        for s, rows in load(a.root, a.prefix, split).items():
            for k in (0.1, 0.05):
                if ("finetuned", k) not in rows:
                    continue
                ft = rows[("finetuned", k)]["psnr_per_sample"]
                parts = []
                for m in ORDER[1:]:
                    d = [x - y for x, y in zip(ft, rows[(m, k)]["psnr_per_sample"])]
                    parts.append(f"{m} {statistics.mean(d):+.2f} [{min(d):+.2f}, {max(d):+.2f}]")
                one = rows[("finetuned", 1.0)]["psnr_per_sample"]
                d = [x - y for x, y in zip(ft, one)]
                parts.append(f"vs finetuned k=1 {statistics.mean(d):+.2f} [{min(d):+.2f}, {max(d):+.2f}]")
                base1 = rows[("random", 1.0)]["psnr_per_sample"]
                parts.append(f"finetuned k=1 minus base k=1 {statistics.mean([x - y for x, y in zip(one, base1)]):+.2f}")
                print(f"{split} seed {s} κ {k}: " + "; ".join(parts))

    print("\nValidation choices (seed 0): finetuned PSNR at κ 1 / 0.1 / 0.05, and minus the best naive row "
          "on its own finetuned parameters")
    for name, d in (("small, 100 steps (reference)", "eval_val_s0"), ("kappa_decoder=0", "eval_val_abl_kd0"),
                    ("kappa_film=False", "eval_val_abl_nofilm"), ("200 steps", "eval_val_abl_steps200"),
                    ("small, 400 steps", "eval400_val_s0")):
        f = a.root / d / "budget.json"
        if not f.is_file():
            continue
        rows = {(r["method"], r["budget"]): r["psnr"] for r in json.loads(f.read_text())}
        cells = []
        for k in (1.0, 0.1, 0.05):
            ft = rows[("finetuned", k)]
            best = max(rows[(m, k)] for m in NAIVE_FT)
            base = max(rows[(m, k)] for m in NAIVE_BASE)
            cells.append(f"{ft:.2f} (sel {ft - best:+.2f}, vs base {ft - base:+.2f})")
        print(f"| {name} | " + " | ".join(cells) + " |")
    if a.json is not None:
        a.json.write_text(json.dumps(summary, indent=1, ensure_ascii=False) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
