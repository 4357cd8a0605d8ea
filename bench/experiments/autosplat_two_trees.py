"""One AutoSplat training command run by two source trees side by side, timed whole and per stage (issue 36:
"the ``small`` preset's wall time on the six-camera, 40-frame quarter-scale protocol stays within 1.25x").

A *tree* is a ``git archive`` of a commit with the three links an editable install maps
(``clsplat/kernels -> ../kernels``, ``clsplat/bench -> ../bench``, ``clsplat/models -> ../models``), so that
with the tree first on ``PYTHONPATH`` its own Python and its own OpenCL kernels load (the venv's editable
finder only answers what the path does not). The venv's installed entry points name today's modules
(``clsplat.models.registry`` since a7a0ea9), so the command is run through ``cli`` below, which registers
the tree's own ``setup.cfg`` commands and then calls the tree's ``clsplat.cli.console`` (what the
``clsplat`` script does)::

    git -C /work/main archive f1f6395 | tar -x -C /work/old    # likewise HEAD into /work/cur
    (cd /work/old/clsplat && ln -s ../kernels kernels && ln -s ../bench bench && ln -s ../models models)
    .venv/bin/python bench/experiments/autosplat_two_trees.py run --tree old=/work/old --tree cur=/work/cur \\
        --prefix /work/runs/i36s9_ -- train autosplat --data pandaset:DIR --preset small --threads 1 \\
        --no-progress --seed 6
    .venv/bin/python bench/experiments/autosplat_two_trees.py table --prefix /work/runs/i36s9_ old cur

``run`` starts both commands at once (``--out PREFIX<name>`` appended), each under ``/usr/bin/time -v -o
PREFIX<name>.time``, stdout and stderr in ``PREFIX<name>.log``; every ``--every`` seconds it appends to
``PREFIX<names>.cpu`` one line per live run: ``HH:MM:SS name ticks step stage`` (the process's user +
system CPU in clock ticks from ``/proc/PID/stat``, its log.jsonl's last step and stage, ``- -`` before the
first). ``table`` reads the runs' ``metrics.json`` (held-out PSNR / SSIM, object PSNR, seconds per stage),
the time files (the whole command's wall and CPU seconds) and the samples (CPU seconds per stage: the
ticks interpolated at each stage's first and last step; a stage boundary is known to one sampling
interval), and prints one table per figure with the ratio of the last tree to the first.
"""
from __future__ import annotations

import argparse
import configparser
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

TICKS = os.sysconf("SC_CLK_TCK")
STAGES = ("bg_phase1", "bg_phase2", "foreground", "fusion")


def cli(argv: list[str]) -> int:
    """``clsplat ARGV`` with the commands of the tree that ``clsplat`` is imported from (its setup.cfg)."""
    import clsplat
    import clsplat.cli as ccli
    from importlib.metadata import EntryPoint

    tree = Path(clsplat.__file__).resolve().parent.parent
    cp = configparser.ConfigParser()
    cp.read(tree / "setup.cfg")
    eps = {}
    for line in cp["options.entry_points"]["clsplat.commands"].strip().splitlines():
        if "=" in line and not line.strip().startswith("#"):
            name, value = (s.strip() for s in line.split("=", 1))
            eps[name] = EntryPoint(name, value, "clsplat.commands")
    ccli.registered_commands = lambda: dict(eps)
    import clsplat.kernels
    print(f"[two_trees] clsplat {clsplat.__file__}, kernels {[os.path.realpath(p) for p in clsplat.kernels.__path__]}",
          file=sys.stderr, flush=True)
    sys.argv = ["clsplat", *argv]
    return int(ccli.console(argv) or 0)


def _last_step(run: Path) -> str:
    """``step stage`` of the last line of ``run``'s log.jsonl (staging or final), ``- -`` without one."""
    for log in (run / ".staging" / "log.jsonl", run / "log.jsonl"):
        try:
            with open(log, "rb") as f:
                f.seek(max(0, os.path.getsize(log) - 4096))
                last = f.read().decode(errors="replace").strip().splitlines()[-1]
            d = json.loads(last)
            return f"{d['step']} {d['stage']}"
        except (OSError, IndexError, ValueError, KeyError):
            continue
    return "- -"


def _child(pid: int) -> int | None:
    """The first child of ``pid`` (the Python process under /usr/bin/time), None while there is none."""
    try:
        kids = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    except OSError:
        return None
    return int(kids[0]) if kids else None


