"""Upper bound for issue 36's "pedestrian shape" candidate (bench/notes/autosplat_moving_objects.md,
helper s5): `clsplat train autosplat ARGS` with every box-template object (on the generated busy
street: the pedestrians; cars and trucks take the car template) started from points on the
generator's own body parts (legs, torso, head: the proportions of
``clsplat.data.synthetic.street.StreetScene._pedestrian_parts``) instead of its box's surface.
This is ground truth put into the initialisation, so it is a bound only (as exact boxes are), never a
preset: it says how much of the pedestrians' error comes from starting from, and keeping, a box
shell around a body that fills half of it.

    PYTHONPATH=<tree> .venv/bin/python bench/experiments/autosplat_body_template.py --preset demo ... --out RUN
"""
from __future__ import annotations

import sys
from typing import Sequence

import numpy as np


def body_parts(size: Sequence[float]) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(centre, half extents)`` of the generator's pedestrian parts in the box frame of ``size`` (L, W, H)."""
    L, W, H = (float(x) for x in size)
    leg_h, torso_h, head_h = 0.46 * H, 0.36 * H, 0.16 * H
    parts = [([0.0, sy * W / 4, -H / 2 + leg_h / 2], [0.3 * L, 0.18 * W, leg_h / 2]) for sy in (-1, 1)]
    parts.append(([0.0, 0.0, -H / 2 + leg_h + torso_h / 2], [0.4 * L, 0.5 * W, torso_h / 2]))
    parts.append(([0.0, 0.0, H / 2 - head_h / 2], [0.2 * L, 0.18 * W, head_h / 2]))
    return [(np.asarray(c), np.asarray(h)) for c, h in parts]


def body_surface_template(size: Sequence[float], n: int, rng: np.random.Generator) -> np.ndarray:
    """``[n, 3]`` points on the surfaces of the body parts of ``size``, each part by its surface area."""
    from clsplat.models.autosplat.objects import _box_surface
    parts = body_parts(size)
    area = np.array([h[0] * h[1] + h[1] * h[2] + h[0] * h[2] for _, h in parts])
    k = rng.multinomial(n, area / area.sum())
    return np.concatenate([_box_surface(int(m), c, h, rng, skip_bottom=False) for (c, h), m in zip(parts, k) if m]
                          or [np.zeros((0, 3))])


def main(argv: list[str]) -> int:
    import clsplat.models.autosplat.objects as objects
    from clsplat.models.autosplat.cli import train
    objects.box_surface_template = body_surface_template
    return train(argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
