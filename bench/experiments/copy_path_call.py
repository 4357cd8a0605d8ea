"""One process: scene S (A, B or a Gaussian count) rendered forward + backward on this machine's default
device, medians of 5 calls after 2: wall and calling-thread CPU ms, and a hash of the image and the
means' gradient. With CLSPLAT_HOST_MEMORY=copy on PoCL it measures the copying path GPUs take:

    CLSPLAT_HOST_MEMORY=copy .venv/bin/python bench/experiments/copy_path_call.py A
    CLSPLAT_HOST_MEMORY=copy .venv/bin/python bench/experiments/run_tree.py OLD_TREE bench/experiments/copy_path_call.py A
"""
from __future__ import annotations

import hashlib
import json
import statistics
import sys
import time

import torch

import clsplat
from clsplat.bench import scenes
from clsplat.bench.scenes import render_args

PARAMS = ("means", "quats", "scales", "opacities", "colors")


def main() -> None:
    torch.set_num_threads(1)
    name = sys.argv[1]
    sc = ({"A": scenes.scene_a, "B": scenes.scene_b}[name]() if name in ("A", "B")
          else scenes.random_frustum_scene(int(name), 640, 352, seed=0))
    args = render_args(sc)
    for k in PARAMS:
        args[k] = args[k].clone().requires_grad_()

    def once() -> str:
        img, alpha, _ = clsplat.rasterization(**args, packed=True)
        (img.sum() + alpha.sum()).backward()
        h = hashlib.sha1(img.detach().numpy().tobytes() + args["means"].grad.numpy().tobytes()).hexdigest()[:10]
        for k in PARAMS:
            args[k].grad = None
        return h

    for _ in range(2):
        h = once()
    wall, cpu = [], []
    for _ in range(5):
        t0, c0 = time.perf_counter(), time.thread_time()
        once()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.thread_time() - c0)
    print(json.dumps({"wall_ms": 1e3 * statistics.median(wall), "cpu_ms": 1e3 * statistics.median(cpu), "hash": h}))


if __name__ == "__main__":
    main()
