"""Fill a street cache's kept geometric fits ahead of a ``--pose geometric`` run (issue 32).

No figure: a run of ``small --pose geometric`` pays ~5-10 CPU s a step for a street whose fit is not
yet kept beside it, and ~1.4 s once it is (:mod:`clsplat.models.drivingforward.geometric_pose`).
Window ``i`` of a run seeded ``S`` is street ``S + i``, so one pass over the streets a set of runs
will draw serves them all. This script computes those fits in a chosen order (``--reverse`` from
the last), so that a second process fills the cache from the other end while a run trains forward;
a fit already kept is read back and skipped, so it can be stopped and restarted at any time.

    python bench/experiments/df_fit_cache_warm.py --cache /work/cache/df --first 0 --last 602 --reverse \
        --set "geometric_size=(176, 320)" --set geometric_keep=0.75 --set geometric_max_yaw_rate=30

(``--first``/``--last``: train windows of a run seeded 0; ``--seed S`` names the windows of seed S.)
"""
from __future__ import annotations

import argparse
import time

import torch

from clsplat.models.common.data import parse_data
from clsplat.models.common.presets import apply_sets, get_preset
from clsplat.models.drivingforward.data import DEFAULT_WORLD
from clsplat.models.drivingforward.geometric_pose import load_window_motions
import clsplat.models.drivingforward.presets  # noqa: F401  (registers the family's presets)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cache", required=True, help="the street cache folder of --data synthetic-cache:DIR")
    p.add_argument("--preset", default="small")
    p.add_argument("--set", action="append", default=[], help="preset overrides, as the train command's --set")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--first", type=int, required=True)
    p.add_argument("--last", type=int, required=True)
    p.add_argument("--reverse", action="store_true")
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    preset = apply_sets(get_preset("drivingforward", a.preset), a.set, pose_source="geometric")
    # the train command's world (a cache street is keyed by its whole config: another world is another street)
    source = parse_data(f"synthetic-cache:{a.cache}", seed=a.seed, default_world=DEFAULT_WORLD)
    order = range(a.last, a.first - 1, -1) if a.reverse else range(a.first, a.last + 1)
    for i in order:
        t0 = time.perf_counter()
        load_window_motions(source, i, preset, "train")
        print(f"window {i}: {time.perf_counter() - t0:.1f} s", flush=True)


if __name__ == "__main__":
    main()
