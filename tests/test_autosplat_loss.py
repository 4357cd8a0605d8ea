"""AutoSplat's step renderer (models/autosplat/loss.py): the preset's rasterisation fields
``eps2d`` / ``rasterize_mode`` (issue 36, the outline band) reach every render of a run (training,
``render_frame``, the view sets' ``render_views``), are checked, and at their defaults (0.3,
"classic", the rasteriser's own) change nothing."""
import numpy as np
import pytest
import torch

import clsplat
from clsplat.constants import EPS2D
from clsplat.data.synthetic import generate_sequence
from clsplat.models.autosplat.data import prepare_data
from clsplat.models.autosplat.loss import StepRenderer
from clsplat.models.autosplat.model import Switches
from clsplat.models.autosplat.trainer import Trainer
from clsplat.models.autosplat.viewsets import render_views
from clsplat.models.common.gaussians import GaussianSet
from clsplat.models.common.presets import apply_sets, get_preset, preset_from_saved

TINY = get_preset("autosplat", "tiny")
CAMS = ["CAM_FRONT", "CAM_BACK_LEFT"]


@pytest.fixture(scope="module")
def street():
    return generate_sequence(height=32, width=56, num_frames=4, seed=1, dt=0.2)


def _scene():
    """Twenty small Gaussians (a few pixels wide, so that the dilation matters) 3-5 m in front of
    one 40 x 24 camera; its ``(gs, data, model, viewmats [1, 4, 4])`` for :class:`StepRenderer`."""
    g = torch.Generator().manual_seed(0)
    n = 20
    means = torch.cat([torch.rand(n, 2, generator=g) - 0.5, 3 + 2 * torch.rand(n, 1, generator=g)], 1)
    gs = GaussianSet(means, torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1),
                     0.004 + 0.01 * torch.rand(n, 3, generator=g), 0.5 + 0.4 * torch.rand(n, generator=g),
                     torch.rand(n, 1, 3, generator=g))
    data = type("D", (), {"Ks": torch.tensor([[[40.0, 0, 20], [0, 40.0, 12], [0, 0, 1]]]), "width": 40, "height": 24})
    model = type("M", (), {"sky_color": torch.zeros(3)})
    return gs, data, model, torch.eye(4)[None]


@pytest.mark.parametrize("eps2d, mode", [(0.3, "classic"), (0.05, "classic"), (0.3, "antialiased")])
def test_the_step_renderer_rasterises_with_its_options(eps2d, mode):
    gs, data, model, vm = _scene()
    col = StepRenderer(data, None, eps2d, mode).render(model, gs, vm, absgrad=False)[0]
    ref = clsplat.rasterization(gs.means, gs.quats, gs.scales, gs.opacities, gs.sh, vm, data.Ks, 40, 24,
                                sh_degree=0, backgrounds=torch.full((1, 3), 0.5), packed=False,
                                eps2d=eps2d, rasterize_mode=mode)[0]
    assert torch.equal(col, ref)
    default = StepRenderer(data).render(model, gs, vm, absgrad=False)[0]
    assert torch.equal(col, default) == (eps2d == EPS2D and mode == "classic")   # the options do change it


def test_the_defaults_are_the_rasterisers_in_every_preset():
    for name in ("tiny", "demo", "small", "paper"):
        p = get_preset("autosplat", name)
        assert (p.eps2d, p.rasterize_mode) == (EPS2D, "classic") == (0.3, "classic"), name
    # a checkpoint written before the fields existed resumes with the rasteriser's defaults
    saved = {k: v for k, v in TINY.to_dict().items() if k not in ("eps2d", "rasterize_mode")}
    assert (preset_from_saved("autosplat", saved).eps2d, preset_from_saved("autosplat", saved).rasterize_mode) \
        == (0.3, "classic")


def test_a_run_renders_every_view_with_the_presets_options(street, tmp_path):
    """``render_frame`` (training, evaluation) and ``render_views`` (the view sets) of the rig's own
    poses agree with each other and with a direct render at the preset's options, not the defaults."""
    p = apply_sets(TINY, ["eps2d=0.05", "rasterize_mode='antialiased'"])
    t = Trainer(prepare_data(street, CAMS, 4), p, Switches(), tmp_path, progress=False)
    t.initialise()
    assert t.renderer.options == {"eps2d": 0.05, "rasterize_mode": "antialiased"}
    f = t.data.train_frames[0]
    frame = t.render_frame(f)
    views = render_views(t, f, np.linalg.inv(t.data.viewmats[f].numpy().astype(np.float64)))
    assert torch.allclose(frame, views, atol=1e-5)
    gs, _ = t.model.scene_at(f)
    bg = torch.sigmoid(t.model.sky_color).expand(len(CAMS), 3)
    with torch.no_grad():
        default = gs.render(t.data.viewmats[f], t.data.Ks, t.data.width, t.data.height, backgrounds=bg,
                            packed=False)[0].clamp(0, 1)
    assert (frame - default).abs().max() > 1e-3


@pytest.mark.parametrize("field, value", [("eps2d", -0.1), ("eps2d", float("nan")), ("eps2d", float("inf")),
                                          ("eps2d", "0.1"), ("eps2d", True), ("rasterize_mode", "mip"),
                                          ("rasterize_mode", None)])
def test_bad_raster_fields_are_named(field, value):
    with pytest.raises(ValueError, match=field) as e:
        TINY.replace(**{field: value})
    assert "\n" not in str(e.value)