def run(trees: dict[str, str], prefix: str, args: list[str], every: float) -> None:
    """Start ``args`` once per tree at the same time and sample their CPU until both have ended."""
    me = Path(__file__).resolve()
    procs = {}
    for name, tree in trees.items():
        env = dict(os.environ, PYTHONPATH=os.path.abspath(tree))
        cmd = ["/usr/bin/time", "-v", "-o", f"{prefix}{name}.time", sys.executable, str(me), "cli", *args,
               "--out", f"{prefix}{name}"]
        log = open(f"{prefix}{name}.log", "w")
        procs[name] = (subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, cwd="/"), log)
    with open(f"{prefix}{'_'.join(trees)}.cpu", "a") as out:
        while any(p.poll() is None for p, _ in procs.values()):
            for name, (p, _) in procs.items():
                c = _child(p.pid) if p.poll() is None else None
                try:
                    f = Path(f"/proc/{c}/stat").read_text().rsplit(")", 1)[1].split() if c else None
                except OSError:
                    f = None
                if f:   # fields after the name: utime and stime are the 12th and 13th
                    out.write(f"{time.strftime('%H:%M:%S')} {name} {int(f[11]) + int(f[12])} "
                              f"{_last_step(Path(prefix + name))}\n")
            out.flush()
            time.sleep(every)
    for name, (p, log) in procs.items():
        log.close()
        print(f"{name}: exit {p.returncode}")


