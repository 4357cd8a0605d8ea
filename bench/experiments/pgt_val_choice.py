"""Issue 33: choosing ``small``'s budget-stage fields on the validation streets, by a criterion
fixed before the cells were scored (bench/notes/ecosplat_controls.md, "Re-choosing ...").

Each cell is a name and a folder pattern with ``{seed}`` standing for the budget seed (a folder
without it is budget seed 0 alone); the folder holds the ``budget.json`` of ``clsplat eval pgt ... --eval-split val``. A cell's score on one seed
is the mean of the learned selection's PSNR (row ``finetuned``) at κ 0.1 and κ 0.05. Prints, per
cell: the score seed by seed and mean ± sd, the finetuned PSNR at κ 1 / 0.1 / 0.05, the learned
selection minus the best naive selection on the same finetuned parameters and minus the best
naive pruning of the base, and κ 0.05 minus the finetuned κ 1; then the decision against the
``--reference`` cell: the best cell (by mean score) replaces the reference only if its mean beats
the reference's by more than the larger of the two seed sds (one seed each: no sd, so no
decision, only the screen's order). ``--guard METRIC`` (repeatable; any per-seed metric above, all
higher-is-better) adds a condition the winner must also meet: its mean not below the reference's by
more than the larger sd of that metric; ``--guard METRIC:gain``: above the reference's by more
than the larger sd (issue 33's 800-step rule, bench/notes/ecosplat_controls.md).

    .venv/bin/python bench/experiments/pgt_val_choice.py --reference current \\
        --cell 'current=/tmp/h33/eval400_val_s{seed}' --cell 'kd1=/tmp/h33v/eval_val_kd1_s{seed}' \\
        --json bench/figures/issue33_val_choice.json
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

NAIVE_FT = ("random@finetuned", "grid@finetuned", "opacity@finetuned", "dedup@finetuned")
NAIVE_BASE = ("random", "grid", "opacity", "dedup")
SEEDS = (0, 1, 2)
KAPPAS = (0.1, 0.05)


def seed_metrics(rows: dict[tuple[str, float], float]) -> dict[str, float]:
    """One seed's numbers from {(method, κ): PSNR}: score, finetuned PSNR at each κ, the margins."""
    out = {"score": statistics.mean(rows[("finetuned", k)] for k in KAPPAS)}
    for k in (1.0,) + KAPPAS:
        out[f"finetuned@{k:g}"] = rows[("finetuned", k)]
    for k in KAPPAS:
        ft = rows[("finetuned", k)]
        out[f"sel@{k:g}"] = ft - max(rows[(m, k)] for m in NAIVE_FT)
        out[f"vs_base@{k:g}"] = ft - max(rows[(m, k)] for m in NAIVE_BASE)
    out["k0.05-k1"] = rows[("finetuned", 0.05)] - rows[("finetuned", 1.0)]
    return out


def load_cell(pattern: str) -> dict[int, dict[str, float]]:
    """{seed: seed_metrics} for the seeds whose folder exists."""
    out = {}
    for s in (SEEDS if "{seed}" in pattern else (0,)):
        f = Path(pattern.format(seed=s)) / "budget.json"
        if f.is_file():
            out[s] = seed_metrics({(r["method"], r["budget"]): r["psnr"] for r in json.loads(f.read_text())})
    return out


def summary(per_seed: dict[int, dict[str, float]]) -> dict[str, dict]:
    """{metric: {"per_seed": {seed: v}, "mean": m, "sd": sd or None}}."""
    keys = next(iter(per_seed.values())).keys()
    res = {}
    for key in keys:
        v = [m[key] for m in per_seed.values()]
        res[key] = {"per_seed": {str(s): m[key] for s, m in per_seed.items()}, "mean": statistics.mean(v),
                    "sd": statistics.stdev(v) if len(v) > 1 else None}
    return res


