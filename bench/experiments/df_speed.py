"""DrivingForward speed and memory per preset: a training step, and a 6-camera inference split
into depth / Gaussians / render.

Each (preset, phase) runs in its own subprocess so that its peak resident memory
(``ru_maxrss``) is its own. A training step is timed whole (data, three networks, losses,
backward, Adam) and with its data loading separately; inference is ``depth_net`` (encoder +
fusion + decoder), the Gaussian network + lifting to a ``GaussianSet`` (ego frame), and one
``clsplat.rasterization`` of the 6 cameras at t+1. In a training step, ``render_fwd_bwd`` is the
renderer's own share: the step's Gaussians (detached) re-rendered at the step's 12 views and
back-propagated, i.e. the PoCL part of the step. The first repetition (kernel builds, allocator
warm-up) is dropped; medians of the rest are reported.

``--threads 1 2`` measures each (preset, phase) with those torch thread counts, alternating the
subprocesses ``--rounds`` times so that the settings see the same machine load (the torch / PoCL
split: PoCL's CPU device always uses every core; torch's threads compete with it).

    nice -n 10 .venv/bin/python bench/experiments/df_speed.py --presets tiny small paper \\
        --out bench/out/df_speed.json
    nice -n 10 .venv/bin/python bench/experiments/df_speed.py --presets small --phases train \\
        --threads 1 2 --rounds 3 --reps 3 --out bench/out/df_threads.json
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time


def _run_phase(preset_name: str, phase: str, reps: int, threads: int = 1) -> dict:
    import resource

    import torch

    from clsplat.models.common.data import parse_data
    from clsplat.models.common.presets import get_preset
    from clsplat.models.common.train import sample_generator
    from clsplat.models.drivingforward.data import colour_jitter, load_triplet
    from clsplat.models.drivingforward.cli import make_optimizer
    from clsplat.models.drivingforward.model import DrivingForward

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    p = get_preset("drivingforward", preset_name)
    model = DrivingForward(p)
    src = parse_data("synthetic")
    times: dict[str, list[float]] = {}

    def tick(key: str, t0: float) -> float:
        t = time.perf_counter()
        times.setdefault(key, []).append(t - t0)
        return t

    if phase == "train":
        opt = make_optimizer(model, p)
        seen: list = []
        render = model.render

        def recording_render(g, viewmats, Ks):
            seen[:] = [g.detach(), viewmats.detach(), Ks.detach()]
            return render(g, viewmats, Ks)

        model.render = recording_render
        for i in range(reps + 1):
            t0 = time.perf_counter()
            s = load_triplet(src, i, p)
            t1 = tick("data", t0)
            net = colour_jitter(s["images"], sample_generator(0, i), p.jitter)
            opt.zero_grad()
            terms = model.training_losses(s["images"], net, s["Ks"], s["cam_to_ego"])
            t2 = tick("forward", t1)
            terms["loss"].backward()
            t3 = tick("backward", t2)
            opt.step()
            tick("adam", t3)
            tick("step", t0)
            g, viewmats, Ks = seen
            g = g._map(lambda t: t.clone().requires_grad_(True))
            t4 = time.perf_counter()
            render(g, viewmats, Ks)[0].square().mean().backward()
            tick("render_fwd_bwd", t4)
    else:
        model.eval()
        s = load_triplet(src, 0, p)
        viewmats = s["viewmats"][2] @ s["ego_to_world"][1]
        with torch.no_grad():
            for _ in range(reps + 1):
                t0 = time.perf_counter()
                d = model.depth_net(s["images"][1], s["Ks"], s["cam_to_ego"])
                t1 = tick("depth", t0)
                g, _ = model.frame_gaussians(s["images"][1], s["images"][1], s["Ks"], s["cam_to_ego"], d)
                t2 = tick("gaussians", t1)
                model.render(g, viewmats, s["Ks"])
                tick("render", t2)
                tick("total", t0)
    med = {k: statistics.median(v[1:]) if len(v) > 1 else v[0] for k, v in times.items()}
    return {"preset": preset_name, "phase": phase, "reps": reps, "torch_threads": threads, "median_s": med,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "gaussians": 6 * p.height * p.width, "size": f"{p.height}x{p.width}"}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", nargs="+", default=["tiny", "small", "paper"])
    ap.add_argument("--phases", nargs="+", default=["infer", "train"])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--paper-train-reps", type=int, default=1, help="training repetitions for the paper preset")
    ap.add_argument("--threads", nargs="+", type=int, default=[1], help="torch thread counts to compare")
    ap.add_argument("--rounds", type=int, default=1, help="alternations of the thread settings")
    ap.add_argument("--out", default="bench/out/df_speed.json")
    ap.add_argument("--child", nargs=2, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(_run_phase(a.child[0], a.child[1], a.reps, a.threads[0])))
        return 0
    results = []
    for preset in a.presets:
        for phase in a.phases:
            reps = a.paper_train_reps if (preset == "paper" and phase == "train") else a.reps
            for rnd in range(a.rounds):
                for threads in a.threads:
                    t = time.time()
                    r = subprocess.run([sys.executable, __file__, "--child", preset, phase,
                                        "--reps", str(reps), "--threads", str(threads)], capture_output=True, text=True)
                    if r.returncode:
                        print(r.stderr[-3000:], file=sys.stderr)
                        results.append({"preset": preset, "phase": phase, "torch_threads": threads,
                                        "error": r.stderr.strip().splitlines()[-1]})
                    else:
                        results.append(json.loads(r.stdout.strip().splitlines()[-1]))
                    results[-1].update(round=rnd, wall_s=round(time.time() - t, 1))
                    print(json.dumps(results[-1]), flush=True)
    from pathlib import Path
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
