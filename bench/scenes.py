"""The standard benchmark scenes, deterministic from a seed.

A scene is a plain dict of rasterization arguments (float32 tensors) plus a ``name``:
``means, quats, scales, opacities, colors, viewmats, Ks, width, height`` and ``sh_degree``
(None for plain colours).

* :func:`scene_a`: 100k random Gaussians inside the frustum of one 640x352 camera, SH degree 3
  (colors [N,16,3]), depths 2-60 m, screen-space standard deviations of a few pixels
  (log-normal, median 1.5 px), random rotations and anisotropy, opacities in (0.05, 1).
* :func:`scene_b`: pixel-aligned: one Gaussian per non-sky pixel of the 6 cameras of the
  synthetic street (176x320, :mod:`clsplat.data.synthetic`), lifted with
  :func:`clsplat.pixel_recon.lift_pixels`, rendered into the same 6 views.
* :func:`sweep_n` / :func:`sweep_pixels`: scene A's generator at other sizes.
"""
from __future__ import annotations

import math

import numpy as np
import torch

__all__ = ["scene_a", "scene_b", "random_frustum_scene", "sweep_n", "sweep_pixels", "n_pixels"]


def _camera(width: int, height: int, hfov_deg: float = 70.0) -> tuple[torch.Tensor, torch.Tensor]:
    f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=torch.float32)
    return torch.eye(4, dtype=torch.float32)[None], K[None]


def random_frustum_scene(n: int, width: int = 640, height: int = 352, sh_degree: int | None = 3,
                         seed: int = 0, sigma_px: float = 1.5, base_width: int | None = None,
                         name: str | None = None) -> dict:
    """``n`` random Gaussians in the frustum of one camera at the origin looking along +z.

    Screen-space size is drawn for a ``base_width``-wide image (default ``width``), so a
    resolution sweep with ``base_width`` fixed renders the same world at more pixels.
    """
    g = torch.Generator().manual_seed(seed)
    base_width = base_width or width
    f_base = 0.5 * base_width / math.tan(math.radians(35.0))
    viewmats, Ks = _camera(width, height)
    u = torch.rand(n, 3, generator=g, dtype=torch.float64)
    z = 2.0 * (30.0 ** u[:, 2])                                   # 2..60 m, log-uniform
    tx, ty = math.tan(math.radians(35.0)), math.tan(math.radians(35.0)) * height / width
    x = (2 * u[:, 0] - 1) * tx * z * 1.05
    y = (2 * u[:, 1] - 1) * ty * z * 1.05
    means = torch.stack([x, y, z], -1)
    px = sigma_px * torch.exp(0.6 * torch.randn(n, generator=g, dtype=torch.float64))
    aniso = torch.exp(0.5 * torch.randn(n, 3, generator=g, dtype=torch.float64))
    scales = (px * z / f_base)[:, None] * aniso
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    opac = 0.05 + 0.95 * torch.rand(n, generator=g, dtype=torch.float64)
    if sh_degree is None:
        colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    else:
        K_ = (sh_degree + 1) ** 2
        colors = 0.15 * torch.randn(n, K_, 3, generator=g, dtype=torch.float64)
        colors[:, 0] = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) / 0.2820947917738781
        colors[:, 1:] /= torch.arange(1, K_, dtype=torch.float64).sqrt()[None, :, None]
    f32 = lambda t: t.to(torch.float32).contiguous()  # noqa: E731
    return {"name": name or f"random N={n} {width}x{height}", "means": f32(means), "quats": f32(quats),
            "scales": f32(scales), "opacities": f32(opac), "colors": f32(colors),
            "viewmats": viewmats, "Ks": Ks, "width": width, "height": height, "sh_degree": sh_degree}


def scene_a(seed: int = 0, n: int = 100_000, width: int = 640, height: int = 352) -> dict:
    """Scene A: 100k Gaussians, one 640x352 camera, SH degree 3."""
    return random_frustum_scene(n, width, height, 3, seed, name=f"A: {n} Gaussians SH3, 1 cam {width}x{height}")


def scene_b(seed: int = 0, height: int = 176, width: int = 320) -> dict:
    """Scene B: one Gaussian per (non-sky) pixel of the 6-camera synthetic rig, same 6 views."""
    from clsplat.data.synthetic import SyntheticConfig, generate_sequence
    from clsplat.pixel_recon import lift_pixels

    seq = generate_sequence(SyntheticConfig(height=height, width=width, num_frames=1, seed=seed, lidar=False))
    g = lift_pixels(seq, 0)
    C = len(seq.cameras)
    return {"name": f"B: pixel-aligned, {g['means'].shape[0]} Gaussians, {C} cams {width}x{height}",
            "means": g["means"], "quats": g["quats"], "scales": g["scales"], "opacities": g["opacities"],
            "colors": g["colors"], "viewmats": torch.from_numpy(seq.viewmats(0).astype(np.float32)),
            "Ks": torch.from_numpy(seq.Ks().astype(np.float32)), "width": width, "height": height,
            "sh_degree": None}


def sweep_n(ns=(1_000, 10_000, 100_000, 1_000_000), width: int = 640, height: int = 352, seed: int = 0):
    """Scene-A-like scenes of growing N at a fixed resolution (same density of sizes)."""
    for n in ns:
        yield random_frustum_scene(int(n), width, height, 3, seed, name=f"N={int(n)}")


def sweep_pixels(sizes=((320, 176), (640, 352), (1280, 704), (1920, 1056)), n: int = 100_000,
                 seed: int = 0, base_width: int = 640):
    """The same 100k-Gaussian world rendered at growing resolutions (footprints grow with it)."""
    for w, h in sizes:
        yield random_frustum_scene(n, w, h, 3, seed, base_width=base_width, name=f"{w}x{h}")


def n_pixels(scene: dict) -> int:
    return int(scene["viewmats"].shape[0]) * scene["width"] * scene["height"]


def render_args(scene: dict) -> dict:
    """The keyword arguments of :func:`clsplat.rasterization` held by ``scene``."""
    return {k: scene[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks",
                                  "width", "height", "sh_degree")}
