"""GaussianSet: the explicit scene every model family produces, and real-SH rotation.

A :class:`GaussianSet` is the hand-over point between a model and the engine: means ``[N, 3]``,
quats ``[N, 4]`` (wxyz, need not be unit), scales ``[N, 3]`` (post-activation, metres; the
covariance uses s², so the sign is irrelevant), opacities ``[N]`` (post-activation, in [0, 1])
and SH coefficients ``[N, K, 3]`` with ``K = (d+1)²``, in the 3DGS real-SH basis order, so that
the colour seen along unit direction ``v`` (from the camera to the Gaussian, in the frame of
``means``) is ``max(SH(v) + 0.5, 0)`` as in clsplat and gsplat.

It concatenates, indexes, moves rigidly between frames (means, rotations *and* SH), reads and
writes the INRIA ``.ply`` layout through :mod:`clsplat.io.ply`, and renders through
:func:`clsplat.rasterization`. Every operation is differentiable with respect to the tensors.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from functools import lru_cache
from pathlib import Path
from typing import Sequence

import torch

from clsplat.io.ply import read_ply, rgb_to_sh, sh_to_rgb, write_ply
from clsplat.sh import sh_basis

__all__ = ["GaussianSet", "rotate_sh", "sh_rotation_matrices", "rgb_to_sh", "sh_to_rgb"]

#: highest SH degree the basis (clsplat.sh.sh_basis) and the engine evaluate.
MAX_SH_DEGREE = 3


@dataclass
class GaussianSet:
    """N 3D Gaussians (see the module docstring for conventions).

    Attributes:
        means: [N, 3] centres, metres.
        quats: [N, 4] rotations, wxyz.
        scales: [N, 3] standard deviations along the rotated axes, metres.
        opacities: [N] in [0, 1].
        sh: [N, K, 3] SH coefficients, K = (sh_degree + 1)².
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor

    def __post_init__(self) -> None:
        self.validate(check_values=False)

    # ------------------------------------------------------------------ checks and basics
    def validate(self, check_values: bool = True) -> "GaussianSet":
        """Raise ValueError naming the first field with a wrong type, shape, dtype or device;
        with ``check_values`` also NaN/Inf anywhere and opacities outside [0, 1]."""
        for f in fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, torch.Tensor):
                raise ValueError(f"GaussianSet.{f.name}: expected a torch.Tensor, got {type(v).__name__}")
            if not v.is_floating_point():
                raise ValueError(f"GaussianSet.{f.name}: expected a floating-point tensor, got {v.dtype}")
        n = self.means.shape[0] if self.means.dim() == 2 else -1
        want = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,)}
        for name, shape in want.items():
            v = getattr(self, name)
            if n < 0 or tuple(v.shape) != shape:
                raise ValueError(f"GaussianSet.{name}: expected shape {list(shape) if n >= 0 else '[N, 3]'}, "
                                 f"got {list(v.shape)}")
        k = self.sh.shape[1] if self.sh.dim() == 3 else 0
        if self.sh.dim() != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3 or math.isqrt(k) ** 2 != k or k == 0:
            raise ValueError(f"GaussianSet.sh: expected shape [{n}, K, 3] with K = (d+1)^2, got {list(self.sh.shape)}")
        if math.isqrt(k) - 1 > MAX_SH_DEGREE:
            raise ValueError(f"GaussianSet.sh: degree {math.isqrt(k) - 1} > {MAX_SH_DEGREE} is not supported")
        for f in fields(self):
            v = getattr(self, f.name)
            if v.dtype != self.means.dtype or v.device != self.means.device:
                raise ValueError(f"GaussianSet.{f.name}: {v.dtype} on {v.device} differs from means' "
                                 f"{self.means.dtype} on {self.means.device}")
        if check_values:
            for f in fields(self):
                v = getattr(self, f.name)
                if not torch.isfinite(v).all():
                    raise ValueError(f"GaussianSet.{f.name}: contains NaN or Inf")
            if len(self) and ((self.opacities < 0) | (self.opacities > 1)).any():
                raise ValueError("GaussianSet.opacities: values must lie in [0, 1] (post-activation)")
        return self

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        """SH degree d, from K = (d+1)²."""
        return math.isqrt(self.sh.shape[1]) - 1

    @property
    def colors(self) -> torch.Tensor:
        """[N, 3] view-independent colour (the DC term)."""
        return sh_to_rgb(self.sh)

    def _map(self, fn) -> "GaussianSet":
        return GaussianSet(*(fn(getattr(self, f.name)) for f in fields(self)))

    def detach(self) -> "GaussianSet":
        return self._map(torch.Tensor.detach)

    def to(self, *args, **kwargs) -> "GaussianSet":
        """Like ``torch.Tensor.to`` on every field."""
        return self._map(lambda t: t.to(*args, **kwargs))

    # ------------------------------------------------------------------ combining
    @staticmethod
    def cat(sets: Sequence["GaussianSet"]) -> "GaussianSet":
        """Concatenate sets; SH are zero-padded to the highest degree among them."""
        sets = list(sets)
        if not sets:
            raise ValueError("sets: need at least one GaussianSet to concatenate")
        K = max(s.sh.shape[1] for s in sets)
        sh = [torch.nn.functional.pad(s.sh, (0, 0, 0, K - s.sh.shape[1])) for s in sets]
        return GaussianSet(torch.cat([s.means for s in sets]), torch.cat([s.quats for s in sets]),
                           torch.cat([s.scales for s in sets]), torch.cat([s.opacities for s in sets]),
                           torch.cat(sh))

    def index(self, idx: torch.Tensor) -> "GaussianSet":
        """The Gaussians selected by a bool mask [N] or integer indices [M]."""
        idx = torch.as_tensor(idx, device=self.means.device)
        if idx.dtype == torch.bool and idx.shape != (len(self),):
            raise ValueError(f"idx: a bool mask must have shape [{len(self)}], got {list(idx.shape)}")
        if idx.dtype != torch.bool and (idx.is_floating_point() or idx.dim() != 1):
            raise ValueError(f"idx: expected a bool mask [N] or integer indices [M], got {idx.dtype} {list(idx.shape)}")
        return self._map(lambda t: t[idx])

    __getitem__ = index

    def with_sh_degree(self, degree: int) -> "GaussianSet":
        """Truncate or zero-pad SH to ``degree``."""
        if not 0 <= degree <= MAX_SH_DEGREE:
            raise ValueError(f"degree: expected 0..{MAX_SH_DEGREE}, got {degree}")
        K = (degree + 1) ** 2
        sh = self.sh[:, :K] if K <= self.sh.shape[1] else torch.nn.functional.pad(self.sh, (0, 0, 0, K - self.sh.shape[1]))
        return GaussianSet(self.means, self.quats, self.scales, self.opacities, sh)

    # ------------------------------------------------------------------ frames
    def transform(self, T: torch.Tensor) -> "GaussianSet":
        """Move the set by the rigid transform ``T`` [4, 4] (new = R·old + t).

        Means are mapped, quaternions left-multiplied by R's quaternion, and SH rotated with
        :func:`rotate_sh`, so that every Gaussian looks the same from a camera moved with it.
        """
        from .geometry import check_rigid, matrix_to_quat, quat_multiply
        T = torch.as_tensor(T, dtype=self.means.dtype, device=self.means.device)
        if T.shape != (4, 4):
            raise ValueError(f"T: expected shape [4, 4], got {list(T.shape)}")
        check_rigid(T, "T")
        R, t = T[:3, :3], T[:3, 3]
        q = matrix_to_quat(R).expand(len(self), 4)
        sh = rotate_sh(self.sh, R) if self.sh.shape[1] > 1 else self.sh
        return GaussianSet(self.means @ R.T + t, quat_multiply(q, self.quats), self.scales, self.opacities, sh)

    # ------------------------------------------------------------------ I/O
    def save_ply(self, path: str | Path) -> Path:
        """Write the INRIA 3DGS ``.ply`` layout (scales stored as log|s|)."""
        g = self.detach().to(device="cpu", dtype=torch.float32)
        return write_ply(path, g.means, g.quats, g.scales.abs().clamp_min(1e-30), g.opacities, g.sh)

    @staticmethod
    def load_ply(path: str | Path) -> "GaussianSet":
        """Read an INRIA-layout ``.ply`` (float32 CPU tensors)."""
        p = read_ply(path)
        return GaussianSet(p.means, p.quats, p.scales, p.opacities, p.sh)

    # ------------------------------------------------------------------ rendering
    def render(self, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int, **kwargs):
        """Render through :func:`clsplat.rasterization` with this set's SH degree.

        Args:
            viewmats: [C, 4, 4] world-to-camera (world = the frame of ``means``).
            Ks: [C, 3, 3] intrinsics.
            width, height: image size.
            **kwargs: any other ``rasterization`` argument (backgrounds, render_mode, absgrad,
                near_plane, far_plane, device, config, ...).
        Returns:
            (colors [C, H, W, X], alphas [C, H, W, 1], meta) as ``rasterization``.
        """
        import clsplat
        dt = self.means.dtype
        viewmats = torch.as_tensor(viewmats, dtype=dt, device=self.means.device)
        Ks = torch.as_tensor(Ks, dtype=dt, device=self.means.device)
        return clsplat.rasterization(self.means, self.quats, self.scales, self.opacities, self.sh,
                                     viewmats, Ks, width, height, sh_degree=self.sh_degree, **kwargs)


