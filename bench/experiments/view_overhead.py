"""What ``clsplat train ... --view`` costs a training run: AutoSplat fits with and without the
viewer, alternated (ABBA) on the same prepared data after a warm-up fit, wall time of ``Trainer.fit``
side by side.

    python bench/experiments/view_overhead.py --preset demo --pairs 3 [--browser] [--out FILE.json]

Without ``--browser`` no client connects: the run with the viewer pays the server's start, a list
append and a look at the client table per step (the issue's target: under 10%). With
``--browser`` a headless Chromium (clsplat.viewer.browser) watches the viewed runs, so the
Gaussians are pushed every ``--every`` steps and the exact renders run between steps: that is
the cost of watching, reported for information (the browser's own CPU competes on a small machine).
Each viewed fit also records the seconds spent inside the viewer's per-step hook (the server's
start included), the figure that a loaded machine's noise does not blur: the wall-time ratio
needs many pairs to resolve a few percent when other work shares the cores.
Prints one JSON line per fit, then the medians and their ratio; ``--out`` writes them all.
"""
from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python bench/experiments/view_overhead.py", description=__doc__.split("\n")[0])
    p.add_argument("--preset", default="demo", help="AutoSplat preset (default demo: 220 iterations)")
    p.add_argument("--pairs", type=int, default=3, help="ABBA pairs of fits (default 3)")
    p.add_argument("--every", type=int, default=10, help="--view-every of the viewed runs (default 10)")
    p.add_argument("--browser", action="store_true", help="a headless chromium watches the viewed runs")
    p.add_argument("--out", default=None, help="JSON file for the rows and the summary")
    a = p.parse_args(argv)

    import torch

    from clsplat.models.autosplat.data import load_sequence
    from clsplat.models.autosplat.model import Switches
    from clsplat.models.autosplat.trainer import Trainer, prepare_data
    from clsplat.models.autosplat.view import autosplat_scene
    from clsplat.models.common.presets import get_preset
    from clsplat.models.common.view import TrainView

    torch.set_num_threads(1)   # as clsplat demo: torch and PoCL's workers otherwise fight over the cores
    preset = get_preset("autosplat", a.preset)
    seq = load_sequence("synthetic", None, None, preset.scale, seed=preset.seed)
    data = prepare_data(seq, None, preset.holdout)
    rows = []
    order = []
    for i in range(a.pairs):
        order += ["plain", "view"] if i % 2 == 0 else ["view", "plain"]
    with tempfile.TemporaryDirectory() as tmp:
        # warm-up, not measured: OpenCL program builds and first-call caches
        Trainer(data, preset, Switches(), Path(tmp) / "warmup", progress=False).fit(stop_at=5)
        for i, mode in enumerate(order):
            tr = Trainer(data, preset, Switches(), Path(tmp) / f"run{i}", progress=False)
            watcher = browser = None
            if mode == "view":
                watcher = TrainView(lambda: autosplat_scene(tr.model, data.seq, data, "overhead"), port=0,
                                    every=a.every)
                if a.browser:
                    watcher.start()
                    from clsplat.viewer.browser import HeadlessChromium
                    browser = HeadlessChromium(watcher.viewer.url, 800, 600)
                    t0 = time.time()
                    while not watcher.viewer.clients() and time.time() - t0 < 120:
                        time.sleep(0.2)
            hook = [0.0, 0, 0.0]   # seconds inside the viewer's per-step hook, calls, the first call's seconds

            def on_step(step, rec, w=watcher):
                h0 = time.perf_counter()
                w.on_step(step, rec)   # the first call starts the server and sends the first scene
                dt = time.perf_counter() - h0
                hook[0] += dt
                hook[1] += 1
                if hook[1] == 1:
                    hook[2] = dt
            t0 = time.perf_counter()
            try:
                tr.fit(on_step=None if watcher is None else on_step)
                wall = time.perf_counter() - t0
            finally:
                if browser is not None:
                    browser.close()
                if watcher is not None:
                    watcher.close()
            steps = [json.loads(x) for x in (Path(tmp) / f"run{i}" / "log.jsonl").read_text().splitlines() if x]
            row = {"fit": i, "mode": mode, "fit_wall_s": round(wall, 3),
                   "steps": len(steps), "step_time_sum_s": round(sum(r["time_s"] for r in steps), 3),
                   "hook_s": round(hook[0], 4), "hook_calls": hook[1], "hook_start_s": round(hook[2], 4),
                   "refreshes": watcher.refreshes if watcher else 0,
                   "exact_renders": watcher.viewer.renders if watcher and watcher.viewer else 0}
            rows.append(row)
            print(json.dumps(row), flush=True)
    med = {m: statistics.median(r["fit_wall_s"] for r in rows if r["mode"] == m) for m in ("plain", "view")}
    viewed = [r for r in rows if r["mode"] == "view"]
    summary = {"preset": a.preset, "pairs": a.pairs, "browser": a.browser, "every": a.every,
               "median_fit_wall_s": med, "view_over_plain": round(med["view"] / med["plain"], 4),
               # the robust figure on a loaded machine: time inside the hook over the viewed fit's wall time
               "hook_share_median": round(statistics.median(r["hook_s"] / r["fit_wall_s"] for r in viewed), 6),
               "hook_start_s_median": statistics.median(r["hook_start_s"] for r in viewed),
               # every later step: a list append and a look at the client table (no browser)
               "hook_per_later_step_ms_median": round(statistics.median(
                   1e3 * (r["hook_s"] - r["hook_start_s"]) / max(1, r["hook_calls"] - 1) for r in viewed), 4)}
    print(json.dumps(summary), flush=True)
    if a.out:
        Path(a.out).write_text(json.dumps({"rows": rows, "summary": summary}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
