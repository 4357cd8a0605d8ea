"""AutoSplat's load stage timed and profiled: reading the sequence, then preparing it.

    python bench/experiments/autosplat_load.py --data pandaset:PATH [--cameras A B ...]
        [--frames 0:40] [--scale 0.5] [--profile 15]

The load stage is what ``clsplat train autosplat`` reports as ``load_seconds``: the sequence
read and resized (:func:`clsplat.models.autosplat.data.load_sequence`) and the per-frame
tensors prepared (:func:`clsplat.models.autosplat.data.prepare_data`: images, LiDAR-labelled
pixel classes, the foreground mask of tracked boxes). Prints one JSON line with the seconds of
each part and, with ``--profile N``, the N cProfile entries with the most cumulative time.
"""
from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import time

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python bench/experiments/autosplat_load.py", description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="synthetic, pandaset:PATH or nuscenes:PATH")
    p.add_argument("--cameras", nargs="+", default=None)
    p.add_argument("--frames", default=None, help="A:B")
    p.add_argument("--scale", type=float, default=0.25)
    p.add_argument("--holdout", type=int, default=8)
    p.add_argument("--profile", type=int, default=0, help="print this many cProfile entries")
    a = p.parse_args(argv)
    try:
        from clsplat.models.autosplat.data import load_sequence, parse_frames, prepare_data
    except ImportError:  # trees before the loaders moved to data.py (to time the branch point)
        from clsplat.models.autosplat.cli import load_sequence, parse_frames
        from clsplat.models.autosplat.trainer import prepare_data

    prof = cProfile.Profile() if a.profile else None
    if prof is not None:
        prof.enable()
    t0 = time.perf_counter()
    seq = load_sequence(a.data, a.cameras, parse_frames(a.frames), a.scale)
    t1 = time.perf_counter()
    data = prepare_data(seq, a.cameras, a.holdout)
    t2 = time.perf_counter()
    if prof is not None:
        prof.disable()
    print(json.dumps({"data": a.data, "frames": len(seq.frames), "cameras": data.cameras,
                      "size": f"{data.width}x{data.height}", "read_s": round(t1 - t0, 2),
                      "prepare_s": round(t2 - t1, 2), "load_s": round(t2 - t0, 2)}), flush=True)
    if prof is not None:
        s = io.StringIO()
        pstats.Stats(prof, stream=s).sort_stats("cumtime").print_stats(a.profile)
        print(s.getvalue())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