# ---------------------------------------------------------------------------------------
# real spherical-harmonic rotation
# ---------------------------------------------------------------------------------------
@lru_cache(maxsize=None)
def _sample_dirs(degree: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Fixed well-spread unit directions [S, 3] (S >= 2(2l+1)) and the pseudo-inverse of the
    basis of each degree at them, float64 CPU. Cached: these are constants."""
    S = 2 * (2 * degree + 1) + 8
    i = torch.arange(S, dtype=torch.float64) + 0.5  # Fibonacci sphere: well conditioned
    z = 1 - 2 * i / S
    phi = math.pi * (1 + 5 ** 0.5) * i
    r = (1 - z * z).sqrt()
    d = torch.stack([r * phi.cos(), r * phi.sin(), z], -1)
    lo, hi = degree ** 2, (degree + 1) ** 2
    A = sh_basis(d, degree)[:, lo:hi]
    return d, torch.linalg.pinv(A)


def sh_rotation_matrices(R: torch.Tensor, degree: int) -> list[torch.Tensor]:
    """Per-degree real-SH rotation matrices D_l(R), l = 1..degree, each [..., 2l+1, 2l+1].

    With ``c' = D_l c`` for every degree, the colour function satisfies f'(R v) = f(v): the SH
    of a Gaussian rotated by R. From Y_l(v)·c' = Y_l(Rᵀv)·c at fixed sample directions v_i,
    D_l = pinv(Y_l(v_i)) · Y_l(Rᵀ v_i): exact, because a rotation maps each degree's space onto
    itself, and differentiable in R.
    """
    out = []
    for l in range(1, degree + 1):
        d, pinv = _sample_dirs(l)
        d, pinv = d.to(R), pinv.to(R)
        rotated = d @ R  # row i = (Rᵀ v_i)ᵀ, batched over R's leading dims
        B = sh_basis(rotated, l)[..., l * l:(l + 1) ** 2]  # [..., S, 2l+1]
        out.append(pinv @ B)
    return out


def rotate_sh(sh: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """Rotate SH coefficients by R: the returned coefficients seen along ``R v`` give the colour
    the input gave along ``v``.

    Args:
        sh: [N, K, 3], K = (d+1)², d <= 3, 3DGS basis order.
        R: [3, 3] or [N, 3, 3] rotation.
    Returns:
        [N, K, 3]; the DC term is unchanged.
    """
    if sh.dim() != 3 or sh.shape[2] != 3 or math.isqrt(sh.shape[1]) ** 2 != sh.shape[1]:
        raise ValueError(f"sh: expected shape [N, K, 3] with K = (d+1)^2, got {list(sh.shape)}")
    if R.shape not in ((3, 3), (sh.shape[0], 3, 3)):
        raise ValueError(f"R: expected shape [3, 3] or [{sh.shape[0]}, 3, 3], got {list(R.shape)}")
    degree = math.isqrt(sh.shape[1]) - 1
    if degree > MAX_SH_DEGREE:
        raise ValueError(f"sh: degree {degree} > {MAX_SH_DEGREE} is not supported")
    parts = [sh[:, :1]]
    for l, D in enumerate(sh_rotation_matrices(R.to(sh.dtype), degree), start=1):
        parts.append(D @ sh[:, l * l:(l + 1) ** 2])
    return torch.cat(parts, 1)
