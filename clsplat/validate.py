"""Input checks for the public API: every failure is a ValueError that names the argument.

Checks cover type, device, dtype, shape, finiteness and value ranges, so that nothing that
reaches a kernel can crash it or silently produce garbage.
"""
from __future__ import annotations

import torch

from . import constants as K

__all__ = ["check_tensor", "check_finite", "check_int", "check_rasterization_inputs"]

_FLOATS = (torch.float32, torch.float64)


def check_tensor(name: str, x: object, shape: tuple, dtypes=_FLOATS) -> torch.Tensor:
    """``x`` must be a CPU torch tensor of a dtype in ``dtypes`` whose shape matches ``shape``.

    ``shape`` holds ints (exact), None (any) or strings (named sizes, only reported).
    """
    if not isinstance(x, torch.Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if x.device.type != "cpu":
        raise ValueError(f"{name}: expected a CPU tensor, got device {x.device}; clsplat moves "
                         "data to the OpenCL device itself")
    if x.dtype not in dtypes:
        raise ValueError(f"{name}: expected dtype in {[str(d) for d in dtypes]}, got {x.dtype}")
    want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
    if x.dim() != len(shape) or any(isinstance(s, int) and s != d for s, d in zip(shape, x.shape)):
        raise ValueError(f"{name}: expected shape {want}, got {list(x.shape)}")
    return x


def check_finite(name: str, x: torch.Tensor) -> None:
    if x.is_floating_point() and not bool(torch.isfinite(x).all()):
        bad = int((~torch.isfinite(x)).sum())
        raise ValueError(f"{name}: contains {bad} NaN or Inf value(s)")


def check_int(name: str, v: object, lo: int, hi: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise ValueError(f"{name}: expected an int, got {type(v).__name__}")
    if not lo <= v <= hi:
        raise ValueError(f"{name}: must lie in [{lo}, {hi}], got {v}")
    return v


def _check_float(name: str, v: object) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"{name}: expected a number, got {type(v).__name__}")
    v = float(v)
    if v != v:
        raise ValueError(f"{name}: is NaN")
    return v


def check_rasterization_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width,
                               height, near_plane, far_plane, radius_clip, eps2d, sh_degree,
                               tile_size, backgrounds, render_mode) -> dict:
    """Validate the arguments of :func:`clsplat.rasterization`; returns derived sizes.

    Returns ``{"C", "N", "D", "sh": bool}`` where D is the number of colour channels.
    """
    means = check_tensor("means", means, ("N", 3))
    N = means.shape[0]
    check_tensor("quats", quats, (N, 4))
    check_tensor("scales", scales, (N, 3))
    check_tensor("opacities", opacities, (N,))
    viewmats = check_tensor("viewmats", viewmats, ("C", 4, 4))
    C = viewmats.shape[0]
    if C == 0:
        raise ValueError("viewmats: at least one camera is required, got C=0")
    check_tensor("Ks", Ks, (C, 3, 3))
    check_int("width", width, 1, K.MAX_IMAGE_SIDE)
    check_int("height", height, 1, K.MAX_IMAGE_SIDE)
    if render_mode not in K.RENDER_MODES:
        raise ValueError(f"render_mode: expected one of {K.RENDER_MODES}, got {render_mode!r}")
    if isinstance(tile_size, bool) or not isinstance(tile_size, int) or tile_size not in (4, 8, 16, 32):
        raise ValueError(f"tile_size: expected 4, 8, 16 or 32, got {tile_size!r}")
    near_plane = _check_float("near_plane", near_plane)
    far_plane = _check_float("far_plane", far_plane)
    if not near_plane > 0:
        raise ValueError(f"near_plane: must be > 0, got {near_plane}")
    if not far_plane > near_plane:
        raise ValueError(f"far_plane: must exceed near_plane ({near_plane}), got {far_plane}")
    if _check_float("eps2d", eps2d) < 0:
        raise ValueError(f"eps2d: must be >= 0, got {eps2d}")
    if _check_float("radius_clip", radius_clip) < 0:
        raise ValueError(f"radius_clip: must be >= 0, got {radius_clip}")

    if sh_degree is None:
        if not isinstance(colors, torch.Tensor) or colors.dim() not in (2, 3):
            raise ValueError(f"colors: expected [N, D] or [C, N, D] without sh_degree, got "
                             f"{list(colors.shape) if isinstance(colors, torch.Tensor) else type(colors).__name__}")
        check_tensor("colors", colors, (N, None) if colors.dim() == 2 else (C, N, None))
        D = colors.shape[-1]
        if D == 0:
            raise ValueError("colors: needs at least one channel, got D=0")
    else:
        check_int("sh_degree", sh_degree, 0, 4)
        per_view = isinstance(colors, torch.Tensor) and colors.dim() == 4
        check_tensor("colors", colors, (C, N, None, 3) if per_view else (N, None, 3))
        need = (sh_degree + 1) ** 2
        if colors.shape[-2] < need:
            raise ValueError(f"colors: sh_degree={sh_degree} needs {need} SH coefficients per "
                             f"Gaussian, got {colors.shape[1]}")
        D = 3
    if backgrounds is not None:
        check_tensor("backgrounds", backgrounds, (C, D))
        check_finite("backgrounds", backgrounds)

    for name, x in (("means", means), ("quats", quats), ("scales", scales),
                    ("opacities", opacities), ("colors", colors), ("viewmats", viewmats), ("Ks", Ks)):
        check_finite(name, x)
    qn = quats.detach().double().norm(dim=-1)
    if N and bool((qn < 1e-12).any()):
        raise ValueError(f"quats: {int((qn < 1e-12).sum())} quaternion(s) have (near) zero norm, "
                         "which defines no rotation")
    if N and bool(((opacities < 0) | (opacities > 1)).any()):
        raise ValueError("opacities: must lie in [0, 1] (post-activation opacities)")
    fx, fy = Ks[:, 0, 0], Ks[:, 1, 1]
    if bool(((fx <= 0) | (fy <= 0)).any()):
        raise ValueError("Ks: focal lengths Ks[:, 0, 0] and Ks[:, 1, 1] must be > 0")
    # As in gsplat, only the top three rows of a view matrix are read (the last row gets a
    # zero gradient), so a perturbed last row is not an error.
    return {"C": C, "N": N, "D": D, "sh": sh_degree is not None}
