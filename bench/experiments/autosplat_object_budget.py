"""Issue 36, deliverable 2: what AutoSplat's scene-following object budget gives a street, and what
an empty street pays (bench/notes/autosplat_moving_objects.md, "A budget that follows the scene").

``budget``: per street and seed, the decomposed tracks, those whose box shows in a training view,
their box pixels over the training views in images (``A``), the foreground iterations and the
objects' initial points the preset (with ``--set``) derives from them, and the seconds the count
took (:func:`clsplat.models.autosplat.objects.object_budget`; boxes only, never instance masks).

``table``: per run folder (``clsplat train autosplat ... --out RUN``), held-out PSNR of the whole
image, of the moving objects pooled and per class (car / pedestrian / other), the gap from the
image to each class, object Gaussians, iterations per stage (from ``log.jsonl``), seconds per stage
and the wall seconds.

``seeds``: run folders named ``PREFIX_<street>_<config>_s<seed>`` grouped by street and config: the
mean and range (min..max) over seeds of the whole image's held-out PSNR, the moving objects' (pooled
and per class), the gaps from the image to the pooled objects, the cars and the pedestrians, the
object Gaussians, the foreground iterations, the mean seconds per stage (``metrics.json``: wall, so
with the load and any pause of the process) and each training stage's iterations times its median
step's seconds (``log.jsonl``: a paused step or a load spike does not count); then, per street, each
config against ``--base`` (default ``old``) paired by seed (mean, min..max of the differences) with
the ratios per seed of the wall time and of the median-step training time, the latter also with each
run's time in units of its own phase 2 (the same work in both runs of a seed: a load gauge; not
meaningful against plain 3DGS, whose phase 2 takes phase 1's iterations too), and with ``--times`` the
whole command's CPU seconds (``/usr/bin/time``; immune to pauses and, mostly, to the load).

``count``: the box-pixel count (:func:`~clsplat.models.autosplat.objects.track_box_pixels`) against
the one before it counted inside each box's rectangle (``count_as_before`` of
tests/test_autosplat_budget.py: a full-image mask per box and view): both on each street and seed's
decomposed tracks and training views, alternating, ``--repeats`` times in this one process; the
medians, their ratio, and whether the counts are equal (they must be, element for element).

``empty``: the ``demo`` preset on the built-in street without moving vehicles (the generator's
``num_moving=0``: parked cars only, which stay in the background), trained with the budget fields
off and on (``--set``); per run the iterations and seconds of each stage, and the object sets.

    .venv/bin/python bench/experiments/autosplat_object_budget.py budget --data synthetic synthetic:busy \\
        --seeds 0 1 2 --set fg_steps_per_track=40 --set fg_steps_per_area=10 --set fg_steps_max=240
    .venv/bin/python bench/experiments/autosplat_object_budget.py table /work/runs/i36b_busy_*
    .venv/bin/python bench/experiments/autosplat_object_budget.py seeds /work/runs/i36c_*_s[345]
    .venv/bin/python bench/experiments/autosplat_object_budget.py count --data synthetic:busy --seeds 0 1 2 --set scale=1.5
    .venv/bin/python bench/experiments/autosplat_object_budget.py empty --out /tmp/empty \\
        --set fg_steps_per_track=40 --set fg_steps_per_area=10 --set fg_steps_max=240
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path


def _preset(name: str, sets: list[str] | None):
    import clsplat.models.autosplat  # noqa: F401  (registers the family's presets)
    from clsplat.models.common.presets import apply_sets, get_preset
    return apply_sets(get_preset("autosplat", name), sets)


def budget(args) -> None:
    from clsplat.models.autosplat.data import load_sequence, prepare_data
    from clsplat.models.autosplat.model import collect_tracks
    from clsplat.models.autosplat.objects import object_budget, track_box_pixels
    p = _preset(args.preset, args.set)
    print("| street | seed | tracks | visible | A (images) | fg iterations | object points (min / median / max) | count s |")
    print("|---" * 8 + "|")
    for spec in args.data:
        for seed in args.seeds:
            d = prepare_data(load_sequence(spec, None, None, p.scale, seed), None, p.holdout, p.dynamic_threshold,
                             tuple(p.road_classes))
            tracks = collect_tracks(d.seq, d.train_frames, p.dynamic_threshold)
            t0 = time.perf_counter()
            px = track_box_pixels(d.seq, [t.track_id for t in tracks], d.train_frames, d.cameras)
            b = object_budget(p, px, d.width * d.height)
            s = time.perf_counter() - t0
            pts = sorted(b.object_points)
            pt = f"{pts[0]} / {pts[len(pts) // 2]} / {pts[-1]}" if pts else "–"
            print(f"| {spec} | {seed} | {len(tracks)} | {b.visible_tracks} | {b.object_area:.2f} | {b.fg_steps} | "
                  f"{pt} | {s:.2f} |")


def table(args) -> None:
    import json
    from collections import Counter
    print("| run | iterations (phase 1 / 2 / fg / fusion) | held-out PSNR | objects | car | pedestrian | other "
          "| image − car | image − pedestrian | object Gaussians | seconds (phase 1 / 2 / fg / fusion) | wall s |")
    print("|---" * 12 + "|")
    f = lambda x: "–" if x is None else f"{x:.2f}"  # noqa: E731
    for run in args.runs:
        m = json.loads((Path(run) / "metrics.json").read_text())
        n = Counter(json.loads(x)["stage"] for x in (Path(run) / "log.jsonl").read_text().splitlines())
        pc = (m.get("objects") or {}).get("per_class", {})
        cls = {c: pc[c]["psnr"] if c in pc and pc[c]["pixels"] else None for c in ("car", "pedestrian", "other")}
        img, s = m["all"]["psnr"], m["seconds_per_stage"]
        gap = {c: None if v is None else img - v for c, v in cls.items()}
        stages = ("bg_phase1", "bg_phase2", "foreground", "fusion")
        print(f"| {Path(run).name} | {' / '.join(str(n.get(k, 0)) for k in stages)} | {img:.2f} | "
              f"{f(m['all'].get('psnr_objects'))} | {f(cls['car'])} | {f(cls['pedestrian'])} | {f(cls['other'])} | "
              f"{f(gap['car'])} | {f(gap['pedestrian'])} | {m['gaussians']['objects']} | "
              f"{' / '.join(f'{s.get(k, 0):.0f}' for k in stages)} | {m['wall_seconds']:.0f} |")


def _run(run: Path, times: list[Path] | None = None) -> dict:
    """One run folder's figures (None where a class has no pixel); ``cpu``: the whole command's user +
    system seconds from ``<first of times>/<run>.time`` (``/usr/bin/time -f "%e %U %S"`` or ``-v``; a rerun of the same
    command where the run itself was not timed) where there is one."""
    import json
    from collections import Counter
    import statistics
    m = json.loads((run / "metrics.json").read_text())
    log = [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines()]
    n = Counter(x["stage"] for x in log)
    # per stage: iterations x the median step's seconds (a step during which the process was paused, or
    # a load spike, does not count)
    med = {k: n[k] * statistics.median(x["time_s"] for x in log if x["stage"] == k) for k in n}
    pc = (m.get("objects") or {}).get("per_class", {})
    cls = {c: pc[c]["psnr"] if c in pc and pc[c]["pixels"] else None for c in ("car", "pedestrian", "other")}
    img, obj = m["all"]["psnr"], m["all"].get("psnr_objects")
    return {"image": img, "objects": obj, **cls, "gap objects": None if obj is None else img - obj,
            "gap car": None if cls["car"] is None else img - cls["car"],
            "gap pedestrian": None if cls["pedestrian"] is None else img - cls["pedestrian"],
            "object Gaussians": m["gaussians"]["objects"], "fg iterations": n.get("foreground", 0),
            "seconds": m["seconds_per_stage"], "wall": m["wall_seconds"], "median seconds": med,
            "train median s": sum(med.values()), "cpu": _cpu(run, times)}


def _cpu(run: Path, times: list[Path] | None) -> float | None:
    f = next((d / f"{run.name}.time" for d in times or [] if (d / f"{run.name}.time").is_file()), None)
    if f is None:
        return None
    text = f.read_text()
    if "User time (seconds):" in text:   # /usr/bin/time -v
        import re
        return sum(float(re.search(rf"{k} time \(seconds\): ([0-9.]+)", text).group(1)) for k in ("User", "System"))
    _, user, system = (float(x) for x in text.split()[-3:])
    return user + system


def seeds(args) -> None:
    import re
    import statistics
    name = re.compile(r"^[^_]+_(?P<street>[^_]+)_(?P<config>.+)_s(?P<seed>\d+)$")
    groups: dict[str, dict[str, dict[int, dict]]] = {}
    for run in map(Path, args.runs):
        g = name.match(run.name)
        if g and (run / "metrics.json").is_file():
            groups.setdefault(g["street"], {}).setdefault(g["config"], {})[int(g["seed"])] = _run(run, args.times)

    def agg(v: list) -> str:
        v = [x for x in v if x is not None]
        return "–" if not v else f"{statistics.mean(v):.2f} ({min(v):.2f}..{max(v):.2f})" if len(v) > 1 else f"{v[0]:.2f}"

    keys = ("image", "objects", "car", "pedestrian", "other", "gap objects", "gap car", "gap pedestrian")
    stages = ("load", "init", "bg_phase1", "bg_phase2", "foreground", "fusion", "eval")
    print("| street | config | seeds | " + " | ".join(keys) + " | object Gaussians | fg iterations | "
          "seconds (load / init / phase 1 / phase 2 / fg / fusion / eval) | wall s | "
          "iterations × median step s (phase 1 / 2 / fg / fusion = sum) | CPU s (command) |")
    print("|---" * (len(keys) + 9) + "|")
    for street, cfgs in sorted(groups.items()):
        for cfg, runs in sorted(cfgs.items()):
            rs = [runs[k] for k in sorted(runs)]
            sec = " / ".join(f"{statistics.mean(r['seconds'].get(k, 0) for r in rs):.0f}" for k in stages)
            print(f"| {street} | {cfg} | {','.join(map(str, sorted(runs)))} | "
                  + " | ".join(agg([r[k] for r in rs]) for k in keys)
                  + f" | {statistics.mean(r['object Gaussians'] for r in rs):.0f} | "
                  f"{'/'.join(str(r['fg iterations']) for r in rs)} | {sec} | "
                  f"{statistics.mean(r['wall'] for r in rs):.0f} | "
                  + " / ".join(f"{statistics.mean(r['median seconds'].get(k, 0) for r in rs):.0f}" for k in stages[2:6])
                  + f" = {statistics.mean(r['train median s'] for r in rs):.0f} | "
                  + ("/".join("–" if r["cpu"] is None else f"{r['cpu']:.0f}" for r in rs)) + " |")
    print(f"\n| street | config − {args.base} | seeds | " + " | ".join(keys[:5]) + " | wall ratio per seed | training ratio per seed (iterations × median step s) "
          "| the same, each run's in units of its own phase 2 | CPU ratio per seed (command) |")
    print("|---" * 12 + "|")
    for street, cfgs in sorted(groups.items()):
        base = cfgs.get(args.base, {})
        for cfg, runs in sorted(cfgs.items()):
            common = sorted(set(runs) & set(base))
            if cfg == args.base or not common:
                continue
            diff = lambda k: agg([None if runs[s][k] is None or base[s][k] is None  # noqa: E731
                                  else runs[s][k] - base[s][k] for s in common])
            ratio = " / ".join(f"{runs[s]['wall'] / base[s]['wall']:.2f}" for s in common)
            work = " / ".join(f"{runs[s]['train median s'] / base[s]['train median s']:.2f}" for s in common)
            # phase 2 is the same work in both runs of a seed (the budget changes the foreground stage and
            # the object sets only), so its time measures each run's load
            unit = lambda r: r["train median s"] / r["median seconds"].get("bg_phase2", float("nan"))  # noqa: E731
            norm = " / ".join(f"{unit(runs[s]) / unit(base[s]):.2f}" for s in common)
            cpu = " / ".join("–" if runs[s]["cpu"] is None or base[s]["cpu"] is None
                             else f"{runs[s]['cpu'] / base[s]['cpu']:.2f}" for s in common)
            print(f"| {street} | {cfg} − {args.base} | {','.join(map(str, common))} | "
                  + " | ".join(diff(k) for k in keys[:5]) + f" | {ratio} | {work} | {norm} | {cpu} |")


def count(args) -> None:
    import importlib.util
    import statistics
    import numpy as np
    from clsplat.models.autosplat.data import load_sequence, prepare_data
    from clsplat.models.autosplat.model import collect_tracks
    from clsplat.models.autosplat.objects import track_box_pixels
    path = Path(__file__).resolve().parents[2] / "tests" / "test_autosplat_budget.py"
    spec = importlib.util.spec_from_file_location("_budget_tests", path)
    ref = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ref)
    p = _preset(args.preset, args.set)
    print(f"| street | seed | H x W | tracks | views | before s (median of {args.repeats}) | now s | now / before | "
          "box pixels | equal |")
    print("|---" * 10 + "|")
    for name in args.data:
        for seed in args.seeds:
            d = prepare_data(load_sequence(name, None, None, p.scale, seed), None, p.holdout, p.dynamic_threshold,
                             tuple(p.road_classes))
            ids = [t.track_id for t in collect_tracks(d.seq, d.train_frames, p.dynamic_threshold)]
            times = {"before": [], "now": []}
            out = {}
            for _ in range(args.repeats):
                for key, fn in (("before", ref.count_as_before), ("now", track_box_pixels)):
                    t0 = time.perf_counter()
                    out[key] = fn(d.seq, ids, d.train_frames, d.cameras)
                    times[key].append(time.perf_counter() - t0)
            a, b = statistics.median(times["before"]), statistics.median(times["now"])
            print(f"| {name} | {seed} | {d.height} x {d.width} | {len(ids)} | {len(d.train_frames)} x {len(d.cameras)} | "
                  f"{a:.3f} | {b:.3f} | {b / a:.3f} | {int(out['now'].sum())} | "
                  f"{'yes' if np.array_equal(out['now'], out['before']) else 'NO'} |", flush=True)


def empty(args) -> None:
    from clsplat.data.synthetic import SyntheticConfig, generate_sequence
    from clsplat.models.autosplat.data import SYNTHETIC_DT, prepare_data
    from clsplat.models.autosplat.model import Switches
    from clsplat.models.autosplat.trainer import Trainer
    from clsplat.models.common.train import set_threads
    set_threads(args.threads, None)
    base = _preset(args.preset, None)
    seq = generate_sequence(SyntheticConfig(height=max(8, round(176 * base.scale)), width=max(8, round(320 * base.scale)),
                                            num_frames=16, seed=args.seeds[0], dt=SYNTHETIC_DT, num_moving=0))
    d = prepare_data(seq, None, base.holdout, base.dynamic_threshold, tuple(base.road_classes))
    print("| budget | iterations per stage | object sets | count s | init s | seconds per stage (phase 1 / 2 / fg / fusion) | train s |")
    print("|---" * 7 + "|")
    for label, p in (("fixed (fields off)", base), ("scaled (" + ", ".join(args.set or []) + ")", _preset(args.preset, args.set))):
        t0 = time.perf_counter()
        t = Trainer(d, p, Switches(), Path(args.out) / label.split()[0], progress=False)
        t.fit()
        s = t.stage_seconds
        print(f"| {label} | {' / '.join(str(v) for v in t.steps.values())} | {len(t.model.objects)} | "
              f"{t.budget.seconds:.3f} | {s['init']:.1f} | {s['bg_phase1']:.1f} / {s['bg_phase2']:.1f} / "
              f"{s['foreground']:.1f} / {s['fusion']:.1f} | {time.perf_counter() - t0:.1f} |", flush=True)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mode", choices=("budget", "table", "seeds", "count", "empty"))
    ap.add_argument("runs", nargs="*", help="run folders (table)")
    ap.add_argument("--data", nargs="+", default=["synthetic", "synthetic:busy"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--set", action="append", default=None, metavar="FIELD=VALUE")
    ap.add_argument("--out", default="/tmp/autosplat_object_budget")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--times", type=Path, nargs="+", default=None,
                    help="seeds: folders of /usr/bin/time outputs RUN.time (the first that has one)")
    ap.add_argument("--base", default="old", help="seeds: the config the others are paired against")
    ap.add_argument("--repeats", type=int, default=3, help="count: timings of each (medians reported)")
    args = ap.parse_args(argv)
    {"budget": budget, "table": table, "seeds": seeds, "count": count, "empty": empty}[args.mode](args)


if __name__ == "__main__":
    main()
