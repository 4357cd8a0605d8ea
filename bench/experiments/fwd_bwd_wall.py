"""Wall time of one rasterization() forward and its backward on a bench scene, medians of
``--calls`` calls after two warm-ups, one torch thread: the figure to compare two trees with
(``run_tree.py OLD_TREE bench/experiments/fwd_bwd_wall.py --scene B`` against this tree, alternating).

    python bench/experiments/fwd_bwd_wall.py --scene A|B|N [--calls 6]

Scenes: A and B of :mod:`clsplat.bench.scenes`, or a number N for scene A's generator at N
Gaussians. Every parameter requires grad; the loss is sum(render * w) with fixed random w.
"""
from __future__ import annotations

import argparse
import statistics
import time

import clsplat  # first: the thread and allocator defaults go in before torch loads
import torch

from clsplat.bench import scenes as S


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="A")
    ap.add_argument("--calls", type=int, default=6)
    a = ap.parse_args()
    torch.set_num_threads(1)
    sc = {"A": S.scene_a, "B": S.scene_b}.get(a.scene, lambda: S.random_frustum_scene(int(a.scene)))()
    args = S.render_args(sc)
    for k in ("means", "quats", "scales", "opacities", "colors"):
        args[k] = args[k].clone().requires_grad_()
    w = torch.rand(int(sc["viewmats"].shape[0]), sc["height"], sc["width"], 3,
                   generator=torch.Generator().manual_seed(1))
    fwd, bwd = [], []
    for r in range(a.calls + 2):
        t0 = time.perf_counter()
        out = clsplat.rasterization(**args)[0]
        t1 = time.perf_counter()
        (out * w).sum().backward()
        t2 = time.perf_counter()
        if r >= 2:
            fwd.append(1e3 * (t1 - t0))
            bwd.append(1e3 * (t2 - t1))
    print(f"{a.scene} fwd {statistics.median(fwd):.1f} bwd {statistics.median(bwd):.1f} ms "
          f"(clsplat from {clsplat.__file__})")


if __name__ == "__main__":
    main()
