"""AutoSplat's object-set optimisation fields (issue 36, small objects): ``object_lr_scale`` scales
the object sets' Adam learning rates and nothing else, ``object_grad_threshold`` replaces the
densification threshold for object sets only, both are checked, and off (1.0 / 0.0) they change
nothing."""
import pytest
import torch

from clsplat.data.synthetic import generate_sequence
from clsplat.models.autosplat.data import prepare_data
from clsplat.models.autosplat.densify import Densifier, GaussianParams
from clsplat.models.autosplat.model import Switches
from clsplat.models.autosplat.trainer import Trainer
from clsplat.models.common.presets import get_preset

TINY = get_preset("autosplat", "tiny")
CAMS = ["CAM_FRONT", "CAM_BACK_LEFT"]


@pytest.fixture(scope="module")
def street():
    return generate_sequence(height=32, width=56, num_frames=4, seed=1, dt=0.2)


def _lrs(t: Trainer) -> dict[str, list[float]]:
    """``{owner: [lr of each of its groups]}`` of the trainer's optimizer (built by ``initialise``)."""
    t.initialise()
    out: dict[str, list[float]] = {}
    for owner, g in zip(t.group_owner, t.opt.param_groups):
        out.setdefault(owner, []).append(g["lr"])
    return out


def test_the_object_lr_scale_multiplies_the_object_sets_only(street, tmp_path):
    d = prepare_data(street, CAMS, 4)
    base = _lrs(Trainer(d, TINY, Switches(), tmp_path / "a", progress=False))
    scaled = _lrs(Trainer(d, TINY.replace(object_lr_scale=3.0), Switches(), tmp_path / "b", progress=False))
    objects = [k for k in base if k.startswith("object")]
    assert objects, "the street has no decomposed track"
    assert base["background"] == [TINY.lr_means, TINY.lr_quats, TINY.lr_scales, TINY.lr_opacity, TINY.lr_sh0,
                                  TINY.lr_shN]
    for k in objects:   # off: the object sets learn at the background's rates, as before the field
        assert base[k] == base["background"]
        assert scaled[k] == pytest.approx([3.0 * lr for lr in base[k]], rel=1e-12)
    for k in ("background", "residuals", "pose", "sky"):
        assert scaled[k] == base[k]


def _set(n: int) -> GaussianParams:
    """``n`` small Gaussians (clone candidates) in a row."""
    means = torch.arange(3 * n, dtype=torch.float32).view(n, 3)
    return GaussianParams.from_points(means, torch.full((n, 3), 0.5), torch.full((n, 3), 0.02), 1, opacity=0.5,
                                      labels=torch.zeros(n, dtype=torch.long))


@pytest.mark.parametrize("object_threshold, grown", [(0.0, 0), (1e-3, 4)])
def test_the_object_grad_threshold_applies_to_object_sets_only(object_threshold, grown):
    """Every Gaussian's mean gradient (5e-3) lies between the two thresholds: with the object
    threshold below it the object set clones all four, the background (at ``grad_threshold``) none."""
    p = TINY.replace(grad_threshold=1e-2, object_grad_threshold=object_threshold)
    sets = {"background": _set(4), "object0": _set(4)}
    dens = Densifier(p, {k: len(g) for k, g in sets.items()}, sky=99, object_caps={"object0": 100})
    for st in dens.stats.values():
        st.grad, st.count = torch.full((4,), 5e-3), torch.ones(4)
    opt = torch.optim.Adam([q for g in sets.values() for q in g.parameters()])
    rec = dens.densify(sets, opt, "foreground", torch.Generator().manual_seed(0))
    assert rec == {"densify_background": 4, "densify_object0": 4 + grown}


@pytest.mark.parametrize("field, value", [("object_lr_scale", 0.0), ("object_lr_scale", -1.0),
                                          ("object_lr_scale", float("inf")), ("object_lr_scale", "3"),
                                          ("object_grad_threshold", -1e-4), ("object_grad_threshold", float("nan")),
                                          ("object_grad_threshold", True)])
def test_bad_object_fields_are_named(field, value):
    with pytest.raises(ValueError, match=field) as e:
        TINY.replace(**{field: value})
    assert "\n" not in str(e.value)


def test_the_fields_are_off_in_every_preset_but_where_chosen():
    for name in ("tiny", "small", "paper"):
        p = get_preset("autosplat", name)
        assert (p.object_lr_scale, p.object_grad_threshold) == (1.0, 0.0), name
    # chosen for demo on validation streets (issue 36, session 15)
    assert get_preset("autosplat", "demo").object_lr_scale == 3.0
