"""kernels/project_bwd.cl via clsplat.autograd.ProjectFn against torch autograd of
clsplat.reference.project, in float64 (1e-9) and float32 (stated bound)."""
from __future__ import annotations

import pytest
import torch

import clsplat
from clsplat import reference as ref
from clsplat.autograd import ProjectFn, Settings
from clsplat.config import RenderConfig

F64 = torch.float64


def _project_grads(scene, fn, dtype, antialiased, near=0.01, far=1e10, eps2d=0.3, radius_clip=0.0):
    xs = [scene[k].to(dtype).clone().requires_grad_() for k in ("means", "quats", "scales", "opacities", "viewmats")]
    W, H = scene["width"], scene["height"]
    if fn == "engine":
        st = Settings(clsplat.get_runtime(), RenderConfig(precision="float64" if dtype == F64 else "float32"),
                      W, H, 16, near, far, eps2d, radius_clip, antialiased)
        means2d, conics, depths, opac, radii, _, _ = ProjectFn.apply(*xs, scene["Ks"].to(dtype), st)
        vis = (radii > 0).any(-1)
    else:
        p = ref.project(*xs[:4], xs[4], scene["Ks"].to(dtype), W, H, near_plane=near, far_plane=far,
                        eps2d=eps2d, radius_clip=radius_clip, antialiased=antialiased)
        means2d, conics, depths, opac, vis = p["means2d"], p["conics"], p["depths"], p["opacities"], p["visible"]
    g = torch.Generator().manual_seed(0)
    w = [torch.randn(t.shape, generator=g, dtype=F64).to(dtype) for t in (means2d, conics, depths, opac)]
    m = vis.to(dtype)
    loss = ((means2d * w[0]).sum(-1) * m).sum() + ((conics * w[1]).sum(-1) * m).sum() \
        + (depths * w[2]).sum() + (opac * w[3] * m).sum()
    loss.backward()
    return [x.grad.double() for x in xs]


@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("seed", [0, 1])
def test_project_bwd_matches_reference(make_scene, seed, antialiased):
    scene = make_scene(seed=seed, N=200, C=3)
    g_ref = _project_grads(scene, "ref", F64, antialiased)
    g64 = _project_grads(scene, "engine", F64, antialiased)
    g32 = _project_grads(scene, "engine", torch.float32, antialiased)
    for name, a, b, c in zip(("means", "quats", "scales", "opacities", "viewmats"), g64, g_ref, g32):
        scale = b.norm().clamp_min(1e-12)
        assert ((a - b).norm() / scale).item() < 1e-9, name
        # float32: the conic of a small Gaussian is ~1/sigma^2 with ~1e-6 relative rounding
        assert ((c - b).norm() / scale).item() < 1e-4, name


@pytest.mark.parametrize("near,far,eps2d,radius_clip", [
    (3.8, 1e10, 0.3, 0.0),     # a near plane that culls part of the scene
    (0.01, 4.2, 0.3, 0.0),     # a far plane that culls part of it
    (0.01, 1e10, 0.0, 0.0),    # no screen-space dilation
    (0.01, 1e10, 3.0, 0.0),    # heavy dilation (radii and conics dominated by eps2d)
    (0.01, 1e10, 0.3, 5.0),    # radius_clip drops the small splats
])
def test_project_bwd_matches_reference_at_each_culling_knob(make_scene, near, far, eps2d, radius_clip):
    """Gradients match the reference for each projection knob, with part of the scene culled
    (the loss weights culled pairs' 2D outputs by zero, their depths not)."""
    scene = make_scene(seed=4, N=200, C=2)
    kw = dict(near=near, far=far, eps2d=eps2d, radius_clip=radius_clip)
    g_ref = _project_grads(scene, "ref", F64, False, **kw)
    g64 = _project_grads(scene, "engine", F64, False, **kw)
    vis = ref.project(*(scene[k] for k in ("means", "quats", "scales", "opacities", "viewmats", "Ks")),
                      scene["width"], scene["height"], near_plane=near, far_plane=far, eps2d=eps2d,
                      radius_clip=radius_clip)["visible"]
    if near > 1 or far < 100 or radius_clip > 0:
        assert 0.1 < vis.double().mean() < 0.9   # the knob culls part of the scene, not all
    for name, a, b in zip(("means", "quats", "scales", "opacities", "viewmats"), g64, g_ref):
        assert ((a - b).norm() / b.norm().clamp_min(1e-12)).item() < 1e-9, name
