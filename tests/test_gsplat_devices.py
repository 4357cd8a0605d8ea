"""Tensors on another torch device: rasterization() takes them, renders on the OpenCL device and
returns images, meta and gradients on the inputs' device, bitwise equal to the CPU run.

CPU-only torch has no second device with data, so this file defines one: a "foreign" torch
device (PrivateUse1, registered from Python) whose tensors keep their values in CPU memory but
report ``device == foreign:0`` and go through torch's device-transfer ops (``_to_copy``,
``empty_strided``, ``copy_``) exactly as CUDA tensors do. Registering a backend changes the
process for good, so the checks run in a child process: this file executed as a script.
"""
from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch


@pytest.mark.slow   # spawns a foreign-device child
def test_foreign_device_round_trip():
    env = dict(os.environ, OMP_NUM_THREADS="1")
    r = subprocess.run([sys.executable, __file__], capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    assert r.stdout.count("ok") == 5, r.stdout


# ---- the child process ------------------------------------------------------------------------

def _register_foreign_device() -> torch.device:
    """A PrivateUse1 device named "foreign" whose tensors wrap CPU tensors."""
    from torch.utils._pytree import tree_map
    from torch.utils.backend_registration import _setup_privateuseone_for_python_backend

    _setup_privateuseone_for_python_backend("foreign")
    dev = torch.device("foreign:0")

    class Foreign(torch.Tensor):
        @staticmethod
        def __new__(cls, data: torch.Tensor):
            strides = data.stride() if data.layout == torch.strided else None
            t = torch.Tensor._make_wrapper_subclass(cls, data.shape, strides=strides,
                                                    dtype=data.dtype, layout=data.layout,
                                                    device=dev, requires_grad=False)
            t.data_cpu = data
            return t

        @classmethod
        def __torch_dispatch__(cls, func, types, args=(), kwargs=None):
            kwargs = kwargs or {}
            unwrap = lambda x: x.data_cpu if isinstance(x, Foreign) else x  # noqa: E731
            if func is torch.ops.aten._to_copy.default:
                target = kwargs.get("device")
                out = func(unwrap(args[0]), **{k: v for k, v in kwargs.items() if k != "device"})
                stays = target.type == "foreign" if target is not None else isinstance(args[0], Foreign)
                return Foreign(out) if stays else out
            kwargs = {k: (torch.device("cpu") if isinstance(v, torch.device) else v)
                      for k, v in kwargs.items()}
            if func._schema.is_mutable:  # in place: the result is the argument itself
                func(*tree_map(unwrap, args), **tree_map(unwrap, kwargs))
                return args[0]
            out = func(*tree_map(unwrap, args), **tree_map(unwrap, kwargs))
            return tree_map(lambda x: Foreign(x) if isinstance(x, torch.Tensor) else x, out)

    def empty_strided(size, stride, dtype=None, layout=None, device=None, pin_memory=None):
        return Foreign(torch.empty_strided(size, stride, dtype=dtype))

    _register_foreign_device.lib = torch.library.Library("aten", "IMPL")  # keep it alive
    _register_foreign_device.lib.impl("empty_strided", empty_strided, "PrivateUse1")
    return dev


def _scene(batch: tuple = (), sh_degree=None, dtype=torch.float32) -> dict:
    g = torch.Generator().manual_seed(3)
    N, C = 50, 2
    vm = torch.eye(4).expand(batch + (C, 4, 4)).clone()
    vm[..., 1, 0, 3] = 0.3  # the second camera a little to the side
    K = (sh_degree + 1) ** 2 if sh_degree is not None else None
    return dict(
        means=torch.randn(batch + (N, 3), generator=g) * 0.5 + torch.tensor([0, 0, 4.0]),
        quats=torch.randn(batch + (N, 4), generator=g),
        scales=torch.rand(batch + (N, 3), generator=g) * 0.4 - 0.2,  # either sign, as in gsplat
        opacities=torch.rand(batch + (N,), generator=g),
        colors=torch.rand(batch + ((N, 3) if K is None else (N, K, 3)), generator=g) - 0.2 * (K is not None),
        viewmats=vm, Ks=torch.tensor([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]]).expand(batch + (C, 3, 3)).clone(),
        backgrounds=torch.rand(batch + (C, 3), generator=g))


def _check(dev: torch.device, name: str, dtype=torch.float32, **kw) -> None:
    """Render the same scene from ``dev`` tensors and from CPU tensors; everything must match."""
    batch, sh = kw.pop("batch", ()), kw.get("sh_degree")
    scene = {k: v.to(dtype) for k, v in _scene(batch, sh).items()}
    grads = {}
    runs = []
    for where in (dev, torch.device("cpu")):
        xs = {k: v.to(where).requires_grad_(k != "Ks") for k, v in scene.items()}
        img, alpha, meta = __import__("clsplat").rasterization(**xs, width=32, height=24, absgrad=True,
                                                               precision="float32", **kw)
        assert img.device == alpha.device == meta["means2d"].device == where, name
        assert img.dtype == alpha.dtype == dtype, name
        for k in ("radii", "depths", "conics", "opacities", "isect_ids", "flatten_ids", "isect_offsets"):
            assert meta[k].device == where, (name, k)
        meta["means2d"].retain_grad()
        w = torch.linspace(0, 1, img.numel(), dtype=dtype).reshape(img.shape)
        (img * w.to(where)).sum().backward()
        grads = {k: x.grad for k, x in xs.items() if k != "Ks"}
        for k, gr in grads.items():
            assert gr is not None and gr.device == where and gr.dtype == dtype, (name, k)
        runs.append((img, alpha, meta, grads))
    (img, alpha, meta, g_dev), (img_c, alpha_c, meta_c, g_cpu) = runs
    assert torch.equal(img.cpu(), img_c) and torch.equal(alpha.cpu(), alpha_c), name
    for k in ("radii", "means2d", "isect_ids", "flatten_ids"):
        assert torch.equal(meta[k].cpu(), meta_c[k]), (name, k)
    assert torch.equal(meta["means2d"].grad.cpu(), meta_c["means2d"].grad), name
    assert torch.equal(meta["means2d"].absgrad.cpu(), meta_c["means2d"].absgrad), name
    for k in g_dev:
        assert torch.equal(g_dev[k].cpu(), g_cpu[k]), (name, k)
    print("ok", name)


def _check_sparse(dev: torch.device) -> None:
    """sparse_grad: means, quats and scales get sparse COO gradients on the inputs' device."""
    import clsplat
    scene = _scene()
    grads = []
    for where in (dev, torch.device("cpu")):
        xs = {k: v.to(where).requires_grad_(k != "Ks") for k, v in scene.items()}
        img, _, _ = clsplat.rasterization(**xs, width=32, height=24, sparse_grad=True)
        img.sum().backward()
        for k in ("means", "quats", "scales"):
            assert xs[k].grad.is_sparse and xs[k].grad.device == where, k
        grads.append({k: x.grad.to_dense() for k, x in xs.items() if k != "Ks"})
    for k in grads[0]:
        assert torch.equal(grads[0][k].cpu(), grads[1][k]), k
    print("ok sparse_grad")


if __name__ == "__main__":
    dev = _register_foreign_device()
    _check(dev, "packed")
    _check(dev, "unpacked, SH degree 2", packed=False, sh_degree=2)
    _check(dev, "batch dims (2,), RGB+ED", packed=False, batch=(2,), render_mode="RGB+ED")
    _check(dev, "float64 in, float32 rendered", dtype=torch.float64, rasterize_mode="antialiased")
    _check_sparse(dev)
