"""Tables of issue 36's object-vs-image gap (bench/notes/autosplat_moving_objects.md) from AutoSplat
run folders named ``PREFIX_<street>_<config>_s<seed>``.

Per run: held-out PSNR over whole images and over the moving tracks' pixels (``psnr_objects``),
their gap, the same on the training frames, the per-class object PSNR / SSIM of ``metrics.json``'s
``objects`` section (issue 36) and the parked vehicles' PSNR (``static_per_class``: objects of the
same kind standing still, reconstructed by the background), Gaussians in the object sets, seconds
per stage and the median seconds per iteration. The ``objects`` section is read from
``EVAL_ROOT/<run>/metrics.json`` where there is one (``clsplat eval autosplat --checkpoint RUN
--out EVAL_ROOT/<run> --views recorded``: runs made before the section, or before its
``static_per_class``, existed), else from the run's own. Then per (street, config)
the mean over seeds with the spread (min..max) of the gap and of the object PSNR.

    .venv/bin/python bench/experiments/autosplat_object_gap.py /work/runs --prefix i36 --eval-root /work/runs/i36_eval
"""
from __future__ import annotations

import argparse
import json
import re
import statistics
from pathlib import Path

NAME = re.compile(r"^(?P<prefix>[^_]+)_(?P<street>[^_]+)_(?P<config>.+)_s(?P<seed>\d+)$")


def _f(x, fmt: str = ".2f") -> str:
    return "–" if x is None else format(x, fmt)


def load(root: Path, prefix: str, eval_root: Path | None) -> list[dict]:
    rows = []
    for d in sorted(root.glob(f"{prefix}_*")):
        m = NAME.match(d.name)
        if not m or not (d / "metrics.json").is_file():
            continue
        r = json.loads((d / "metrics.json").read_text())
        objects = r.get("objects")
        if eval_root is not None and (eval_root / d.name / "metrics.json").is_file():
            objects = json.loads((eval_root / d.name / "metrics.json").read_text()).get("objects") or objects
        rows.append({"run": d.name, **m.groupdict(), "seed": int(m["seed"]), "m": r, "objects": objects})
    return rows


def run_table(rows: list[dict]) -> None:
    print("| run | data | held-out PSNR | objects | gap | train: image / objects | car | pedestrian | other "
          "| parked cars | object Gaussians | fg s | fusion s | s/it | wall s |")
    print("|---" * 15 + "|")
    for r in rows:
        m, o = r["m"], r["objects"] or {}
        a, t = m["all"], m.get("train", {})
        gap = None if a.get("psnr_objects") is None else a["psnr"] - a["psnr_objects"]
        pc = o.get("per_class", {})
        cls = [f"{_f(pc[c]['psnr'])} / {_f(pc[c]['ssim'], '.3f')} ({pc[c]['tracks']})" if c in pc and pc[c]["pixels"]
               else "–" for c in ("car", "pedestrian", "other")]
        st = o.get("static_per_class", {}).get("car")
        sp = m.get("seconds_per_stage", {})
        print(f"| {r['run']} | {m['protocol'].get('data', '?')} | {a['psnr']:.2f} | {_f(a.get('psnr_objects'))} | "
              f"{_f(gap)} | {_f(t.get('psnr'))} / {_f(t.get('psnr_objects'))} | {' | '.join(cls)} | "
              f"{_f(st['psnr']) if st and st['pixels'] else '–'} | {m['gaussians']['objects']} | "
              f"{sp.get('foreground', 0):.0f} | {sp.get('fusion', 0):.0f} | {_f(m.get('seconds_per_iteration'), '.3f')} | "
              f"{m.get('wall_seconds', 0):.0f} |")


def seed_table(rows: list[dict]) -> None:
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["street"], r["config"]), []).append(r)
    print("\n| street | config | seeds | held-out PSNR | objects (min..max) | gap (min..max) | train objects |")
    print("|---" * 7 + "|")
    for (street, config), rs in sorted(groups.items()):
        img = [r["m"]["all"]["psnr"] for r in rs]
        obj = [r["m"]["all"]["psnr_objects"] for r in rs if r["m"]["all"].get("psnr_objects") is not None]
        gap = [r["m"]["all"]["psnr"] - r["m"]["all"]["psnr_objects"] for r in rs
               if r["m"]["all"].get("psnr_objects") is not None]
        tro = [r["m"]["train"]["psnr_objects"] for r in rs if r["m"].get("train", {}).get("psnr_objects") is not None]
        rng = lambda v: f"{statistics.mean(v):.2f} ({min(v):.2f}..{max(v):.2f})" if v else "–"  # noqa: E731
        print(f"| {street} | {config} | {','.join(str(r['seed']) for r in rs)} | {statistics.mean(img):.2f} | "
              f"{rng(obj)} | {rng(gap)} | {rng(tro)} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("root", type=Path, help="folder holding the run folders")
    p.add_argument("--prefix", default="i36")
    p.add_argument("--eval-root", type=Path, default=None, help="re-evaluations of runs made before 'objects' existed")
    a = p.parse_args()
    rows = load(a.root, a.prefix, a.eval_root)
    run_table(rows)
    seed_table(rows)


if __name__ == "__main__":
    main()
