"""Issue 18's budget pieces (models/pgt/budget.py, evaluate.py): the baselines keep exactly the
budget per view (random, opacity, grid, dedup) as does the stratified selection; the stratified
selection follows its density and spreads out; cross-view coverage finds the views that see a
point; the density target gives a redundant view low importance and a unique detail high; the
evaluation's coverage mask; the log-uniform κ schedule."""
from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from clsplat.models.pgt.budget import (cross_view_coverage, dedup_mask, density_target, grid_mask, hilbert_order,
                                       sample_kappa, stratified_mask)
from clsplat.models.pgt.evaluate import BASELINES, baseline_mask, covered_mask

H, W = 32, 48


def _plane_views(shifts=(0.0, 0.0), yaws=(0.0, 0.0), depth=10.0):
    """Cameras at x = shifts looking at a fronto-parallel plane ``depth`` m away, turned by ``yaws``
    (radians, about the y axis): their z-depth maps, intrinsics and poses."""
    V = len(shifts)
    f = 0.8 * W
    Ks = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]]).expand(V, 3, 3).clone()
    c2w = torch.eye(4).repeat(V, 1, 1)
    for v, (x, a) in enumerate(zip(shifts, yaws)):
        c, s = math.cos(a), math.sin(a)
        c2w[v, :3, :3] = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        c2w[v, 0, 3] = x
    depth = torch.full((V, H, W), depth)
    return depth, Ks, c2w


def test_hilbert_order_visits_every_pixel_once_through_neighbours():
    for h, w in ((32, 48), (8, 8), (5, 7), (64, 112)):
        o = hilbert_order(h, w)
        assert sorted(o.tolist()) == list(range(h * w))
    o = hilbert_order(16, 16)  # a square power of two: every step moves to a 4-neighbour
    y, x = o // 16, o % 16
    assert ((y[1:] - y[:-1]).abs() + (x[1:] - x[:-1]).abs()).eq(1).all()


