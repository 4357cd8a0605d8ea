"""Input checks for the public API: every failure is a ValueError that names the argument.

Checks cover type, device, dtype, shape, finiteness and value ranges, so that nothing that
reaches a kernel can crash it or silently produce garbage. The value checks read the CPU
tensors through numpy: one reduction there costs a few microseconds against ~20 for the same
torch expression, and a small render's whole fixed cost is about 3 ms (bench/RESULTS.md,
"Issue 21").
"""
from __future__ import annotations

import numpy as np
import torch

from . import constants as K

__all__ = ["all_finite", "check_tensor", "check_finite", "check_int", "check_index_range",
           "check_rasterization_inputs", "check_options", "rescale_large_quats", "check_screen_extent"]

INT32_MAX = 2**31 - 1

_FLOATS = (torch.float32, torch.float64)


def check_tensor(name: str, x: object, shape: tuple, dtypes=_FLOATS) -> torch.Tensor:
    """``x`` must be a CPU torch tensor of a dtype in ``dtypes`` whose shape matches ``shape``.

    ``shape`` holds ints (exact), None (any) or strings (named sizes, only reported).
    """
    if not isinstance(x, torch.Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if x.layout != torch.strided:
        raise ValueError(f"{name}: expected a dense (strided) tensor, got layout {x.layout}; "
                         "call .to_dense() first")
    if x.device.type != "cpu":
        raise ValueError(f"{name}: expected a CPU tensor, got device {x.device}; clsplat moves "
                         "data to the OpenCL device itself")
    if x.dtype not in dtypes:
        raise ValueError(f"{name}: expected dtype in {[str(d) for d in dtypes]}, got {x.dtype}")
    if x.dim() != len(shape) or any(isinstance(s, int) and s != d for s, d in zip(shape, x.shape)):
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name}: expected shape {want}, got {list(x.shape)}")
    return x


def _values(x: torch.Tensor) -> np.ndarray:
    """The values of a CPU tensor as a numpy array (no copy; detached only where needed)."""
    return x.detach().numpy() if x.requires_grad else x.numpy()


