"""Device limits respected, not assumed: local memory, kernel work-group sizes, wide features,
int32 index ranges, and faulty scan results (DESIGN.md section 4).

Wide features are composited in chunks of channels (gsplat's channel_chunk), so D = 4096
renders and differentiates like D = 3; every compositing kernel fits 48 KiB of local memory.
"""
from __future__ import annotations

from collections import OrderedDict

import pyopencl as cl
import pytest
import torch

import clsplat
from clsplat import reference as ref
from clsplat import stages
from clsplat.config import RenderConfig
from clsplat.runtime import LOCAL_MEM_BUDGET, Runtime

F64 = torch.float64


def _scene(D: int, dtype=F64, N: int = 6, W: int = 20, H: int = 16, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([(torch.rand(N, 2, generator=g, dtype=F64) - 0.5), 2 + torch.rand(N, 1, generator=g, dtype=F64)], 1)
    return dict(means=means.to(dtype), quats=(torch.randn(N, 4, generator=g, dtype=F64) + 0.1).to(dtype),
                scales=(0.1 + 0.2 * torch.rand(N, 3, generator=g, dtype=F64)).to(dtype),
                opacities=(0.3 + 0.6 * torch.rand(N, generator=g, dtype=F64)).to(dtype),
                colors=torch.rand(N, D, generator=g, dtype=F64).to(dtype),
                viewmats=torch.eye(4, dtype=dtype)[None],
                Ks=torch.tensor([[[20.0, 0, W / 2], [0, 20, H / 2], [0, 0, 1]]], dtype=dtype),
                width=W, height=H)


def _grads(fn, scene: dict, **kw):
    xs = {k: scene[k].clone().requires_grad_() for k in ("means", "quats", "scales", "opacities", "colors")}
    img, alpha, _ = fn(**{**scene, **xs}, **kw)
    C, H, W, D = img.shape  # channel c gets the same weights whatever D is
    ramp = torch.linspace(-1, 1, C * H * W, dtype=img.dtype).reshape(C, H, W, 1)
    w = ramp * (1 + 0.1 * torch.arange(D, dtype=img.dtype))
    ((img * w).sum() + alpha.sum()).backward()
    return img.detach(), {k: x.grad for k, x in xs.items()}


@pytest.mark.parametrize("D,dtype,absgrad", [pytest.param(4096, F64, False, marks=pytest.mark.slow),  # extreme width
                                             (40, torch.float32, True), (17, F64, True)])
def test_wide_features_match_reference(D, dtype, absgrad):
    """Past the old local-memory overflow (float64 from ~17 channels with absgrad, float32
    from ~40) and up to D = 4096, which segfaulted: images and gradients match the float64
    reference."""
    scene = _scene(D, dtype)
    img, g = _grads(clsplat.rasterization, scene, absgrad=absgrad)
    want_img, want_g = _grads(ref.rasterization, _scene(D))
    tol = 1e-9 if dtype == F64 else 2e-4
    assert float((img.double() - want_img).abs().max()) <= tol
    for k in g:
        scale = float(want_g[k].abs().max()) or 1.0
        assert float((g[k].double() - want_g[k]).abs().max()) <= tol * max(scale, 1.0), k


@pytest.mark.slow   # builds and runs every chunk width up to 4096 channels
def test_channel_chunks_are_bitwise_independent_of_width():
    """The first channels of a 70-channel render are bitwise those of a 3-channel render:
    chunks make the same decisions as one launch."""
    wide = _scene(70)
    narrow = dict(wide, colors=wide["colors"][:, :3].contiguous())
    a, ga = _grads(clsplat.rasterization, wide)
    b, gb = _grads(clsplat.rasterization, narrow)
    assert torch.equal(a[..., :3], b)
    assert torch.equal(ga["colors"][:, :3], gb["colors"])


@pytest.mark.parametrize("precision", ["float32", "float64"])
@pytest.mark.parametrize("CH", [3, pytest.param(40, marks=pytest.mark.slow), pytest.param(4096, marks=pytest.mark.slow)])
def test_compositing_kernels_fit_48k_local_memory(rt, precision, CH):
    """The kernels the engine builds for its layouts fit 48 KiB by the compiler's own count
    (stages._composite_kernel: on GPUs whose compiler adds local memory of its own, the batch
    shrinks until they do)."""
    cfg = RenderConfig(precision=precision)
    for tile in (8, 16, 32):
        pix, batch, chunk, _ = stages.composite_layout(rt, cfg, tile, CH)
        group = tile * tile // pix
        k = stages._composite_kernel(rt, cfg, "composite", cfg.defines(tile) | {
            "PIX": pix, "BATCH": batch, "CHANNELS": CH, "CCHUNK": chunk, "SAVE_LAST": True}, group, tile)
        local = k.get_work_group_info(cl.kernel_work_group_info.LOCAL_MEM_SIZE, rt.device)
        assert local <= LOCAL_MEM_BUDGET, (tile, local)
        for absgrad in (False, True):
            geom = 8 if absgrad else 6
            pix, batch, chunk, waves = stages.composite_layout(
                rt, cfg, tile, CH, geom_grads=geom, color_grad=True, backward=True)
            k = stages._composite_kernel(rt, cfg, "composite_bwd", cfg.defines(tile) | {
                "PIX": pix, "CHANNELS": CH, "CCHUNK": chunk, "GEOM_GRAD": True,
                "COLOR_GRAD": True, "ABSGRAD": absgrad, "BWD_DIVIDE": False,
                "SLOT_G": geom + CH, "SLOT_COLOR0": geom, "BATCH": batch, "WAVES": waves}, group, tile)
            local = k.get_work_group_info(cl.kernel_work_group_info.LOCAL_MEM_SIZE, rt.device)
            assert local <= LOCAL_MEM_BUDGET, (tile, absgrad, local)


def test_a_kernel_over_its_local_memory_is_rebuilt_with_a_smaller_batch(monkeypatch, rt):
    """Where the compiler counts more local memory than the layout planned, the batch shrinks
    (one rebuild per try) until the kernel fits; the image is the same."""
    scene = _scene(3, torch.float32)
    base = clsplat.rasterization(**scene)[0]
    real_build, batches = stages._build_composite_kernel_once, []

    def build(rt_, cfg, stage, defines, tile_size):  # a compiler that adds 4 KiB of its own
        batches.append(defines["BATCH"])
        k = real_build(rt_, cfg, stage, defines, tile_size)
        return _Reporting(k, rt_.local_mem + 4096) if len(batches) == 1 else k
    monkeypatch.setattr(stages, "_build_composite_kernel_once", build)
    monkeypatch.setattr(rt, "_plans", OrderedDict())
    monkeypatch.setattr(rt, "_group_limits", {})
    assert torch.equal(clsplat.rasterization(**scene)[0], base)
    assert len(batches) >= 2 and batches[1] < batches[0], batches


class _Reporting:
    """A kernel whose LOCAL_MEM_SIZE reads ``local``."""

    def __init__(self, k, local):
        self._k, self._local = k, local

    def get_work_group_info(self, what, device):
        if what == cl.kernel_work_group_info.LOCAL_MEM_SIZE:
            return self._local
        return self._k.get_work_group_info(what, device)

    def __getattr__(self, name):
        return getattr(self._k, name)


def test_gpu_sized_groups_fit_by_waves():
    """A 32x32 tile at one pixel per item (1024 items, a GPU's maximum, asked for with ``pix=1``)
    does not fit its backward partials in 48 KiB; the layout hands them over in waves instead of
    overflowing. By default a GPU takes 4 pixels per item there (groups within
    stages.GPU_DEFAULT_GROUP_MAX = 256 items, what NVIDIA's driver gives the float64 compositor)."""
    class FakeGPU:
        is_cpu, max_group, local_mem = False, 1024, LOCAL_MEM_BUDGET
    pix, batch, chunk, waves = stages.composite_layout(FakeGPU(), RenderConfig(precision="float64", pix=1),
                                                       32, 3, geom_grads=8, color_grad=True,
                                                       backward=True)
    assert pix == 1 and waves > 1 and batch >= 1
    for tile, want in ((32, 4), (16, 1), (8, 1)):
        got = stages.composite_layout(FakeGPU(), RenderConfig(precision="float64"), tile, 3)[0]
        assert got == want and tile * tile // got <= stages.GPU_DEFAULT_GROUP_MAX, (tile, got)


def test_kernel_work_group_limit_is_respected(monkeypatch, rt):
    """A kernel may allow less than the device maximum (CL_KERNEL_WORK_GROUP_SIZE):
    1D launches shrink to it; compositing, whose group is fixed by the tile, says so."""
    scene = _scene(3, torch.float32) | {"config": RenderConfig(pix=8)}  # PoCL's default on AVX2, set on any device
    base = clsplat.rasterization(**scene)[0]
    monkeypatch.setattr(Runtime, "kernel_group_limit", lambda self, k: 32)
    monkeypatch.setattr(rt, "_group_limits", {})
    with pytest.raises(ValueError, match="tile_size") as e:
        clsplat.rasterization(**scene, tile_size=32)
    assert "CL_KERNEL_WORK_GROUP_SIZE" in str(e.value)
    # tile 16 with 8 pixels per item: 32 items, within the limit; 1D stages run with 32
    assert torch.equal(clsplat.rasterization(**scene)[0], base)


def test_int32_pair_range_refused_before_allocation():
    C, N = 2**14, 2**15 + 1  # C*N*4 > 2^31 - 1 with ~2 MB of input
    vm = torch.eye(4).expand(C, 4, 4).contiguous()
    K = torch.tensor([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]]).expand(C, 3, 3).contiguous()
    with pytest.raises(ValueError, match=r"^means, viewmats: .*int32"):
        clsplat.rasterization(torch.zeros(N, 3), torch.tensor([[1.0, 0, 0, 0]]).expand(N, 4),
                              torch.full((N, 3), 0.1), torch.full((N,), 0.5), torch.zeros(N, 3),
                              vm, K, 16, 16)