@pytest.mark.parametrize("method", BASELINES)
def test_baselines_keep_exactly_the_budget_per_view(method):
    g = torch.Generator().manual_seed(0)
    depth, Ks, c2w = _plane_views((0.0, 0.3, 5.0))
    base = SimpleNamespace(opacities=torch.rand(3, H, W, generator=g), depth=depth)
    P = H * W
    for k in ([0, 0, 0], [1, 2, 3], [77, 5, 1000], [P // 20, P // 10, P // 2], [P - 1, P, 0], [P, P, P]):
        budgets = torch.tensor(k)
        keep = baseline_mask(method, base, budgets, Ks, c2w, torch.Generator().manual_seed(1))
        assert keep.dtype == torch.bool and keep.shape == (3, H, W)
        assert keep.sum(dim=(1, 2)).tolist() == k, (method, k)


def test_stratified_selection_is_exact_follows_the_density_and_spreads():
    g = torch.Generator().manual_seed(0)
    P = H * W
    dens = torch.rand(2, H, W, generator=g)
    for k in range(0, P + 1, 37):
        keep = stratified_mask(dens, torch.tensor([k, P - k]))
        assert keep.sum(dim=(1, 2)).tolist() == [k, P - k]
    # 4x the density on the right half: about 4x the picks there
    d = torch.ones(1, H, W)
    d[..., W // 2:] = 4.0
    keep = stratified_mask(d, torch.tensor([P // 10]))[0]
    left, right = int(keep[:, :W // 2].sum()), int(keep[:, W // 2:].sum())
    assert 3.5 < right / left < 4.5, (left, right)
    # uniform density: every 8x8 block gets its share (P/10 -> 6.4 per block) within +-3;
    # top-K of a noisy score or the plain raster order would not
    keep = stratified_mask(torch.ones(1, H, W), torch.tensor([P // 10]))[0]
    blocks = keep.reshape(H // 8, 8, W // 8, 8).sum(dim=(1, 3)).float()
    assert (blocks - 6.4).abs().max() <= 3.0, blocks
    # a pixel due more than one pick is capped: all of a tiny dense region is kept, the rest spread
    d = torch.full((1, H, W), 1e-3)
    d[0, :2, :2] = 1e6
    keep = stratified_mask(d, torch.tensor([100]))[0]
    assert keep[:2, :2].all() and int(keep.sum()) == 100


def test_grid_keeps_one_pixel_per_cell():
    keep = grid_mask(torch.tensor([H * W // 16]), H, W)[0]  # 4x4 cells, exactly as many as the budget
    cells = keep.reshape(H // 4, 4, W // 4, 4).sum(dim=(1, 3))
    assert cells.eq(1).all()
    assert keep[2::4, 2::4].all()  # the cells' centres


def test_cross_view_coverage_finds_the_views_that_see_a_point():
    # views 0 and 1: the same plane from 0.3 m apart (most points seen by both);
    # view 2 looks the other way (sees none of them)
    depth, Ks, c2w = _plane_views((0.0, 0.3, 0.0), (0.0, 0.0, math.pi))
    count, earlier = cross_view_coverage(depth, Ks, c2w)
    assert count[2].eq(1).all() and not earlier[2].any()
    shift_px = 0.3 * Ks[0, 0, 0] / 10.0  # how far the plane moves between views 0 and 1
    inner = slice(int(shift_px) + 2, W - int(shift_px) - 2)
    assert count[0][:, inner].eq(2).all() and count[1][:, inner].eq(2).all()
    assert not earlier[0].any() and earlier[1][:, inner].all()  # the first view keeps the point
    # an occluder: view 1 sees a wall 2 m away instead of the plane, so nothing is shared
    depth[1] = 2.0
    count, earlier = cross_view_coverage(depth, Ks, c2w)
    assert count[:2].eq(1).all() and not earlier.any()


def test_dedup_prefers_points_no_earlier_view_has():
    earlier = torch.zeros(2, H, W, dtype=torch.bool)
    earlier[1, :, : W // 2] = True  # view 1's left half is view 0's again
    keep = dedup_mask(earlier, torch.tensor([100, 100]), torch.Generator().manual_seed(0))
    assert keep.sum(dim=(1, 2)).tolist() == [100, 100]
    assert not (keep[1] & earlier[1]).any()  # all of view 1's budget goes to what only it sees
    keep = dedup_mask(earlier, torch.tensor([0, H * W // 2 + 10]), torch.Generator().manual_seed(0))
    assert int((keep[1] & earlier[1]).sum()) == 10  # duplicates only once the unique ones are used up


def test_density_target_low_for_a_redundant_view_high_for_a_unique_detail():
    g = torch.Generator().manual_seed(0)
    flat = torch.full((3, H, W), 0.5)
    images = flat.expand(3, 3, H, W).clone()
    detail = (torch.rand(3, 8, 8, generator=g) > 0.5).float()
    images[:, :, 12:20, 20:28] = detail  # the same textured patch in every view
    depth, Ks, c2w = _plane_views((0.0, 0.1, 0.0), (0.0, 0.0, math.pi))  # views 0, 1 redundant; 2 unique
    count, _ = cross_view_coverage(depth, Ks, c2w)
    t = density_target(images, 1.0 / count.float(), floor=0.1, w_redundancy=1.0)
    assert t.shape == (3, H, W) and t.min() >= 0 and t.max() <= 1
    patch = (slice(13, 19), slice(21, 27))
    unique_detail = t[2][patch].mean()
    assert unique_detail > 0.8  # a detail only one view sees: high
    assert t[0][patch].mean() < 0.6 * unique_detail and t[1][patch].mean() < 0.6 * unique_detail  # seen twice
    assert t[2][:4, :4].mean() < 0.2  # a flat area: the floor
    # without the redundancy term the views are alike
    t0 = density_target(images, None, floor=0.1)
    torch.testing.assert_close(t0[0], t0[2])


def test_coverage_mask_is_the_full_models_alpha_above_a_half():
    alpha = torch.tensor([[0.0, 0.49], [0.51, 1.0]]).reshape(1, 2, 2, 1)
    assert covered_mask(alpha).tolist() == [[[False, False], [True, True]]]


def test_log_uniform_kappa_covers_the_whole_range_from_the_first_step():
    g = torch.Generator().manual_seed(0)
    ks = [sample_kappa(0, g, low=0.02, high=0.95, schedule="log_uniform") for _ in range(2000)]
    assert min(ks) >= 0.02 and max(ks) <= 0.95
    below, above = sum(k < 0.1 for k in ks), sum(k > 0.5 for k in ks)
    assert 0.3 < below / 2000 < 0.52 and 0.1 < above / 2000 < 0.25  # log(5)/log(47.5), log(1.9)/log(47.5)
    with pytest.raises(ValueError, match="schedule"):
        sample_kappa(0, g, schedule="linear")


def test_a_checkpoint_from_before_issue_18_keeps_ecosplats_budget_stage():
    """small's budget stage changed in issue 18; a record without the new fields (an older
    checkpoint) is read with the class defaults (EcoSplat's stage 2), which is how it was trained,
    and it still matches its preset."""
    from clsplat.models.common.presets import check_preset_matches
    from clsplat.models.pgt.presets import BUDGET_FIELDS, SMALL, PGTPreset, saved_preset
    new = {"budget_views", "selection", "importance_head", "budget_colour", "learned_fill", "coverage_input",
           "coverage_tol", "target", "target_floor", "w_redundancy", "kappa_schedule", "fill_cap_px"}
    assert new <= set(BUDGET_FIELDS)
    old = {k: v for k, v in SMALL.to_dict().items() if k not in new}
    old["kappa_min"] = 0.05
    got = saved_preset(old)
    assert got.selection == "topk" and not got.importance_head and got.budget_views == 2 and got.fill_cap_px == 0
    assert got.height == SMALL.height and got.steps == SMALL.steps
    check_preset_matches(old, got, "old.pt")
    assert saved_preset(SMALL.to_dict()) == SMALL
    assert PGTPreset.__dataclass_fields__["selection"].default == "topk"


def test_a_checkpoint_from_before_the_kappa_decoder_keeps_kappa_at_the_heads():
    """small now conditions its decoder on κ (``kappa_decoder=2``); a budget checkpoint written
    before the field existed (κ only at the heads, no decoder copies in its state) is read with
    ``kappa_decoder=0``, so its state loads into the model it was trained as."""
    from clsplat.models.pgt.model import PGT
    from clsplat.models.pgt.presets import BUDGET_FIELDS, SMALL, TINY, saved_preset
    assert {"kappa_decoder", "kappa_film"} <= set(BUDGET_FIELDS) and SMALL.kappa_decoder == 2
    old = {k: v for k, v in SMALL.to_dict().items() if k not in ("kappa_decoder", "kappa_film")}
    got = saved_preset(old)
    assert got.kappa_decoder == 0 and got.selection == SMALL.selection and got.fill_cap_px == SMALL.fill_cap_px
    tiny_old = {k: v for k, v in TINY.replace(kappa_decoder=2).to_dict().items() if k != "kappa_decoder"}
    state = PGT(TINY).enable_budget().state_dict()  # written by the code before the field
    m = PGT(saved_preset(tiny_old)).enable_budget()
    m.load_state_dict(state)  # strict: no decoder copies expected
    assert m.budget.decoder is None
