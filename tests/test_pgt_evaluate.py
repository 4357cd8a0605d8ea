"""PGT evaluation helpers (models/pgt/evaluate.py): the Pareto front of the budget curve and its
figure. (The evaluation itself runs end to end in test_pgt_cli.py.)"""
from __future__ import annotations

from clsplat.models.pgt.evaluate import pareto_front, plot_budget


def test_pareto_front_keeps_only_undominated_points():
    pts = [(10.0, 20.0), (5.0, 18.0), (5.0, 15.0), (7.0, 17.0), (1.0, 12.0), (20.0, 19.0), (2.0, 12.0)]
    # (5, 15) loses to (5, 18) at equal cost; (7, 17) to the cheaper (5, 18); (20, 19) to (10, 20);
    # (2, 12) to the cheaper (1, 12) of equal quality
    assert pareto_front(pts) == [(1.0, 12.0), (5.0, 18.0), (10.0, 20.0)]
    assert pareto_front([]) == []


def test_budget_figure_is_written(tmp_path):
    rows = [{"method": m, "budget": k, "n_gaussians": 1000 * k, "psnr": 20 * k + d, "ssim": 0.5,
             "render_ms": 10 * k + 1} for m, d in (("finetuned", 1.0), ("opacity", 0.0), ("random", 0.5))
            for k in (1.0, 0.5, 0.1)]
    png = plot_budget(rows, tmp_path / "budget.png")
    assert png.stat().st_size > 10_000
