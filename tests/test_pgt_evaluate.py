"""PGT evaluation helpers (models/pgt/evaluate.py): the Pareto front of the budget curve and its
figure. (The evaluation itself runs end to end in test_pgt_cli.py.)"""
from __future__ import annotations

import numpy as np

from clsplat.models.pgt.evaluate import METHODS, pareto_front, plot_budget


def test_pareto_front_keeps_only_undominated_points():
    pts = [(10.0, 20.0), (5.0, 18.0), (5.0, 15.0), (7.0, 17.0), (1.0, 12.0), (20.0, 19.0), (2.0, 12.0)]
    # (5, 15) loses to (5, 18) at equal cost; (7, 17) to the cheaper (5, 18); (20, 19) to (10, 20);
    # (2, 12) to the cheaper (1, 12) of equal quality
    assert pareto_front(pts) == [(1.0, 12.0), (5.0, 18.0), (10.0, 20.0)]
    assert pareto_front([]) == []


def _pixels_near(img, rgb_hex: str, tol: float = 0.06) -> int:
    rgb = np.array([int(rgb_hex[i:i + 2], 16) / 255 for i in (1, 3, 5)], dtype=np.float32)
    return int((np.abs(img - rgb).max(axis=-1) < tol).sum())


def test_budget_figure_draws_one_curve_per_method(tmp_path):
    """Both panels are drawn (the figure's size) and each method's curve is there in its own
    colour (matplotlib's cycle C0, C1, C2 in METHODS order); a method without rows draws none."""
    from clsplat.io.images import read_image

    rows = [{"method": m, "budget": k, "n_gaussians": 1000 * k, "psnr": 20 * k + d, "ssim": 0.5,
             "render_ms": 10 * k + 1} for m, d in zip(METHODS, (1.0, 0.0, 0.5)) for k in (1.0, 0.5, 0.1)]
    img = read_image(plot_budget(rows, tmp_path / "budget.png"))
    assert img.shape == (440, 1210, 3)
    colours = ("#1f77b4", "#ff7f0e", "#2ca02c")
    assert all(_pixels_near(img, c) > 100 for c in colours), [_pixels_near(img, c) for c in colours]
    only_first = read_image(plot_budget([r for r in rows if r["method"] == METHODS[0]],
                                        tmp_path / "first.png"))
    assert _pixels_near(only_first, colours[0]) > 100 and _pixels_near(only_first, colours[1]) < 10
