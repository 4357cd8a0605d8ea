"""Build-time configuration of the pipeline: precision, tiling and the accuracy knobs.

A :class:`RenderConfig` becomes the ``-D`` options every stage is specialised with, so each
distinct configuration is its own cached set of programs.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from . import constants as K

__all__ = ["RenderConfig"]


@dataclass(frozen=True)
class RenderConfig:
    """Accuracy and layout knobs (DESIGN.md §6). Defaults reproduce gsplat's semantics.

    precision:    "float32", "float64" (needs cl_khr_fp64), or None: the dtype of the means.
    alpha_min:    samples with alpha below it are skipped.
    alpha_max:    alpha is clamped to it, with no gradient through the clamp: 0.999 as in
                  gsplat; 0.99 is the original 3DGS value.
    t_min:        a pixel stops before the sample that would take its transmittance to <= t_min.
    radius_rule:  "opacity" (gsplat's default: per axis min(3.33, sqrt(2 ln(o / alpha_min)))
                  sigmas, culling o < alpha_min), "3.33sigma" (fixed) or "4sigma".
    fast_math:    build with -cl-fast-relaxed-math.
    pix:          pixels per work-item in compositing (None: one 256-bit vector on CPUs,
                  i.e. 8 floats or 4 doubles; on GPUs 1, or as many as keep a tile's group
                  within 256 items: 4 for 32x32 tiles, stages.GPU_DEFAULT_GROUP_MAX).
    sort_local:   keys sorted in local memory per work-group (None: from device limits).
    sort_layout:  "serial" (CPU default) or "bitonic" (GPU default). With sort_impl "depth":
                  the serial layout walks a few long chunks per compute unit, the GPU layout
                  many short ones (kernels/order.cl). With "tiles": a merge sort per segment
                  and work-item, or a work-group per segment in local memory.
    sort_impl:    "depth" (the pairs sorted once by depth, then placed into their tiles by a
                  stable counting pass, kernels/order.cl; issue 35) or "tiles" (keys scattered
                  into tile segments by atomics, each segment then sorted, kernels/bin.cl +
                  sort.cl). Both give the same tile lists, key for key. None: "depth" on CPU
                  devices, "tiles" on GPUs, where it was measured the faster
                  (:func:`clsplat.stages.sort_by_depth`).
    sort_chunks:  work-items (chunks) of kernels/order.cl's passes (None: from the layout and
                  the device; tests set it to exercise many chunks on tiny scenes).
    composite_impl: "tuned" (kernels/composite.cl and composite_bwd.cl built with CLS_TUNED=1:
                  inline maths instead of the OpenCL library builtins PoCL's CPU device cannot
                  inline, extent tests a word of samples at a time; CPU default) or "baseline"
                  (the same files with CLS_TUNED=0, the kernels before issue 21 item 5; GPU
                  default). None: by device. Both give the same images and gradients.
    backward_impl: "pixel" (kernels/composite_bwd.cl: a work-item per row segment of pixels, the
                  group summing each Gaussian's per-item partials in local memory) or "gaussian"
                  (kernels/composite_bwd_gauss.cl: a work-item per tile walks its Gaussians and
                  sums each one's gradient over the tile's pixels in registers; issue 35). None:
                  "gaussian" on PoCL's CPU device, "pixel" elsewhere
                  (:func:`clsplat.stages.backward_gaussian`). Both write the same
                  per-intersection slots, equal to rounding; each is bitwise reproducible.
    """

    precision: str | None = None
    alpha_min: float = K.ALPHA_MIN
    alpha_max: float = K.ALPHA_MAX
    t_min: float = K.T_MIN
    radius_rule: str = "opacity"
    fast_math: bool = False
    pix: int | None = None
    sort_local: int | None = None
    sort_layout: str | None = None
    sort_impl: str | None = None
    sort_chunks: int | None = None
    composite_impl: str | None = None
    backward_impl: str | None = None

    def __post_init__(self) -> None:
        for name in ("pix", "sort_local", "sort_chunks"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int)):
                raise ValueError(f"{name}: expected an int or None, got {v!r} ({type(v).__name__})")
        for name in ("alpha_min", "t_min"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ValueError(f"{name}: expected a number, got {v!r} ({type(v).__name__})")
        if not isinstance(self.fast_math, bool):
            raise ValueError(f"fast_math: expected True or False, got {self.fast_math!r}")
        if self.precision not in (None, "float32", "float64"):
            raise ValueError(f"precision: expected 'float32' or 'float64', got {self.precision!r}")
        if not 0.0 < self.alpha_max < 1.0:
            raise ValueError(f"alpha_max: must lie in (0, 1), got {self.alpha_max}")
        if not 0.0 <= self.alpha_min < self.alpha_max:
            raise ValueError(f"alpha_min: must lie in [0, alpha_max={self.alpha_max}), got {self.alpha_min}")
        if not 0.0 <= self.t_min < 1.0:
            raise ValueError(f"t_min: must lie in [0, 1), got {self.t_min}")
        if self.radius_rule not in K.RADIUS_RULES:
            raise ValueError(f"radius_rule: expected one of {K.RADIUS_RULES}, got {self.radius_rule!r}")
        if self.pix is not None and self.pix not in (1, 2, 4, 8, 16):
            raise ValueError(f"pix: expected 1, 2, 4, 8 or 16, got {self.pix}")
        if self.sort_layout not in (None, "serial", "bitonic"):
            raise ValueError(f"sort_layout: expected 'serial' or 'bitonic', got {self.sort_layout!r}")
        if self.sort_impl not in (None, "depth", "tiles"):
            raise ValueError(f"sort_impl: expected 'depth' or 'tiles', got {self.sort_impl!r}")
        if self.sort_chunks is not None and self.sort_chunks < 1:
            raise ValueError(f"sort_chunks: must be >= 1, got {self.sort_chunks}")
        if self.composite_impl not in (None, "tuned", "baseline"):
            raise ValueError(f"composite_impl: expected 'tuned' or 'baseline', got {self.composite_impl!r}")
        if self.backward_impl not in (None, "pixel", "gaussian"):
            raise ValueError(f"backward_impl: expected 'pixel' or 'gaussian', got {self.backward_impl!r}")
        if self.sort_local is not None and (self.sort_local < 2 or self.sort_local & (self.sort_local - 1)):
            raise ValueError(f"sort_local: must be a power of two >= 2, got {self.sort_local}")

    def with_(self, **changes) -> "RenderConfig":
        return replace(self, **changes)

    @property
    def dtype(self) -> torch.dtype:
        return torch.float64 if self.precision == "float64" else torch.float32

    def defines(self, tile_size: int) -> dict[str, object]:
        """The -D options shared by every stage."""
        return {
            "REAL_DOUBLE": self.precision == "float64",
            "TILE": tile_size,
            "ALPHA_MIN": float(self.alpha_min),
            "ALPHA_MAX": float(self.alpha_max),
            "T_MIN": float(self.t_min),
            "RADIUS_SIGMA": 4.0 if self.radius_rule == "4sigma" else K.RADIUS_SIGMA,
            "OPACITY_AWARE_RADIUS": self.radius_rule == "opacity",
        }
