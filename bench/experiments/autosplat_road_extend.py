"""Issue 33, the road-continuation prior on the divided road: the table of full, full with
``road_extend_m`` and plain 3DGS at 0, 1, 2 and 3 m off the recorded path, over whole images, road
pixels and the pixels no training camera saw, from the runs of ``autosplat_views.py``.

The 1-3 m figures are the runs' own ``metrics.json`` (``lane_change.{1m,2m,3m}``); the 0 m ones
(the recorded rig at the held-out frames: whole image, road pixels, unseen pixels) are not in it,
so each run's checkpoint is rebuilt (:func:`clsplat.models.autosplat.evaluate.trainer_from_checkpoint`)
and scored with :func:`.viewsets.lane_change` at a 0 m shift, cached as ``zero_shift.json`` beside
the run's ``metrics.json``. Then the paired differences per seed (mean ± sample sd) and, with
``--rule``, the adoption rule of ``bench/notes/autosplat_unseen_share.md`` (2026-11-27).

    .venv/bin/python bench/experiments/autosplat_road_extend.py --out /work/runs/i33e_roadext_val \\
        --seeds 0 1 2 --ext "full, road extend 8m" "full, road extend 16m" --control "plain, road extend 8m" --rule
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

SHIFTS = ("0m", "1m", "2m", "3m")
#: (column, key in a shift's block)
KINDS = (("image", "psnr"), ("road px", "psnr_road"), ("unseen px", "psnr_unseen"))


def folder(out: Path, row: str, seed: int) -> Path:
    """The run folder ``autosplat_views.py`` gives ``row`` and ``seed``."""
    return out / row.replace(", ", "_").replace(" ", "_") / f"seed{seed}"


def zero_shift(run: Path) -> dict:
    """``lane_change``'s block for the recorded rig (0 m) of the run in ``run`` (cached)."""
    cache = run / "zero_shift.json"
    if cache.is_file():
        return json.loads(cache.read_text())
    import torch

    from clsplat.models.autosplat import viewsets
    from clsplat.models.autosplat.evaluate import trainer_from_checkpoint

    torch.set_num_threads(1)
    ck_path = run / "checkpoint.pt"
    ck = torch.load(ck_path, map_location="cpu", weights_only=False)
    tr = trainer_from_checkpoint(ck, ck_path, run, None)
    kept = viewsets.LATERAL_SHIFTS_M
    viewsets.LATERAL_SHIFTS_M = (0.0,)
    try:
        block = viewsets.lane_change(tr, tr.data.test_frames[0], None)["0m"]
    finally:
        viewsets.LATERAL_SHIFTS_M = kept
    block = {k: v for k, v in block.items() if k != "unseen_share"} | {
        "unseen_share": block["unseen_share"]["overall"]}
    cache.write_text(json.dumps(block, indent=1) + "\n")
    return block


def scores(out: Path, row: str, seed: int) -> dict | None:
    """``{shift: {key: PSNR}}`` of one run (None if it has not finished), with ``held_out``."""
    run = folder(out, row, seed)
    if not (run / "metrics.json").is_file():
        return None
    m = json.loads((run / "metrics.json").read_text())
    res = {s: m["lane_change"][s] for s in SHIFTS[1:]}
    res["0m"] = zero_shift(run)
    res["held_out"] = m["all"]["psnr"]
    res["gaussians_road"] = m["gaussians"]["road"]
    return res