def test_too_many_intersections_refused(monkeypatch, rt):
    """30,000 huge Gaussians over 2000x2000 (4.7e8 intersections, 7.5 GB of keys): refused
    from the tile rectangles before the keys are allocated, when memory does not hold them."""
    monkeypatch.setattr("clsplat.memory.available_host_memory", lambda: 2 << 30)
    monkeypatch.setattr("clsplat.memory._address_space_limit", lambda: None)
    N = 30000
    scene = dict(means=torch.zeros(N, 3) + torch.tensor([0, 0, 5.0]), quats=torch.tensor([[1.0, 0, 0, 0]]).expand(N, 4),
                 scales=torch.full((N, 3), 50.0), opacities=torch.full((N,), 0.5),
                 colors=torch.rand(N, 3), viewmats=torch.eye(4)[None],
                 Ks=torch.tensor([[[1000.0, 0, 1000], [0, 1000, 1000], [0, 0, 1]]]),
                 width=2000, height=2000)
    with pytest.raises(ValueError, match=r"^means, scales: 468750000 \(camera, Gaussian, tile\) "
                       r"intersections need about 7\.0 GiB \(468750000 x 16 bytes\) besides about "
                       r"76 MiB of pixel buffers, over the 2\.0 GiB this process may allocate"):
        clsplat.rasterization(**scene)