def _time_file(path: Path) -> dict[str, float] | None:
    """Wall and CPU seconds (user + system) of a ``/usr/bin/time -v`` report; None before it is written."""
    text = path.read_text()
    if "User time (seconds)" not in text:
        return None
    user = float(re.search(r"User time \(seconds\): ([\d.]+)", text).group(1))
    system = float(re.search(r"System time \(seconds\): ([\d.]+)", text).group(1))
    wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): ([\d:.]+)", text).group(1)
    secs = sum(float(x) * 60 ** i for i, x in enumerate(reversed(wall.split(":"))))
    return {"wall": secs, "cpu": user + system, "user": user, "system": system,
            "max_rss_mb": int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", text).group(1)) / 1024}


def _ticks_at(samples: list[tuple[int, int]], step: float) -> float:
    """Process ticks when the run reached ``step``: linear between the samples around it (``samples``
    [(step, ticks)] in time order, step 0 before the first logged step; the last sample's ticks past it)."""
    if not samples:
        raise ValueError("samples: no sample of this run")
    for i, (s, t) in enumerate(samples):
        if s >= step:
            if i == 0:
                return float(t)
            s0, t0 = samples[i - 1]
            return t0 + (t - t0) * (step - s0) / max(s - s0, 1e-9)
    return float(samples[-1][1])


def _run_rows(prefix: str, name: str, lines: list[list[str]]) -> dict:
    """One run's figures: finished (``metrics.json``) or not (its staging log only)."""
    run = Path(prefix + name)
    done = (run / "metrics.json").exists()
    m = json.loads((run / "metrics.json").read_text()) if done else {}
    log = run / "log.jsonl" if (run / "log.jsonl").exists() else run / ".staging" / "log.jsonl"
    steps = [json.loads(ln) for ln in log.read_text().splitlines() if ln.strip()]
    bounds: dict[str, tuple[int, int]] = {}
    wall: dict[str, list[float]] = {}
    for r in steps:
        a, _ = bounds.get(r["stage"], (r["step"], r["step"]))
        bounds[r["stage"]] = (a, r["step"])
        wall.setdefault(r["stage"], []).append(r["time_s"])
    seen, samples = 0, []
    for ln in lines:   # HH:MM:SS name ticks step stage
        if ln[1] == name:
            seen = int(ln[3]) if ln[3] != "-" else seen
            samples.append((seen, int(ln[2])))
    tf = Path(f"{prefix}{name}.time")
    tf = tf if tf.exists() else Path(f"{prefix}{name}.log")
    t = _time_file(tf) if done and tf.exists() else None
    a = m.get("all", {})
    return {"finished": done, "time": t, "bounds": bounds, "step_wall": wall, "samples": samples,
            "stage_wall": m.get("seconds_per_stage", {}), "psnr": a.get("psnr"), "ssim": a.get("ssim"),
            "psnr_objects": a.get("psnr_objects"),
            "per_class": {k: v.get("psnr") for k, v in (m.get("objects") or {}).get("per_class", {}).items()},
            "gaussians": m.get("gaussians", {})}


def table(prefix: str, names: list[str], samples_files: list[str] | None = None) -> None:
    """Print the runs' figures and, for each stage over the steps both runs reached, wall seconds (the
    log's per-step times) and CPU seconds (the samples) with the last run over the first; finished runs
    also their whole command (the time report ``PREFIX<NAME>.time``, else the end of ``PREFIX<NAME>.log``)
    and ``metrics.json``'s seconds per stage. The samples come from ``samples_files``, else every
    ``PREFIX*.cpu``."""
    cpu_files = [Path(f) for f in samples_files] if samples_files else \
        list(Path(prefix).parent.glob(Path(prefix).name + "*.cpu"))
    lines = [ln.split() for f in cpu_files for ln in f.read_text().splitlines() if len(ln.split()) == 5]
    rows = {name: _run_rows(prefix, name, lines) for name in names}
    for name, r in rows.items():
        print(f"{name}: finished {r['finished']}, stages reached {r['bounds']}, PSNR {r['psnr']} SSIM {r['ssim']} "
              f"objects {r['psnr_objects']} per class {r['per_class']} gaussians {r['gaussians']}")
        if r["time"]:
            print(f"  whole command: {json.dumps(r['time'])}; seconds per stage {json.dumps(r['stage_wall'])}")
        if r["samples"]:
            print(f"  CPU before the first step (load, init): {_ticks_at(r['samples'], 0.5) / TICKS:.0f} s")
    first, last = names[0], names[-1]
    rf, rl = rows[first], rows[last]
    print(f"\n{last} / {first}, per stage over the steps both reached:")
    print("| stage | steps | wall s | wall ratio | CPU s | CPU ratio |")
    print("|---|---|---|---|---|---|")
    for st in STAGES:
        if st not in rf["bounds"] or st not in rl["bounds"]:
            continue
        n = min(b - a + 1 for a, b in (rf["bounds"][st], rl["bounds"][st]))
        w = [sum(r["step_wall"][st][:n]) for r in (rf, rl)]
        c = []
        for r in (rf, rl):
            a = r["bounds"][st][0]
            c.append((_ticks_at(r["samples"], a - 1 + n) - _ticks_at(r["samples"], a - 0.5)) / TICKS
                     if r["samples"] else float("nan"))
        print(f"| {st} | {n} | {w[1]:.0f} / {w[0]:.0f} | {w[1] / w[0]:.3f} | {c[1]:.0f} / {c[0]:.0f} | "
              f"{c[1] / c[0]:.3f} |")
    if rf["time"] and rl["time"]:
        for k in ("wall", "cpu"):
            print(f"whole command {k}: {rl['time'][k]:.0f} / {rf['time'][k]:.0f} s = "
                  f"{rl['time'][k] / rf['time'][k]:.3f}")
        if rf["samples"] and rl["samples"]:
            for name, r in ((first, rf), (last, rl)):
                end = max(b for _, b in r["bounds"].values())
                print(f"{name}: CPU after the last step (eval, writing): "
                      f"{r['time']['cpu'] - _ticks_at(r['samples'], end) / TICKS:.0f} s")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="start the command once per tree, side by side, and sample their CPU")
    r.add_argument("--tree", action="append", required=True, help="NAME=PATH (a tree as in the docstring)")
    r.add_argument("--prefix", required=True, help="run folders, logs and samples are PREFIX<NAME>...")
    r.add_argument("--every", type=float, default=15.0, help="seconds between CPU samples")
    r.add_argument("args", nargs=argparse.REMAINDER, help="-- then clsplat's arguments (without --out)")
    t = sub.add_parser("table", help="the runs' figures and the ratio of the last tree to the first")
    t.add_argument("--prefix", required=True)
    t.add_argument("names", nargs="+")
    t.add_argument("--samples", nargs="+", help="CPU sample files (default: PREFIX*.cpu)")
    if sys.argv[1:2] == ["cli"]:
        sys.exit(cli(sys.argv[2:]))
    a = p.parse_args()
    if a.cmd == "run":
        trees = {}
        for spec in a.tree:
            name, sep, path = spec.partition("=")
            if not sep or not name or not (Path(path) / "clsplat" / "kernels").is_dir():
                p.error(f"--tree: expected NAME=PATH of a tree with clsplat/kernels, got {spec!r}")
            trees[name] = path
        args = a.args[1:] if a.args[:1] == ["--"] else a.args
        if not args or "--out" in args:
            p.error("args: expected clsplat's arguments after --, without --out (PREFIX<NAME> is the run)")
        if not a.every > 0:
            p.error(f"--every: expected seconds > 0, got {a.every}")
        run(trees, a.prefix, args, a.every)
    else:
        table(a.prefix, a.names, a.samples)


if __name__ == "__main__":
    main()
