"""PGT model (models/pgt/model.py, heads.py): head shapes and ranges, unprojection onto each
pixel's own ray, κ = 1 bitwise equal to the base model, Gaussian counts per κ, gradients from the
renderer to the encoder, and clear errors on bad input. Tiny preset."""
from __future__ import annotations

import math

import pytest
import torch

from clsplat.models.common.geometry import invert_rigid, pixel_centres, project, quat_to_matrix
from clsplat.models.pgt.matching import u_to_depth
from clsplat.models.pgt.model import PGT
from clsplat.models.pgt.presets import TINY


def _views(V=2, H=TINY.height, W=TINY.width, seed=0):
    g = torch.Generator().manual_seed(seed)
    images = torch.rand(V, 3, H, W, generator=g)
    f = 0.8 * W
    Ks = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]]).expand(V, 3, 3).clone()
    c2w = torch.eye(4).expand(V, 4, 4).clone()
    c2w[:, 0, 3] = torch.arange(V) * 0.5  # sideways baseline
    c2w[:, 2, 3] = torch.arange(V) * 0.3
    return images, Ks, c2w


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    m = PGT(TINY)
    with torch.no_grad():  # a non-trivial residual head (it starts at zero)
        m.depth_head.net[2].weight.normal_(0, 0.3)
    return m


@pytest.fixture(scope="module")
def out(model):
    images, Ks, c2w = _views()
    with torch.no_grad():
        return model(images, Ks, c2w), (images, Ks, c2w)


def _with_budget(model: PGT, preset) -> PGT:
    """A PGT of ``preset`` holding ``model``'s weights, with fresh budget heads (copies of its own)."""
    m = PGT(preset)
    m.load_state_dict(model.state_dict())
    m.enable_budget()
    return m