def fmt(r: dict, signed: bool = False) -> str:
    f = "{:+.2f}" if signed else "{:.2f}"
    s = " / ".join(f.format(v) for v in r["per_seed"].values())
    if r["sd"] is not None:
        s += f" ({f.format(r['mean'])} ± {r['sd']:.2f})"
    return s


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cell", action="append", default=[], help="NAME=FOLDER, FOLDER with {seed} or seed 0 alone")
    ap.add_argument("--reference", default=None, help="the cell the winner must beat (the current recipe)")
    ap.add_argument("--json", type=Path, default=None, help="write every cell's numbers and the decision here")
    ap.add_argument("--guard", action="append", default=[],
                    help="METRIC or METRIC:gain, a further condition on the winner (see the docstring)")
    a = ap.parse_args(argv)
    guards: list[tuple[str, bool]] = []
    for g in a.guard:
        metric, _, mode = g.partition(":")
        if mode not in ("", "gain") or metric not in ("score", "finetuned@1", "k0.05-k1") + tuple(
                f"{p}@{k:g}" for p in ("finetuned", "sel", "vs_base") for k in KAPPAS):
            print(f"error: guard: expected METRIC or METRIC:gain with a metric of seed_metrics, got {g!r}",
                  file=sys.stderr)
            return 2
        guards.append((metric, mode == "gain"))
    cells: dict[str, dict] = {}
    for spec in a.cell:
        name, sep, pattern = spec.partition("=")
        if not sep or not name or not pattern:
            print(f"error: cell: expected NAME=FOLDER (FOLDER may hold {{seed}}), got {spec!r}", file=sys.stderr)
            return 2
        per = load_cell(pattern)
        if per:
            cells[name] = {"pattern": pattern, "seeds": sorted(per), **summary(per)}
    if not cells:
        print("error: cell: no cell has a budget.json", file=sys.stderr)
        return 2
    if a.reference is not None and a.reference not in cells:
        print(f"error: reference: {a.reference!r} is not a cell with results", file=sys.stderr)
        return 2
    print("| cell | seeds | score (mean of finetuned at κ 0.1, 0.05) | finetuned κ 1 | κ 0.1 | κ 0.05 "
          "| sel κ 0.1 | sel κ 0.05 | vs base κ 0.1 | vs base κ 0.05 | κ 0.05 − κ 1 |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, c in sorted(cells.items(), key=lambda kv: -kv[1]["score"]["mean"]):
        print(f"| {name} | {len(c['seeds'])} | {fmt(c['score'])} | {fmt(c['finetuned@1'])} | {fmt(c['finetuned@0.1'])} "
              f"| {fmt(c['finetuned@0.05'])} | {fmt(c['sel@0.1'], True)} | {fmt(c['sel@0.05'], True)} "
              f"| {fmt(c['vs_base@0.1'], True)} | {fmt(c['vs_base@0.05'], True)} | {fmt(c['k0.05-k1'], True)} |")
    out: dict = {"criterion": "mean of finetuned PSNR at kappa 0.1 and 0.05, validation streets; the best cell "
                              "replaces the reference only if its mean beats it by more than the larger seed sd",
                 "cells": cells}
    if a.reference is not None:
        best = max(cells, key=lambda n: cells[n]["score"]["mean"])
        ref = cells[a.reference]["score"]
        win = cells[best]["score"]
        diff = win["mean"] - ref["mean"]
        if best == a.reference:
            verdict = f"the reference {a.reference!r} scores best: it stands"
        elif win["sd"] is None or ref["sd"] is None:
            verdict = f"{best!r} leads by {diff:+.2f} dB on one seed: screen only, no decision"
        else:
            bar = max(win["sd"], ref["sd"])
            checks = []
            for metric, gain in guards:
                w, r = cells[best][metric], cells[a.reference][metric]
                d, gbar = w["mean"] - r["mean"], max(w["sd"], r["sd"])
                ok = d > gbar if gain else d >= -gbar
                checks.append({"metric": metric, "mode": "gain" if gain else "no fall", "diff": d, "bar": gbar,
                               "met": ok})
            failed = [c["metric"] for c in checks if not c["met"]]
            verdict = (f"{best!r} beats {a.reference!r} by {diff:+.2f} dB, "
                       + (f"beyond the larger sd {bar:.2f}" if diff > bar
                          else f"inside the larger sd {bar:.2f}: no gain, the reference stands"))
            if diff > bar:
                verdict += (f"; guards not met: {', '.join(failed)}: the reference stands" if failed
                            else ": it replaces the reference")
            for c in checks:
                verdict += (f"\n  guard {c['metric']} ({c['mode']}): {c['diff']:+.2f} dB against "
                            f"{'+' if c['mode'] == 'gain' else '-'}{c['bar']:.2f}: {'met' if c['met'] else 'NOT met'}")
            out["guards"] = checks
        out.update(reference=a.reference, best=best, diff=diff, verdict=verdict)
        print("\n" + verdict)
    if a.json is not None:
        a.json.write_text(json.dumps(out, indent=1, ensure_ascii=False) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
