"""Densification strategies in plain torch, with gsplat's interface, for clsplat's outputs.

gsplat's ``DefaultStrategy`` (3DGS: clone, split, prune, opacity reset) and ``MCMCStrategy``
(3DGS-as-MCMC: relocate dead Gaussians, add new ones, perturb positions) read only
``meta["means2d"].grad`` / ``.absgrad``, ``radii``, ``gaussian_ids``, ``width``, ``height``
and ``n_cameras``, which :func:`clsplat.rasterization` provides in gsplat's layouts. gsplat
itself is not a clsplat dependency, and its MCMC path calls two CUDA ops; this module is a
torch implementation of the same strategies, with the same constructor arguments, state and
callbacks, so that a gsplat training loop runs on the CPU unchanged apart from its imports.

For users who keep gsplat's own strategy classes on a machine without CUDA,
:func:`compute_relocation` and :func:`quat_scale_to_covar_preci` have the signatures of
gsplat's CUDA-backed ops and can be passed in in their place (``gsplat.strategy.ops``
looks both names up at call time)::

    import gsplat.strategy.ops as ops, clsplat.strategy as cs
    ops.compute_relocation, ops.quat_scale_to_covar_preci = cs.compute_relocation, cs.quat_scale_to_covar_preci

Parameters follow gsplat's convention: ``params`` maps names to [N, ...] leaves holding
``means``, raw log ``scales``, raw ``quats`` and logit ``opacities``; ``optimizers`` maps
each trainable name to an optimizer with one param group.

The package, as gsplat's ``gsplat.strategy``: :mod:`~clsplat.strategy.ops` (geometry, relocation
and the parameter / optimiser surgery, :func:`swap_parameter` among it),
:mod:`~clsplat.strategy.base` (:class:`Strategy`), :mod:`~clsplat.strategy.default`
(:class:`DefaultStrategy`) and :mod:`~clsplat.strategy.mcmc` (:class:`MCMCStrategy`); every
public name is importable from ``clsplat.strategy``.
"""
from __future__ import annotations

from .base import Strategy
from .default import DefaultStrategy
from .mcmc import MCMCStrategy
from .ops import (
    compute_relocation,
    duplicate,
    inject_noise_to_position,
    quat_scale_to_covar_preci,
    rebuild,
    relocate,
    remove,
    reset_opa,
    sample_add,
    split,
    swap_parameter,
)

__all__ = ["Strategy", "swap_parameter", "rebuild", "DefaultStrategy", "MCMCStrategy", "compute_relocation",
           "quat_scale_to_covar_preci", "duplicate", "split", "remove", "reset_opa",
           "relocate", "sample_add", "inject_noise_to_position"]