def test_head_shapes_and_ranges(out):
    o, (images, Ks, c2w) = out
    V, _, H, W = images.shape
    assert o.u.shape == o.u0.shape == o.depth.shape == o.depth0.shape == (V, H, W)
    assert o.prob.shape == (V, TINY.num_depths, H // 8, W // 8)
    torch.testing.assert_close(o.prob.sum(1), torch.ones(V, H // 8, W // 8))
    assert o.means.shape == (V, H, W, 3) and o.quats.shape == (V, H, W, 4) and o.scales.shape == (V, H, W, 3)
    assert o.opacities.shape == (V, H, W) and o.sh.shape == (V, H, W, 1, 3)
    assert ((o.u >= 0) & (o.u <= 1)).all() and ((o.u0 >= 0) & (o.u0 <= 1)).all()
    assert (o.depth >= TINY.min_depth * (1 - 1e-5)).all() and (o.depth <= TINY.max_depth * (1 + 1e-5)).all()
    # the residual is 0.5·tanh(r): at most half the (normalised) depth range, and it is active
    assert (o.u - o.u0).abs().max() <= 0.5 and (o.u - o.u0).abs().max() > 1e-3
    torch.testing.assert_close(o.quats.norm(dim=-1), torch.ones(V, H, W))
    assert (o.scales > 0).all() and (o.scales <= TINY.scale_cap).all()
    assert ((o.opacities >= 0) & (o.opacities <= 1)).all()
    # pixel colour: the DC term reproduces the source pixel
    torch.testing.assert_close(o.sh[..., 0, :] * 0.28209479177387814 + 0.5, images.permute(0, 2, 3, 1))
    g = o.gaussians()
    assert len(g) == V * H * W
    g.validate()


def test_sh_colour_head_shapes():
    p = TINY.replace(colour="sh", sh_degree=2)
    torch.manual_seed(0)
    images, Ks, c2w = _views()
    with torch.no_grad():
        o = PGT(p)(images, Ks, c2w)
    assert o.sh.shape == (2, p.height, p.width, 9, 3) and torch.isfinite(o.sh).all()
    assert o.gaussians().sh_degree == 2


def test_unprojection_on_own_ray_at_predicted_depth(out):
    o, (images, Ks, c2w) = out
    V, _, H, W = images.shape
    uv, z = project(o.means.reshape(V, -1, 3), Ks, invert_rigid(c2w))
    torch.testing.assert_close(uv.reshape(V, H, W, 2), pixel_centres(H, W).expand(V, H, W, 2), atol=2e-3, rtol=0)
    torch.testing.assert_close(z.reshape(V, H, W), o.depth, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(o.depth, u_to_depth(o.u, TINY.min_depth, TINY.max_depth))


def test_prediction_moves_with_the_world_frame():
    """A rigid change of world frame T moves means and rotations by T and leaves the rest."""
    torch.manual_seed(1)
    m = PGT(TINY).double()  # float64: no valid-mask flips at image borders from rounding
    images, Ks, c2w = (t.double() for t in _views())
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = quat_to_matrix(torch.nn.functional.normalize(torch.tensor([0.9, 0.1, -0.3, 0.2]), dim=0).double())
    T[:3, 3] = torch.tensor([3.0, -1.0, 2.0])
    with torch.no_grad():
        a = m(images, Ks, c2w)
        b = m(images, Ks, T @ c2w)
    torch.testing.assert_close(b.depth, a.depth)
    torch.testing.assert_close(b.means, a.means @ T[:3, :3].T + T[:3, 3])
    torch.testing.assert_close(quat_to_matrix(b.quats), T[:3, :3] @ quat_to_matrix(a.quats))


#: issue 18's budget stage: importance head, coverage input, stratified selection, density target, fill cap
ISSUE18 = TINY.replace(selection="stratified", importance_head=True, coverage_input=True, target="density",
                       fill_cap_px=8.0, kappa_schedule="log_uniform", kappa_min=0.02, budget_colour=True,
                       learned_fill=True)

#: issue 18, lead 4: κ-conditioned copies of every decoder stage feed the budget heads
KDEC = ISSUE18.replace(kappa_decoder=4)


@pytest.mark.parametrize("preset", [TINY, ISSUE18, KDEC], ids=["ecosplat", "issue18", "kappa_decoder"])
def test_kappa_one_is_the_base_model_bitwise(model, preset):
    images, Ks, c2w = _views(seed=3)
    with torch.no_grad():
        base = model(images, Ks, c2w)
    m = _with_budget(model, preset)
    with torch.no_grad():  # finetuned heads that differ from the base heads
        for prm in m.budget.parameters():
            prm.add_(torch.randn_like(prm) * 0.1)
        one = m(images, Ks, c2w, kappa=1.0)
        none = m(images, Ks, c2w)
    for o in (one, none):
        assert o.keep is None and len(o.gaussians()) == images.shape[0] * TINY.height * TINY.width
        for f in ("means", "quats", "scales", "opacities", "sh", "depth"):
            assert torch.equal(getattr(o, f), getattr(base, f)), f


def test_fresh_budget_heads_copy_the_base_heads_exactly(model):
    images, Ks, c2w = _views(seed=4)
    m = _with_budget(model, TINY)
    with torch.no_grad():
        base = m(images, Ks, c2w)
        half = m(images, Ks, c2w, kappa=0.5)
    for f in ("quats", "scales", "opacities", "sh"):
        assert torch.equal(getattr(half, f), getattr(base, f)), f
    # the kept ones are the top-K_v by (here: the base) opacity
    for v in range(2):
        kept = base.opacities[v][half.keep[v]]
        dropped = base.opacities[v][~half.keep[v]]
        assert kept.min() >= dropped.max()


@pytest.mark.parametrize("preset", [TINY, ISSUE18, KDEC], ids=["ecosplat", "issue18", "kappa_decoder"])
@pytest.mark.parametrize("views", [2, 3])
def test_gaussian_count_for_every_kappa(model, views, preset):
    images, Ks, c2w = _views(V=views, seed=5)
    m = _with_budget(model, preset)
    P = TINY.height * TINY.width
    with torch.no_grad():
        for kappa in (1.0, 0.5, 0.1, 0.05, 1e-4):
            o = m(images, Ks, c2w, kappa=kappa)
            want = round(kappa * views * P)
            assert abs(len(o.gaussians()) - want) <= views, kappa
            assert len(o.gaussians()) == PGT.expected_count(kappa, views, TINY.height, TINY.width)
            if kappa < 1:
                assert o.keep.sum(dim=(1, 2)).tolist() == o.budgets.tolist()
                assert o.importance.shape == o.opacities.shape


def test_issue18_heads_start_as_the_base_and_select_by_importance(model):
    """Fresh issue-18 budget heads return the base parameters; the importance head starts as the
    base opacity; the selection spreads the budget (no top-K by opacity); the fill cap lets a
    widened far Gaussian grow past ``scale_cap`` metres."""
    images, Ks, c2w = _views(seed=4)
    m = _with_budget(model, ISSUE18)
    with torch.no_grad():
        base = m(images, Ks, c2w)
        o = m(images, Ks, c2w, kappa=0.1)
    for f in ("quats", "opacities", "sh"):
        assert torch.equal(getattr(o, f), getattr(base, f)), f
    torch.testing.assert_close(o.importance, base.opacities)
    assert o.fill_log is not None and o.fill_log.eq(0).all()  # the learned fill starts as the fill
    with torch.no_grad():
        m.budget.fill[2].bias.copy_(torch.tensor([1.0, -1.0, 0.0]))
        wide = m(images, Ks, c2w, kappa=0.1)
    a, b = o.gaussians().scales, wide.gaussians().scales
    assert (b[:, 0] >= a[:, 0]).all() and (b[:, 1] <= a[:, 1]).all() and not torch.equal(a, b)
    assert o.coverage is not None and o.coverage.min() >= 1
    topk = base.opacities[0][o.keep[0]].min() >= base.opacities[0][~o.keep[0]].max()
    assert not topk
    g = o.gaussians()
    cap = torch.maximum(torch.full_like(o.footprint, ISSUE18.scale_cap), 8.0 * o.footprint)[o.keep]
    assert (g.scales <= cap[:, None] + 1e-6).all()
    no_cap = PGT(ISSUE18.replace(fill_cap_px=0.0)).enable_budget()
    no_cap.load_state_dict(m.state_dict())
    with torch.no_grad():
        assert no_cap(images, Ks, c2w, kappa=0.1).gaussians().scales.max() <= ISSUE18.scale_cap + 1e-6


@pytest.mark.parametrize("stages", [1, 2, 4])
def test_kappa_decoder_starts_as_the_base_and_changes_the_features_with_kappa(model, stages):
    """Fresh κ-conditioned decoder copies give the base decoder's features exactly (so the budget
    stage starts from the base); once the FiLM has weights, the parameters differ between two κ
    while the depth stays the base's; gradients reach the copies and the FiLM; without
    ``kappa_film`` there is no κ input in the decoder."""
    images, Ks, c2w = _views(V=3, seed=6)
    p = ISSUE18.replace(kappa_decoder=stages)
    m = _with_budget(model, p)
    assert len(m.budget.decoder.stages) == stages and len(m.budget.decoder.film) == stages
    with torch.no_grad():
        base = m(images, Ks, c2w)
        o = m(images, Ks, c2w, kappa=0.1)
    for f in ("quats", "opacities", "sh", "scales"):
        torch.testing.assert_close(getattr(o, f), getattr(base, f), rtol=0, atol=0, msg=f)
    with torch.no_grad():
        for film in m.budget.decoder.film:
            film.net[2].weight.normal_(0, 0.1)
        a = m(images, Ks, c2w, kappa=0.1)
        b = m(images, Ks, c2w, kappa=0.05)
    assert torch.equal(a.depth, base.depth) and torch.equal(b.depth, base.depth)
    assert not torch.equal(a.opacities, b.opacities) and not torch.equal(a.opacities, base.opacities)
    o = m(images, Ks, c2w, kappa=0.2)
    (o.opacities.sum() + o.scales.sum()).backward()
    assert all(prm.grad is not None and prm.grad.abs().sum() > 0 for prm in m.budget.decoder.film.parameters())
    assert all(prm.grad is not None for prm in m.budget.decoder.stages.parameters())
    assert all(prm.grad is None for prm in m.decoder.parameters())  # the base decoder stays frozen
    plain = PGT(p.replace(kappa_film=False)).enable_budget()
    assert plain.budget.decoder.film is None and len(plain.budget.decoder.stages) == stages


@pytest.mark.parametrize("preset", [TINY, ISSUE18, KDEC], ids=["ecosplat", "issue18", "kappa_decoder"])
def test_full_gives_the_finetuned_parameters_unpruned(model, preset):
    """Issue 33's controls select from the finetuned parameters: ``full=True`` runs the stage-2
    heads at κ and keeps every Gaussian; the model's own selection applied to them is its κ
    output exactly; every naive selection at κ = 1 keeps every pixel, so it is the finetuned model
    itself; random, grid and dedup pick the very pixels of the base model's row."""
    from clsplat.models.pgt.evaluate import BASELINES, baseline_mask
    from clsplat.models.pgt.model import learned_selection
    images, Ks, c2w = _views(V=3, seed=7)
    m = _with_budget(model, preset)
    with torch.no_grad():
        for prm in m.budget.parameters():   # finetuned heads that differ from the base heads
            prm.add_(torch.randn_like(prm) * 0.1)
        base = m(images, Ks, c2w)
        for kappa in (0.1, 1.0):
            ft = m(images, Ks, c2w, kappa=kappa, full=True)
            assert ft.keep is None and len(ft.gaussians()) == 3 * TINY.height * TINY.width
            assert not torch.equal(ft.opacities, base.opacities)      # not the base model
            assert torch.equal(ft.depth, base.depth)                  # the depth stays the base's
            assert int(ft.budgets.sum()) == PGT.expected_count(kappa, 3, TINY.height, TINY.width)
            for meth in BASELINES:
                gen = lambda: torch.Generator().manual_seed(11)  # noqa: E731  (the same draw for both rows)
                keep_ft = baseline_mask(meth, ft, ft.budgets, Ks, c2w, gen(), preset.coverage_tol)
                keep_base = baseline_mask(meth, base, ft.budgets, Ks, c2w, gen(), preset.coverage_tol)
                if meth != "opacity":   # the same pixels; only the parameters differ
                    assert torch.equal(keep_ft, keep_base), meth
                if kappa == 1.0:
                    assert keep_ft.all()
                    a, b = ft.gaussians(keep_ft), ft.gaussians()
                    for f in ("means", "quats", "scales", "opacities", "sh"):
                        assert torch.equal(getattr(a, f), getattr(b, f)), (meth, f)
        own = m(images, Ks, c2w, kappa=0.1)
        ft = m(images, Ks, c2w, kappa=0.1, full=True)
        keep = learned_selection(ft.importance, ft.budgets, preset.selection)
        assert torch.equal(keep, own.keep)
        a, b = ft.gaussians(keep), own.gaussians()
        for f in ("means", "quats", "scales", "opacities", "sh"):
            assert torch.equal(getattr(a, f), getattr(b, f)), f
    with pytest.raises(ValueError, match="full=True needs the budget stage"):
        model(images, Ks, c2w, full=True)


def test_kappa_decoder_field_is_checked():
    with pytest.raises(ValueError, match="kappa_decoder"):
        TINY.replace(kappa_decoder=5)


def test_gradients_reach_the_encoder_through_the_renderer():
    torch.manual_seed(0)
    m = PGT(TINY)
    images, Ks, c2w = _views()
    o = m(images, Ks, c2w)
    rgb, alpha, _ = o.gaussians().render(invert_rigid(c2w[:1]), Ks[:1], TINY.width, TINY.height)
    loss = (rgb[0] - images[0].permute(1, 2, 0)).abs().mean()  # render loss only
    loss.backward()
    for name in ("encoder.stem.0.weight", "encoder.stage3.1.conv2.weight", "decoder.out.0.weight",
                 "heads.opacity.2.weight", "heads.scale.2.weight", "heads.rotation.2.weight"):
        g = dict(m.named_parameters())[name].grad
        assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0, name
    # the matcher only moves the means, so its gradient says the depth reaches the renderer
    g = m.matcher.logits.weight.grad
    assert g is not None and g.abs().sum() > 0


def test_bad_input_names_the_argument(model):
    images, Ks, c2w = _views()
    cases = [
        ((images[:1], Ks[:1], c2w[:1]), {}, "images: PGT needs at least 2"),
        ((images, Ks[:1], c2w), {}, "Ks: expected shape"),
        ((images, Ks, c2w[:, :3]), {}, "cam_to_world: expected shape"),
        ((images[:, :, :30], Ks, c2w), {}, "images: height and width must be multiples of 8"),
        ((images[:, :2], Ks, c2w), {}, "images: expected"),
        ((images.clone().index_fill_(2, torch.tensor([3]), math.nan), Ks, c2w), {}, "images: contains NaN"),
        ((images, Ks.clone().fill_(math.nan), c2w), {}, "Ks: contains NaN"),
        ((images, Ks, c2w * 2), {}, "cam_to_world[0]"),
        ((images, Ks, c2w), {"kappa": 0.0}, "kappa"),
        ((images, Ks, c2w), {"kappa": 1.5}, "kappa"),
        ((images, Ks, c2w), {"kappa": math.nan}, "kappa"),
        ((images, Ks, c2w), {"kappa": 0.5}, "kappa: 0.5 < 1 needs the budget stage"),
    ]
    for args, kw, msg in cases:
        with pytest.raises(ValueError, match=msg.replace("[", r"\[").replace("]", r"\]")):
            model(*args, **kw)
