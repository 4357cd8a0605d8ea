"""DrivingForward training data: what a sample costs ray-cast on the fly against read from the
synthetic-street cache (``bench/notes/synthetic_data.md``, issue 17, "Data share of a step").

For each supersample factor, ``--samples`` training samples (frames t-1, t, t+1 of six cameras at
the preset's size, :func:`~clsplat.models.drivingforward.data.load_triplet`) are loaded three ways:
generated (``--data synthetic``), generated and written to a fresh cache (a cache miss), and read
back from it (a hit). Prints the median seconds of each; the caller puts them beside a training
step's median ``time_s`` from a run's ``log.jsonl``.

    .venv/bin/python bench/experiments/df_data.py --preset small --supersample 1 3 --samples 3
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time


def measure(preset_name: str, supersample: int, samples: int, first: int = 500_000) -> dict[str, float]:
    """Median seconds per sample: generated, cache miss (generate + write), cache hit (read)."""
    from clsplat.models.common.data import parse_data
    from clsplat.models.common.presets import get_preset
    from clsplat.models.drivingforward.data import load_triplet

    p = get_preset("drivingforward", preset_name).replace(supersample=supersample)
    out: dict[str, list[float]] = {"generated": [], "miss": [], "hit": []}
    with tempfile.TemporaryDirectory() as d:
        plain, cached = parse_data("synthetic"), parse_data(f"synthetic-cache:{d}")
        for i in range(first, first + samples):
            for key, src in (("generated", plain), ("miss", cached), ("hit", cached)):
                t0 = time.perf_counter()
                load_triplet(src, i, p, "train")
                out[key].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in out.items()}


def main(argv: list[str] | None = None) -> int:
    import torch

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="small")
    p.add_argument("--supersample", type=int, nargs="+", default=[1, 3])
    p.add_argument("--samples", type=int, default=3)
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    print("| supersample | generated (s) | cache miss: generate + write (s) | cache hit: read (s) |")
    print("|---|---|---|---|")
    for s in a.supersample:
        m = measure(a.preset, s, a.samples)
        print(f"| {s} | {m['generated']:.3f} | {m['miss']:.3f} | {m['hit']:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
