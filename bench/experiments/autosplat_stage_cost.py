"""Why AutoSplat's foreground stage costs more per iteration than its background stage.

    python bench/experiments/autosplat_stage_cost.py [--data synthetic] [--preset demo]
        [--scale S] [--frames A:B] [--repeats 3]

Initialises a :class:`~clsplat.models.autosplat.trainer.Trainer` (no training) and, for each
training frame, renders what each stage renders, forward + backward of the summed image, timing
it (median over ``--repeats``) and counting Gaussians and tile intersections:

* ``background``: the background set alone (``bg_phase2``);
* ``objects``: the object sets alone, mirrored copies included (what ``foreground`` adds);
* ``both``: background (detached) + objects (``foreground``);

and, for the objects, the time to build their world-frame set (residual MLPs, mirroring, placing).
Prints one JSON line per frame and a summary line of medians over frames.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import clsplat  # noqa: F401  (first: thread defaults before torch loads)

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python bench/experiments/autosplat_stage_cost.py",
                                description=__doc__.split("\n")[0])
    p.add_argument("--data", default="synthetic")
    p.add_argument("--cameras", nargs="+", default=None)
    p.add_argument("--frames", default=None)
    p.add_argument("--preset", default="demo")
    p.add_argument("--scale", type=float, default=None)
    p.add_argument("--repeats", type=int, default=3)
    a = p.parse_args(argv)
    import tempfile

    import torch

    from clsplat.models.autosplat.data import load_sequence, parse_frames, prepare_data
    from clsplat.models.autosplat.model import Switches
    from clsplat.models.autosplat.trainer import Trainer
    from clsplat.models.common.presets import get_preset

    torch.set_num_threads(1)
    preset = get_preset("autosplat", a.preset)
    seq = load_sequence(a.data, a.cameras, parse_frames(a.frames), preset.scale if a.scale is None else a.scale)
    data = prepare_data(seq, a.cameras, preset.holdout)
    with tempfile.TemporaryDirectory() as tmp:
        tr = Trainer(data, preset, Switches(), tmp, progress=False)
        tr.initialise()
    m = tr.model
    rows = []
    for frame in data.train_frames:
        vm = data.viewmats[frame]
        rec: dict = {"frame": int(frame)}
        t0 = time.perf_counter()
        obj_sets = [m.object_set(k, frame) for k in range(len(tr.tracks))
                    if bool(m.present[k, frame]) and len(m.objects[k])]
        rec["objects_build_s"] = time.perf_counter() - t0
        for name, kw in (("background", dict(background=True, objects=False)),
                         ("objects", dict(background=False, objects=True)),
                         ("both", dict(background=True, objects=True, detach_background=True))):
            times = []
            for _ in range(a.repeats):
                gs, _ = m.scene_at(frame, **kw)
                if len(gs) == 0:
                    break
                t0 = time.perf_counter()
                col, alpha, meta = tr._render(gs, vm)
                t1 = time.perf_counter()
                (col.sum() + alpha.sum()).backward()
                t2 = time.perf_counter()
                times.append((t1 - t0, t2 - t1))
                tr.opt.zero_grad(set_to_none=True)
            if not times:
                continue
            rec[name] = {"gaussians": len(gs), "isects": int(meta["isect_ids"].numel()),
                         "fwd_s": statistics.median(t[0] for t in times),
                         "bwd_s": statistics.median(t[1] for t in times)}
        rec["object_sets"] = len(obj_sets)
        rows.append(rec)
        print(json.dumps(rec), flush=True)
    summary = {"frames": len(rows)}
    for name in ("background", "objects", "both"):
        got = [r[name] for r in rows if name in r]
        if got:
            summary[name] = {k: statistics.median(g[k] for g in got) for k in got[0]}
    summary["objects_build_s"] = statistics.median(r["objects_build_s"] for r in rows)
    print(json.dumps({"summary": summary}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