def all_finite(v: np.ndarray) -> bool:
    """Whether the float array ``v`` holds no NaN or Inf.

    One pass and no temporary: a sum is NaN or Inf where any term is, so a finite sum settles it
    (about half the time of ``isfinite(v).all()``: 9 against 17 ms for 1M Gaussians' 48 SH
    coefficients, the largest input a call checks); only a sum that overflows (finite terms near
    the float range's end) takes the exact test. Quiet: an infinity or an overflow in the sum
    raises no RuntimeWarning (the caller reports the bad values itself)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return bool(np.isfinite(v.sum())) or bool(np.isfinite(v).all())


def check_finite(name: str, x: torch.Tensor, values: np.ndarray | None = None) -> None:
    """``x`` (float; ``values``: its numpy view, if at hand) holds no NaN or Inf."""
    if x.is_floating_point():
        if not all_finite(_values(x) if values is None else values):
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


def check_index_range(C: int, N: int, D: int, width: int, height: int) -> None:
    """The kernels index (camera, Gaussian) pairs and pixels with int32 arithmetic, up to
    3 values per pair (conics) and 4 per pixel row block; refuse sizes past that before any
    allocation."""
    if C * N * 4 > INT32_MAX:
        raise ValueError(f"means, viewmats: {C} cameras x {N} Gaussians = {C * N} pairs exceed "
                         f"the int32 index range of the kernels (at most {INT32_MAX // 4}); "
                         "render fewer cameras or Gaussians per call")
    if C * height * width > INT32_MAX or N * max(D, 3) > INT32_MAX:
        raise ValueError(f"width, height, colors: {C}x{height}x{width} pixels or {N}x{D} "
                         f"features exceed the int32 index range ({INT32_MAX})")


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
    eps2d_f = _check_float("eps2d", eps2d)
    if not 0 <= eps2d_f < float("inf"):
        raise ValueError(f"eps2d: must be finite and >= 0, got {eps2d}")
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

    q, o, k = _values(quats), _values(opacities), _values(Ks)
    for name, x, v in (("means", means, None), ("quats", quats, q), ("scales", scales, None),
                       ("opacities", opacities, o), ("colors", colors, None),
                       ("viewmats", viewmats, None), ("Ks", Ks, k)):
        check_finite(name, x, v)
    if N:
        # norm below 1e-12, in the quaternions' own precision: float32 squares of components
        # under ~1e-19 go subnormal or zero, still below 1e-24, and overflow only above ~1e19, far
        # from it, so no float64 copy (32 MB and ~15 ms at 1M Gaussians) is needed
        small = np.einsum("ij,ij->i", q, q) < 1e-24
        if small.any():
            raise ValueError(f"quats: {int(small.sum())} quaternion(s) have (near) zero norm, "
                             "which defines no rotation")
        if o.min() < 0 or o.max() > 1:
            raise ValueError("opacities: must lie in [0, 1] (post-activation opacities)")
    if min(k[:, 0, 0].min(), k[:, 1, 1].min()) <= 0:
        raise ValueError("Ks: focal lengths Ks[:, 0, 0] and Ks[:, 1, 1] must be > 0")
    check_index_range(C, N, D, width, height)
    # As in gsplat, only the top three rows of a view matrix are read (the last row gets a
    # zero gradient), so a perturbed last row is not an error.
    return {"C": C, "N": N, "D": D, "sh": sh_degree is not None}


def check_options(config: object, events: object) -> None:
    """``config`` must be None or a :class:`RenderConfig`; ``events`` None or a list."""
    from .config import RenderConfig
    if config is not None and not isinstance(config, RenderConfig):
        raise ValueError(f"config: expected a clsplat.RenderConfig or None, got {type(config).__name__}")
    if events is not None and not isinstance(events, list):
        raise ValueError(f"events: expected a list (filled with the launches' events) or None, "
                         f"got {type(events).__name__}")


#: quaternions whose largest component exceeds this are divided by it before the kernels
#: normalise them: their squared norm would overflow float32 (about 1.8e19 squared).
QUAT_RESCALE_ABOVE = 1e15


def rescale_large_quats(quats: torch.Tensor) -> torch.Tensor:
    """``[N, 4]`` -> ``[N, 4]``: rows whose largest |component| exceeds :data:`QUAT_RESCALE_ABOVE`
    divided by it (the rotation is unchanged; the divisor is detached, which gives exact gradients
    because the rotation does not depend on the quaternion's norm). Other rows are untouched,
    bitwise."""
    q = _values(quats)
    if q.size == 0 or max(q.max(), -q.min()) <= QUAT_RESCALE_ABOVE:  # (NaN rows: left as they are)
        return quats
    m = quats.detach().abs().amax(dim=-1, keepdim=True)
    big = m > QUAT_RESCALE_ABOVE
    return quats / torch.where(big, m, torch.ones_like(m))


#: the largest screen-space standard deviation (pixels) the kernels handle per precision: the 2D
#: covariance's determinant is a product of two variances, so sigma**4 must fit the float type.
MAX_SCREEN_SIGMA = {"float32": 1e9, "float64": 1e70}


def check_screen_extent(means: torch.Tensor, scales: torch.Tensor, viewmats: torch.Tensor,
                        Ks: torch.Tensor, near_plane: float, far_plane: float, precision: str) -> None:
    """Refuse Gaussians whose projected size overflows ``precision`` (they would render as nothing).

    means [N, 3], scales [N, 3], viewmats [C, 4, 4], Ks [C, 3, 3]. The bound is
    max|scale| * max(fx, fy) / depth for every visible (camera, Gaussian) pair, checked
    cheaply first with depth = near_plane.
    """
    if scales.shape[0] == 0:
        return
    limit = MAX_SCREEN_SIGMA[precision]
    k, sc = _values(Ks)[:, :2, :2], _values(scales)
    if (max(float(sc.max()), -float(sc.min())) * max(float(k.max()), -float(k.min())) / near_plane
            <= limit):  # every pair within the limit even at the near plane
        return
    f = Ks.detach().double()[:, :2, :2].abs().amax(dim=(1, 2))  # [C]
    s = scales.detach().double().abs().amax(dim=-1)  # [N]
    vm = viewmats.detach().double()
    z = means.detach().double() @ vm[:, 2, :3].T + vm[:, 2, 3]  # [N, C]
    vis = (z >= near_plane) & (z <= far_plane)
    sigma = s[:, None] * f[None, :] / z.clamp_min(near_plane)
    bad = vis & (sigma > limit)
    if bool(bad.any()):
        n = int(bad.any(dim=1).sum())
        if float(f.max()) > limit:  # no real camera: the culprit is the intrinsics, not the Gaussians
            c = int(f.argmax())
            raise ValueError(f"Ks: camera {c} has focal length {float(f[c]):.3g} px, over the {limit:g} px that "
                             f"{precision} can project with ({n} Gaussian(s) overflow the 2D covariance); check "
                             "the intrinsics' units")
        raise ValueError(f"scales: {n} Gaussian(s) project to a screen-space size over {limit:g} px "
                         f"(largest scale {float(s.max()):.3g}), which overflows {precision} in the "
                         f"2D covariance; use smaller scales" + (" or precision='float64'" if precision == "float32" else ""))