@pytest.mark.parametrize("sort_impl,layout", [("tiles", None), ("tiles", "bitonic"), ("depth", "bitonic")])
def test_garbage_scan_offsets_raise_instead_of_crashing(monkeypatch, rt, sort_impl, layout):
    """A faulty scan (an implementation that miscompiles pyopencl's scan, as Oclgrind's
    uninitialised checker makes it) must not send out-of-range offsets into the kernels: the
    scan is checked against the host's before its first use (Runtime.checked_scan_int32), on
    every path that scans on the device (the per-tile sort's binning; the depth sort's passes
    in the GPU layout)."""
    def bad_scan(self):
        def scan(a, b, queue=None):
            garbage = torch.randint(-2**30, 2**30, (b.shape[0],), dtype=torch.int32).numpy()
            return cl.enqueue_copy(queue, b.data, garbage)
        return scan
    monkeypatch.setattr(Runtime, "exclusive_scan_int32", bad_scan)
    monkeypatch.setenv("CLSPLAT_HOST_SCAN", "0")  # the device's scan, wherever the host's is the default
    cfg = RenderConfig(sort_impl=sort_impl, sort_layout=layout)
    with pytest.raises(RuntimeError, match="^scan: the device's prefix scan returned inconsistent sums"):
        clsplat.rasterization(**_scene(3, torch.float32), config=cfg)


def test_the_scan_self_test_passes_on_a_sound_scan(monkeypatch, rt):
    """The same renders with the real scan on the device: the check passes, the images equal
    the host scan's."""
    scene = _scene(3, torch.float32)
    monkeypatch.setenv("CLSPLAT_HOST_SCAN", "1")
    want = [clsplat.rasterization(**scene, config=RenderConfig(sort_impl=s, sort_layout="bitonic"))[0]
            for s in ("tiles", "depth")]
    monkeypatch.setenv("CLSPLAT_HOST_SCAN", "0")
    for s, w in zip(("tiles", "depth"), want):
        img = clsplat.rasterization(**scene, config=RenderConfig(sort_impl=s, sort_layout="bitonic"))[0]
        assert torch.equal(img, w), s