def _cell(vals: list[float]) -> str:
    txt = " / ".join(f"{v:+.2f}" for v in vals)
    return txt + (f" (**{np.mean(vals):+.2f} ± {np.std(vals, ddof=1):.2f}**)" if len(vals) > 1 else "")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True, help="the --out of autosplat_views.py")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--ext", nargs="+", default=["full, road extend 8m"], help="the rows with the prior")
    ap.add_argument("--control", nargs="*", default=[],
                    help="plain 3DGS rows given the prior (e.g. 'plain, road extend 8m'): in the table, against "
                         "plain and against the full model with the same width")
    ap.add_argument("--rule", action="store_true", help="print the adoption rule's verdict per width")
    ap.add_argument("--h2", nargs=2, metavar=("BASE", "CONTROL"),
                    help="H2 (2026-11-27, helper s7): for every --ext row, ext − CONTROL at 3 m (> 0 on every "
                         "seed) and the held-out drop against BASE (paired mean <= 0.1 dB); both rows join the "
                         "table, e.g. 'full, road extend 8m' 'plain, road extend 8m'")
    a = ap.parse_args()
    out = Path(a.out)
    rows = ["full", *a.ext, "plain", *a.control]
    rows += [r for r in (a.h2 or []) if r not in rows]
    runs = {r: {s: scores(out, r, s) for s in a.seeds} for r in rows}
    runs = {r: {s: v for s, v in by.items() if v is not None} for r, by in runs.items()}
    lines = ["| row | seeds | " + " | ".join(f"{s} {k}" for s in SHIFTS for k, _ in KINDS) + " | held-out |",
             "|---|---|" + "---|" * (len(SHIFTS) * len(KINDS) + 1)]
    for r in rows:
        ss = sorted(runs[r])
        if not ss:
            continue
        cells = [" / ".join(f"{runs[r][s][sh][k]:.2f}" if runs[r][s][sh].get(k) is not None else "-" for s in ss)
                 for sh in SHIFTS for _, k in KINDS]
        held = " / ".join(f"{runs[r][s]['held_out']:.2f}" for s in ss)
        lines.append(f"| {r}, PSNR | {' / '.join(map(str, ss))} | " + " | ".join(cells) + f" | {held} |")

    def diff(x: str, y: str) -> None:
        ss = sorted(set(runs[x]) & set(runs[y]))
        if not ss:
            return
        cells = [_cell([runs[x][s][sh][k] - runs[y][s][sh][k] for s in ss
                        if runs[x][s][sh].get(k) is not None and runs[y][s][sh].get(k) is not None])
                 for sh in SHIFTS for _, k in KINDS]
        held = _cell([runs[x][s]["held_out"] - runs[y][s]["held_out"] for s in ss])
        lines.append(f"| {x} − {y} | {' / '.join(map(str, ss))} | " + " | ".join(cells) + f" | {held} |")

    diff("full", "plain")
    for e in a.ext:
        diff(e, "plain")
        diff(e, "full")
    for c in a.control:
        diff(c, "plain")
        for e in a.ext:
            if e.split(", ", 1)[1:] == c.split(", ", 1)[1:]:
                diff(e, c)
    if a.h2:
        for e in a.ext:
            for r in a.h2:
                if r != e:
                    diff(e, r)
    print("\n".join(lines))
    print("\nroad Gaussians at the end: " + "; ".join(
        f"{r}: " + " / ".join(str(runs[r][s]["gaussians_road"]) for s in sorted(runs[r])) for r in rows))
    if a.rule:
        for e in a.ext:
            ss = sorted(set(runs[e]) & set(runs["full"]) & set(runs["plain"]))
            if len(ss) < 2:
                print(f"{e}: too few seeds ({ss})")
                continue
            g = np.array([runs[e][s]["3m"]["psnr"] - runs["full"][s]["3m"]["psnr"] for s in ss])
            h = np.array([runs["full"][s]["held_out"] - runs[e][s]["held_out"] for s in ss])
            v = np.array([runs[e][s]["3m"]["psnr"] - runs["plain"][s]["3m"]["psnr"] for s in ss])
            a_ok = bool((g > 0).all() and g.mean() > g.std(ddof=1))
            b_ok = bool(h.mean() <= 0.1)
            print(f"{e}: (a) 3 m gain over full {g.round(2).tolist()} mean {g.mean():+.2f} sd {g.std(ddof=1):.2f}: "
                  f"{'pass' if a_ok else 'fail'}; (b) held-out drop {h.round(2).tolist()} mean {h.mean():+.2f}: "
                  f"{'pass' if b_ok else 'fail'}; adopt: {a_ok and b_ok}; ext − plain at 3 m {v.round(2).tolist()}: "
                  f"H {'confirmed' if a_ok and b_ok and (v > 0).all() else 'not confirmed'}")

    if a.h2:
        base, control = a.h2
        for e in a.ext:
            ss = sorted(set(runs[e]) & set(runs[base]) & set(runs[control]))
            if len(ss) < 2:
                print(f"{e}: too few seeds for H2 ({ss})")
                continue
            v = np.array([runs[e][s]["3m"]["psnr"] - runs[control][s]["3m"]["psnr"] for s in ss])
            h = np.array([runs[base][s]["held_out"] - runs[e][s]["held_out"] for s in ss])
            ok = bool((v > 0).all() and h.mean() <= 0.1)
            print(f"{e}: H2 — 3 m against {control} {v.round(2).tolist()} mean {v.mean():+.2f} sd "
                  f"{v.std(ddof=1):.2f}; held-out drop against {base} {h.round(2).tolist()} mean {h.mean():+.2f}: "
                  f"H2 {'holds' if ok else 'refuted'}")


if __name__ == "__main__":
    main()
