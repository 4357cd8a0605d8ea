"""kernels/sh.cl (clsplat.stages.sh_colors) against clsplat.reference.sh_colors, and the torch-side
basis clsplat/sh.py (which the reference and the model families both use)."""
from __future__ import annotations

import pytest
import torch

from clsplat import stages

F64 = torch.float64


def engine_sh(rt, cfg, scene, radii, degree):
    dt = cfg.dtype
    cols = stages.sh_colors(rt, cfg, rt.array(scene["means"].to(dt)), rt.array(scene["viewmats"].to(dt)),
                            rt.array(scene["colors"].to(dt)), rt.array(radii), degree)
    return cols.host().clone()


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("K_extra", [0, 5])
def test_sh_float64(rt, cfg64, make_scene, reference, degree, K_extra):
    scene = make_scene(degree + 10 * K_extra, N=100, C=3, sh_degree=degree, K_extra=K_extra)
    assert scene["colors"].shape[1] == (degree + 1) ** 2 + K_extra
    radii = torch.ones(3, 100, 2, dtype=torch.int32)
    got = engine_sh(rt, cfg64, scene, radii, degree)
    want = reference.sh_colors(scene["colors"], scene["means"], scene["viewmats"], degree)
    assert (got - want).abs().max() <= 1e-12
    assert (got >= 0).all()


def test_sh_clamp_and_culled(rt, cfg64, make_scene, reference):
    """max(SH + 0.5, 0) clamps; culled pairs are skipped and keep colour 0."""
    scene = make_scene(3, N=80, C=2, sh_degree=3, K_extra=16)  # K = 32 > 16 needed
    scene["colors"] = scene["colors"] * 4  # large coefficients: many negative values before the clamp
    radii = torch.ones(2, 80, 2, dtype=torch.int32)
    radii[:, ::7] = 0
    got = engine_sh(rt, cfg64, scene, radii, 3)
    want = reference.sh_colors(scene["colors"], scene["means"], scene["viewmats"], 3)
    vis = (radii != 0).any(-1)
    assert (want[vis] == 0).any()  # the clamp is active somewhere
    assert got.shape == (2, 80, 3)
    assert (got[vis] - want[vis]).abs().max() <= 1e-12
    assert (got[~vis] == 0).all()


@pytest.mark.parametrize("degree", [0, 3])
def test_sh_float32(rt, cfg32, make_scene, reference, degree):
    # float32 SH of unit directions with coefficients ~0.5: absolute error a few ulp of 1
    scene = make_scene(20 + degree, N=100, C=2, sh_degree=degree, K_extra=1)
    radii = torch.ones(2, 100, 2, dtype=torch.int32)
    got = engine_sh(rt, cfg32, scene, radii, degree)
    s32 = {k: (v.float().double() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    want = reference.sh_colors(s32["colors"], s32["means"], s32["viewmats"], degree)
    assert got.dtype == torch.float32
    assert (got.double() - want).abs().max() <= 2e-6


def test_the_torch_basis_is_orthonormal_to_degree_4_and_the_references_own():
    """clsplat.sh.sh_basis integrates to the identity Gram matrix over the sphere (real SH are
    orthonormal), which checks every constant and sign pattern up to degree 4; the float64
    reference evaluates this same function (one definition, in the engine's module)."""
    import numpy as np

    from clsplat import reference, sh
    assert reference.sh_basis is sh.sh_basis
    # Gauss-Legendre in cos(theta) and uniform phi: exact for the degree-8 products of two basis functions
    z, wz = np.polynomial.legendre.leggauss(12)
    phi = torch.arange(24, dtype=F64) * (2 * torch.pi / 24)
    z, wz = torch.tensor(z, dtype=F64), torch.tensor(wz, dtype=F64)
    r = (1 - z * z).sqrt()
    d = torch.stack([r[:, None] * phi.cos(), r[:, None] * phi.sin(), z[:, None].expand(-1, 24)], -1)
    w = (wz[:, None] * (2 * torch.pi / 24)).expand(-1, 24)
    B = sh.sh_basis(d, 4).reshape(-1, 25)
    gram = B.T @ (w.reshape(-1, 1) * B)
    assert (gram - torch.eye(25, dtype=F64)).abs().max() < 1e-12
    for degree in range(5):
        assert sh.sh_basis(d[:2, :2], degree).shape == (2, 2, (degree + 1) ** 2)
    with pytest.raises(ValueError, match="degree"):
        sh.sh_basis(d, 5)
