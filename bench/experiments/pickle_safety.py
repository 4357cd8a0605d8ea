"""Cost of the safe (allow-listed) unpickler against the trusting one on a PandaSet-sized sequence.

Figure: the "Safe by default (issue 23)" table in bench/notes/hardening.md (summary: bench/RESULTS.md). Command:

    nice -n 10 .venv/bin/python bench/experiments/pickle_safety.py --frames 80 --points 100000 --repeats 3

Writes ``--frames`` LiDAR sweeps of ``--points`` points each in PandaSet's format (a gzip-pickled
DataFrame with float64 x, y, z, i, t and int64 d, as :func:`clsplat.data.write_pandaset` writes
them) into a temporary folder, then reads the whole sequence with each reader, interleaved, and
prints the median seconds per sequence of:

* ``trusting``      ``pd.read_pickle(path, compression="gzip")`` (what ``safe_pickle=False`` was);
* ``safe_before``   the previous safe path: pandas' pure-Python compat unpickler with the allow-list,
                    reading straight from the gzip stream;
* ``safe_now``      :func:`clsplat.data.files.read_pickled_dataframe` (default, safe);
* ``trusting_now``  ``read_pickled_dataframe(..., safe=False)``;

and where the time goes: ``gunzip`` (decompression alone, through the bounded reader) and ``unpickle_c`` /
``unpickle_py`` (the allow-listed C and pure-Python unpickler on the decompressed bytes),
``unpickle_c_trusting`` (``pickle.loads``). Each reader's median wall time and median CPU time of
this process (``time.process_time``: all readers are single-threaded, and CPU time is far less
disturbed than wall time by other jobs on a shared machine) over ``--repeats`` interleaved rounds.
"""
from __future__ import annotations

import argparse
import gzip
import io
import pickle
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np


def write_sweeps(folder: Path, frames: int, points: int, seed: int = 0) -> list[Path]:
    import pandas as pd

    rng = np.random.default_rng(seed)
    paths = []
    for k in range(frames):
        df = pd.DataFrame({"x": rng.normal(0, 20, points), "y": rng.normal(0, 20, points),
                           "z": rng.normal(0, 2, points), "i": rng.integers(0, 256, points).astype(np.float64),
                           "t": np.full(points, 0.1 * k), "d": rng.integers(0, 2, points)})
        p = folder / f"{k:02d}.pkl.gz"
        df.to_pickle(p, compression="gzip")
        paths.append(p)
    return paths


def main(argv: list[str] | None = None) -> None:
    import pandas as pd

    from clsplat.data import files

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--points", type=int, default=100_000)
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        paths = write_sweeps(Path(tmp), a.frames, a.points)
        size = sum(p.stat().st_size for p in paths)
        print(f"{a.frames} sweeps x {a.points} points, {size / 2**20:.1f} MiB compressed")
        raw = [gzip.decompress(p.read_bytes()) for p in paths]
        print(f"{sum(map(len, raw)) / 2**20:.1f} MiB decompressed")
        compat = files._safe_compat_unpickler()

        def safe_before(p):
            with gzip.open(p, "rb") as fh:
                return compat(fh).load()

        def gunzip(p):
            with gzip.open(p, "rb") as fh:
                r = files._BoundedReader(fh, files.MAX_PICKLE_BYTES, p)
                while r.read(1 << 20):
                    pass

        readers = {
            "trusting": lambda p, i: pd.read_pickle(p, compression="gzip"),
            "safe_before": lambda p, i: safe_before(p),
            "safe_now": lambda p, i: files.read_pickled_dataframe(p),
            "trusting_now": lambda p, i: files.read_pickled_dataframe(p, safe=False),
            "gunzip": lambda p, i: gunzip(p),
            "unpickle_c": lambda p, i: files._SafeUnpickler(io.BytesIO(raw[i])).load(),
            "unpickle_py": lambda p, i: compat(io.BytesIO(raw[i])).load(),
            "unpickle_c_trusting": lambda p, i: pickle.loads(raw[i]),
        }
        ref = pd.read_pickle(paths[0], compression="gzip")
        for name, fn in readers.items():
            if name.startswith(("safe", "trusting", "unpickle")):
                assert fn(paths[0], 0).equals(ref), name
        times: dict[str, list[float]] = {k: [] for k in readers}
        cpu: dict[str, list[float]] = {k: [] for k in readers}
        for _ in range(a.repeats):
            for name, fn in readers.items():
                t0, c0 = time.perf_counter(), time.process_time()
                for i, p in enumerate(paths):
                    fn(p, i)
                cpu[name].append(time.process_time() - c0)
                times[name].append(time.perf_counter() - t0)
        base, cbase = statistics.median(times["trusting"]), statistics.median(cpu["trusting"])
        print(f"{'reader':22s} {'wall s':>7s} {'ratio':>6s} {'CPU s':>7s} {'ratio':>6s}   wall of each run")
        for name in readers:
            m, c = statistics.median(times[name]), statistics.median(cpu[name])
            print(f"{name:22s} {m:7.3f} {m / base:5.2f}x {c:7.3f} {c / cbase:5.2f}x   "
                  + " ".join(f"{t:.3f}" for t in times[name]))

if __name__ == "__main__":
    main()
