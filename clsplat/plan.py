"""The render plan's memory: what a :func:`clsplat.rasterization` call will allocate, checked
against what the process may allocate before the buffers are made.

Two checks, each a one-line ValueError naming the sizes:

* :func:`check_pixel_memory`, before any work: the per-pixel buffers of every image of the
  call (B batch elements x C cameras x H x W pixels): the composited channels and final
  transmittance (the kernel's outputs), the alphas and, where they apply, the batch stack,
  the background blend and the expected-depth division; with gradients wanted, the last
  contributor (int32) and the incoming image gradients of the backward.
* :func:`check_intersection_memory`, once the (camera, Gaussian, tile) intersection count is
  known from the tile rectangles and before the keys are allocated: the keys and the sort's
  scratch (8 + 8 bytes each) or, with gradients wanted, the keys kept for the backward and its
  gradient slots (8 + max(8, slot values x real bytes)); besides the pixel buffers still to come.

The limit is :meth:`clsplat.runtime.Runtime.allowance`: the process's address-space limit
(``RLIMIT_AS``) less what is in use, else the host memory available now; on a device with
memory of its own (a GPU) its global memory too. The estimates count the buffers a call
holds at its peak (checked against ``VmPeak``, see :func:`pixel_plan`); they are
estimates (torch's temporaries vary with the loss), so a request near the limit may still fail
in the allocator.
"""
from __future__ import annotations

from dataclasses import dataclass

from .memory import fmt_bytes
from .runtime import HOST_CHECK_BYTES, Runtime

__all__ = ["PixelPlan", "pixel_plan", "intersection_bytes", "check_pixel_memory",
           "check_intersection_memory"]


@dataclass(frozen=True)
class PixelPlan:
    """The per-pixel buffers of one call: ``images`` (B x C) images of ``pixels`` (H x W)
    pixels, each holding ``real_values`` floats of ``real_bytes`` and ``int_values`` int32."""

    images: int
    pixels: int
    real_values: int
    real_bytes: int
    int_values: int

    @property
    def bytes_per_pixel(self) -> int:
        return self.real_values * self.real_bytes + 4 * self.int_values

    @property
    def nbytes(self) -> int:
        return self.images * self.pixels * self.bytes_per_pixel

    def describe(self) -> str:
        """The sizes, e.g. ``1 x 268435456 pixels x (13 values x 4 bytes + 1 x 4)``."""
        ints = f" + {self.int_values} x 4" if self.int_values else ""
        return (f"{self.images} x {self.pixels} pixels x ({self.real_values} values x "
                f"{self.real_bytes} bytes{ints})")


def pixel_plan(batch: int, cameras: int, height: int, width: int, colour_channels: int,
               depth_channel: bool, real_bytes: int, *, grad: bool, background: bool,
               expected_depth: bool) -> PixelPlan:
    """The per-pixel buffers of a call rendering ``batch`` x ``cameras`` images of
    ``height`` x ``width`` with ``colour_channels`` colour channels (plus a depth channel).

    Per pixel, in floats: CH (composited channels) + 1 (T) + 1 (alphas); the batch stack
    copies CH + 1 more when batch > 1; a background adds 2 x colour + CH (the blend and its
    concatenation); expected depth 2 + CH (clamp, divide, concatenate); gradients wanted,
    CH + 1 (the image and transmittance gradients the backward kernel reads) and an int32
    (the last contributor). Measured against ``VmPeak`` at 4096 x 4096 RGB float32: 20.2
    bytes a pixel forward (planned 20), 41.0 forward and backward of ``img.sum() +
    alphas.sum()`` (planned 40)."""
    ch = colour_channels + int(depth_channel)
    real = ch + 2
    if batch > 1:
        real += ch + 1
    if background and colour_channels:
        real += 2 * colour_channels + ch
    if expected_depth:
        real += 2 + ch
    if grad:
        real += ch + 1
    return PixelPlan(batch * cameras, height * width, real, real_bytes, int(grad))


def intersection_bytes(channels: int, real_bytes: int, *, grad: bool, absgrad: bool) -> int:
    """Bytes held per (camera, Gaussian, tile) intersection at the call's peak: the int64 key
    and the sort's scratch key; with ``grad`` the key kept for the backward and, at the
    backward's peak, the gradient slots (geometry 6, or 8 with ``absgrad``, + ``channels``
    values; see :func:`clsplat.stages.slot_width`) instead of the scratch key."""
    if not grad:
        return 16
    slots = ((8 if absgrad else 6) + channels) * real_bytes
    return 8 + max(8, slots)


def check_pixel_memory(rt: Runtime, plan: PixelPlan) -> None:
    """Refuse, naming the sizes, a call whose pixel buffers exceed what may be allocated."""
    need = plan.nbytes
    if need < HOST_CHECK_BYTES:
        return  # small: reading /proc per call cost more than such a render
    allowed, why = rt.allowance()
    if need > allowed:
        raise ValueError(
            f"width, height: the render's pixel buffers need about {fmt_bytes(need)} "
            f"({plan.describe()}), over the {fmt_bytes(allowed)} this process may allocate "
            f"({why}); render fewer cameras or smaller images per call")


def check_intersection_memory(rt: Runtime, intersections: int, per_intersection: int,
                              reserve: int = 0) -> None:
    """Refuse, naming the sizes, ``intersections`` x ``per_intersection`` bytes that do not fit
    in what may be allocated besides ``reserve`` bytes still to come (the pixel buffers)."""
    need = intersections * per_intersection
    if need + reserve < HOST_CHECK_BYTES:
        return
    allowed, why = rt.allowance()
    if need + reserve > allowed:
        besides = f" besides about {fmt_bytes(reserve)} of pixel buffers" if reserve else ""
        raise ValueError(
            f"means, scales: {intersections} (camera, Gaussian, tile) intersections need about "
            f"{fmt_bytes(need)} ({intersections} x {per_intersection} bytes){besides}, over the "
            f"{fmt_bytes(allowed)} this process may allocate ({why}); render fewer cameras, "
            "fewer or smaller Gaussians per call")
