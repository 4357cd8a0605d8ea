"""DrivingForward ``eval`` on a PandaSet-format sequence (the real-data path, without real data).

No real PandaSet sequence is available on the development machine, so this writes one with
clsplat's own PandaSet writer (:func:`clsplat.data.write_pandaset`) from a held-out synthetic
street with simulated LiDAR (test-split street ``--street``: no training street, and not one of
the synthetic evaluation's streets 0..7), then runs
``clsplat eval drivingforward --data pandaset:DIR`` on it. The PandaSet folder has no depth maps:
depth is scored against the LiDAR sweep projected into each camera, as on real data; there is no
oracle-depth baseline for the same reason. With ``--write-only`` it only writes the folder.

    nice -n 10 .venv/bin/python bench/experiments/df_pandaset_eval.py \\
        --checkpoint bench/out/df_small/checkpoint.pt --seq bench/out/df_pandaset/001 \\
        --out bench/out/df_small/eval_pandaset
"""
from __future__ import annotations

import argparse
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", default="bench/out/df_small/checkpoint.pt")
    p.add_argument("--seq", default="bench/out/df_pandaset/001", help="PandaSet-format folder (written if absent)")
    p.add_argument("--out", default="bench/out/df_small/eval_pandaset")
    p.add_argument("--frames", type=int, default=30, help="frames of the written sequence (last 20%%: test split)")
    p.add_argument("--height", type=int, default=64)
    p.add_argument("--width", type=int, default=112)
    p.add_argument("--street", type=int, default=100, help="held-out synthetic street of the written sequence")
    p.add_argument("--write-only", action="store_true")
    a = p.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    seq_dir = Path(a.seq)
    if not (seq_dir / "camera").is_dir():
        from clsplat.data import write_pandaset
        from clsplat.models.common.data import parse_data

        seq = parse_data("synthetic").sequence(a.street, num_frames=a.frames, height=a.height, width=a.width,
                                               split="test", lidar=True, dt=0.1)
        write_pandaset(seq, seq_dir)
        print(f"wrote {seq_dir} ({a.frames} frames, {a.height}x{a.width}, held-out street {a.street})", flush=True)
    if a.write_only:
        return 0
    from clsplat.models.common.data import TRAIN_SHARE
    from clsplat.models.drivingforward.cli import evaluate

    n_test = a.frames - int(round(a.frames * TRAIN_SHARE))
    return evaluate(["--checkpoint", a.checkpoint, "--data", f"pandaset:{seq_dir}", "--num-scenes",
                     str(max(1, n_test - 2)), "--out", a.out])


if __name__ == "__main__":
    raise SystemExit(main())
