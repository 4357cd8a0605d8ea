"""clsplat.runtime: device choice, program and kernel caches, device description."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest
import torch

import clsplat


def _skip_where_the_pool_is_off(rt) -> None:
    """Skip a test of the array pool or the kept inputs where they are off by design: they exist only
    where the device computes in the arrays' host memory (PoCL's CPU device, not with
    ``CLSPLAT_HOST_MEMORY=copy``; :attr:`Runtime.pools`' device part), so nothing there to test."""
    if not (rt.computes_in_host_memory and rt.shares_host_memory):
        pytest.skip("the pool and kept inputs are on only where the device computes in host memory "
                    "(PoCL's CPU device, not with CLSPLAT_HOST_MEMORY=copy)")


def _pocl_spec() -> str:
    """The "platform:device" index of PoCL's first device (not assumed to be 0:0: on a GPU host
    the GPU driver's platform may come first)."""
    import pyopencl as cl

    for i, p in enumerate(cl.get_platforms()):
        if "portable computing language" in p.name.lower() and p.get_devices():
            return f"{i}:0"
    pytest.fail("PoCL is a dependency of clsplat, but no PoCL platform was found")


POCL = _pocl_spec()


def test_device_by_argument():
    a = clsplat.get_runtime(POCL)
    c = clsplat.get_runtime("cpu")
    p = clsplat.get_runtime("portable")
    assert "portable computing language" in a.name.lower()
    for r in (a, c, p):
        assert r.device.int_ptr == a.device.int_ptr and r.is_cpu
    assert clsplat.get_runtime(POCL) is a  # runtimes are cached per spec
    assert clsplat.get_runtime(a) is a


def test_device_pocl_by_name():
    """The runtime docstring (and DESIGN.md) name PoCL's device "pocl"; PoCL's platform name is
    "Portable Computing Language" (vendor "The pocl project"), so the label must carry it."""
    r = clsplat.get_runtime("pocl")
    assert r.device.int_ptr == clsplat.get_runtime(POCL).device.int_ptr


def test_device_by_environment(monkeypatch):
    monkeypatch.setenv("CLSPLAT_DEVICE", POCL)
    assert clsplat.get_runtime().device.int_ptr == clsplat.get_runtime(POCL).device.int_ptr
    monkeypatch.setenv("CLSPLAT_DEVICE", "no-such-device")
    with pytest.raises(clsplat.DeviceError, match="device"):
        clsplat.get_runtime()


@pytest.mark.parametrize("spec", ["no-such-device", "9:9", "0:99"])
def test_unknown_device(spec):
    with pytest.raises(clsplat.DeviceError) as exc:
        clsplat.get_runtime(spec)
    assert isinstance(exc.value, ValueError)
    assert str(exc.value).startswith("device") and spec in str(exc.value)
    assert POCL in str(exc.value)  # lists what is available


def test_device_wrong_type():
    with pytest.raises(clsplat.DeviceError, match="device"):
        clsplat.get_runtime(0)


def test_program_and_kernel_cache(rt):
    d = {"SORT_LOCAL": 64}
    p1 = rt.program("sort", d)
    assert rt.program("sort", dict(d)) is p1
    assert rt.program("sort", {"SORT_LOCAL": 128}) is not p1
    assert rt.program("sort", d, fast_math=True) is not p1
    k1 = rt.kernel("sort", "sort_local", d)
    assert rt.kernel("sort", "sort_local", d) is k1
    assert rt.kernel("sort", "merge_runs", d) is not k1
    n_prog, n_kern = len(rt._programs), len(rt._kernels)
    for _ in range(3):
        rt.kernel("sort", "sort_local", d)
    assert (len(rt._programs), len(rt._kernels)) == (n_prog, n_kern)


def _failing_builds(monkeypatch, fails: int) -> list[int]:
    """Make the next ``fails`` program builds of clsplat.runtime fail as PoCL's kernel-cache race
    does (BUILD_PROGRAM_FAILURE, no compiler diagnostic); returns the list the builds are counted in."""
    import pyopencl as cl

    from clsplat import runtime

    calls: list[int] = []

    class Flaky(cl.Program):
        def build(self, *args, **kwargs):
            calls.append(1)
            if len(calls) <= fails:
                raise cl.RuntimeError(cl._cl._ErrorRecord("clBuildProgram failed: BUILD_PROGRAM_FAILURE",
                                                          cl.status_code.BUILD_PROGRAM_FAILURE,
                                                          "Device failed to build the program"))
            return super().build(*args, **kwargs)

    monkeypatch.setattr(runtime.cl, "Program", Flaky)
    return calls


def test_a_build_that_fails_as_pocls_cache_race_does_is_built_again(monkeypatch):
    """PoCL 3.0's kernel cache races between processes (pocl/pocl#1480): a build fails with an empty
    log and succeeds when made again. On PoCL a failed build is made up to BUILD_RETRIES more times
    before it counts; one more failure than that is reported as the BuildError it is."""
    from clsplat.runtime import BUILD_RETRIES

    rt = clsplat.get_runtime(POCL)
    d = {"SORT_LOCAL": 64, "UNUSED_TAG": "retried"}   # a program no other test has built here
    calls = _failing_builds(monkeypatch, BUILD_RETRIES)
    assert rt.program("sort", d) is rt.program("sort", d)
    assert len(calls) == BUILD_RETRIES + 1
    calls = _failing_builds(monkeypatch, BUILD_RETRIES + 1)
    with pytest.raises(clsplat.BuildError, match="failed to build"):
        rt.program("sort", dict(d, UNUSED_TAG="failed"))
    assert len(calls) == BUILD_RETRIES + 1


def test_renders_reuse_programs(make_scene):
    scene = make_scene(0, N=20, C=1, width=32, height=24, dtype=torch.float32)
    rt = clsplat.get_runtime()
    clsplat.rasterization(**scene)
    n_prog, n_kern = len(rt._programs), len(rt._kernels)
    clsplat.rasterization(**scene)
    assert (len(rt._programs), len(rt._kernels)) == (n_prog, n_kern)


def test_describe_devices():
    text = clsplat.describe_devices()
    assert POCL in text and "Portable Computing Language" in text
    for feat in ("fp64: yes", "int64 atomics", "float atomics", "subgroups", "max work-group"):
        assert feat in text
    assert "*" in text  # the default device is marked


def test_device_array_roundtrip(rt):
    t = torch.arange(10, dtype=torch.float32)
    a = rt.array(t)
    assert torch.equal(a.host(), t)
    assert rt.array(torch.zeros(0)).host().numel() == 0
    with pytest.raises(ValueError):
        rt.array(torch.zeros(3, device="meta"))


def test_pocl_group_limit_is_in_effect(rt):
    assert rt.max_group <= 256  # POCL_MAX_WORK_GROUP_SIZE=256, set by conftest (DESIGN.md §4)


_PIX_SCRIPT = textwrap.dedent("""
    import os, sys, math, torch
    os.environ.setdefault("POCL_MAX_WORK_GROUP_SIZE", "256")
    import clsplat
    g = torch.Generator().manual_seed(0)
    N = 40
    means = torch.cat([(torch.rand(N, 2, generator=g) - 0.5), 2 + torch.rand(N, 1, generator=g)], 1)
    kw = dict(means=means, quats=torch.randn(N, 4, generator=g) + 0.1, scales=torch.full((N, 3), 0.1),
              opacities=torch.full((N,), 0.7), colors=torch.rand(N, 3, generator=g),
              viewmats=torch.eye(4)[None], Ks=torch.tensor([[[30.0, 0, 16], [0, 30, 16], [0, 0, 1]]]),
              width=32, height=32)
    prec, pix = sys.argv[1], int(sys.argv[2])
    base = clsplat.rasterization(**kw, config=clsplat.RenderConfig(precision=prec, pix=1))[0]
    try:
        img = clsplat.rasterization(**kw, config=clsplat.RenderConfig(precision=prec, pix=pix))[0]
    except (ValueError, clsplat.BuildError) as e:
        print("REJECTED", type(e).__name__, str(e).splitlines()[0]); sys.exit(0)
    err = float((img - base).abs().max())
    print("ERR", err); sys.exit(0 if err <= 1e-6 else 3)
""")


@pytest.mark.slow   # spawns an interpreter per layout
@pytest.mark.parametrize("precision,pix", [("float32", 16), ("float64", 8), ("float64", 16)])
def test_wide_pix_layouts_work_or_are_rejected(precision, pix):
    """RenderConfig accepts pix up to 16. Where the device cannot run that vector width (PoCL
    without AVX-512 gives no kernel, a crash or wrong images for float16/double8/double16), the
    engine must say so with a ValueError or BuildError instead. Run in a subprocess because the
    failure mode can be a segfault."""
    env = dict(os.environ, POCL_MAX_WORK_GROUP_SIZE="256")
    p = subprocess.run([sys.executable, "-c", _PIX_SCRIPT, precision, str(pix)], env=env,
                       capture_output=True, text=True, timeout=120)
    tail = (p.stdout + p.stderr)[-600:]
    assert p.returncode == 0, f"rc={p.returncode}: {tail}"


def test_copying_path_of_discrete_devices_matches_zero_copy(make_scene, monkeypatch):
    """GPUs do not share host memory: DeviceArray then copies in and out. Forcing that path
    on PoCL must give bitwise the same images and gradients as the zero-copy path."""
    import torch

    import clsplat
    from clsplat.runtime import Runtime

    scene = make_scene(seed=12, N=120, C=2, dtype=torch.float32)

    def run():
        xs = [scene[k].clone().requires_grad_() for k in ("means", "quats", "scales", "opacities", "colors")]
        r, a, _ = clsplat.rasterization(*xs, scene["viewmats"], scene["Ks"], scene["width"],
                                        scene["height"], render_mode="RGB+ED")
        (r.sum() + a.sum()).backward()
        return [r.detach(), a.detach()] + [x.grad for x in xs]

    shared = run()
    monkeypatch.setattr(Runtime, "shares_host_memory", property(lambda self: False))
    monkeypatch.setattr(clsplat.get_runtime(), "_pools_device", None)  # (worked out once: again)
    copied = run()
    for x, y in zip(shared, copied):
        assert torch.equal(x, y)


def test_small_render_waits_on_the_queue_few_times(make_scene, monkeypatch):
    """The fixed cost of a call is mostly waits on the queue (each wakes PoCL's workers): a
    forward + backward of one camera waits once per stage that reads results back, and
    arrays nothing launched into since their creation or last read are never waited for."""
    from clsplat.runtime import read_back
    rt = clsplat.get_runtime()
    scene = make_scene(0, N=40, C=1, width=32, height=24, dtype=torch.float32)
    for k in ("means", "quats", "scales", "opacities", "colors"):
        scene[k] = scene[k].clone().requires_grad_()
    clsplat.rasterization(**scene)[0].sum().backward()  # builds the programs
    waits = []
    real = rt.finish
    monkeypatch.setattr(rt, "finish", lambda: (waits.append(1), real())[1])
    launches = rt.launches
    img, alpha, _ = clsplat.rasterization(**scene)
    (img.sum() + alpha.sum()).backward()
    # project (with the tile lists launched behind it, stages.early_tile_lists), composite,
    # the backward's compositing (with the slots' sum, FUSED_REDUCE), project_bwd; on the
    # copying path (CLSPLAT_HOST_MEMORY=copy) the tile lists wait once more, no early launch there
    assert len(waits) <= (4 if rt.pools else 5), len(waits)
    if rt.pools and clsplat.stages.backward_gaussian(rt, clsplat.RenderConfig()):
        assert rt.launches - launches == 5  # those, and order_small
    waits.clear()
    a = rt.array(torch.arange(10, dtype=torch.float32))
    assert torch.equal(read_back(a)[0], torch.arange(10, dtype=torch.float32)) and not waits
    out = rt.empty((10,), torch.float32)  # written by a launch: read back with one wait
    k = rt.kernel("reduce", "reduce_slots", {"REAL_DOUBLE": False, "CHANNELS": 1, "GEOM_GRAD": False,
                                              "COLOR_GRAD": False, "ABSGRAD": False})
    assert k is rt.kernel("reduce", "reduce_slots", {"ABSGRAD": False, "COLOR_GRAD": False,
                                                     "GEOM_GRAD": False, "CHANNELS": 1,
                                                     "REAL_DOUBLE": False})
    rt.launches += 1  # as a launch writing ``out`` would
    read_back(out)
    assert len(waits) == 1
    read_back(out)  # nothing launched since
    assert len(waits) == 1


def test_scratch_memory_is_zeroed_reused_and_never_shared_by_two_blocks(monkeypatch):
    rt = clsplat.get_runtime()
    rt.release_scratch()
    monkeypatch.setattr(rt, "pool_limit", 0)  # small blocks come from the array pool otherwise
    with rt.scratch() as alloc:
        a = alloc((1000, 9), torch.float32)
        a.tensor.fill_(7)
        ptr = a.tensor.data_ptr()
        with rt.scratch() as alloc2:  # a block inside (another thread's): its own memory
            b = alloc2((10,), torch.float64)
            assert b.tensor.data_ptr() != ptr and not b.tensor.any()
    with rt.scratch() as alloc:  # the largest block handed back is handed out again, zeroed
        c = alloc((500, 9), torch.int32)
        assert c.tensor.data_ptr() == ptr and not c.tensor.any() and c.tensor.shape == (500, 9)
    with rt.scratch() as alloc:  # larger than what is kept: fresh memory
        assert alloc((2000, 9), torch.float32).tensor.data_ptr() != ptr
    rt.release_scratch()


def test_render_plan_is_reused_per_shape_and_bounded(make_scene):
    """Runtime.plan: a second forward + backward of one shape builds no plan entry (every
    per-shape piece is found), and its results are bitwise the first's; the cache keeps at most
    PLAN_CACHE_SIZE entries, least recently used dropped first; a build that raises is not kept."""
    from clsplat.runtime import PLAN_CACHE_SIZE
    rt = clsplat.get_runtime()
    scene = make_scene(0, N=40, C=1, width=32, height=24, dtype=torch.float32)
    for k in ("means", "quats", "scales", "opacities", "colors"):
        scene[k] = scene[k].clone().requires_grad_()

    def render() -> list[torch.Tensor]:
        img, alpha, _ = clsplat.rasterization(**scene)
        (img.sum() + alpha.sum()).backward()
        grads = [scene[k].grad for k in ("means", "quats", "scales", "opacities", "colors")]
        for k in ("means", "quats", "scales", "opacities", "colors"):
            scene[k].grad = None
        return [img.detach(), alpha.detach()] + grads

    first = render()
    builds, hits = rt.plan_builds, rt.plan_hits
    second = render()
    assert rt.plan_builds == builds  # nothing per shape worked out again
    assert rt.plan_hits >= hits + 4  # both compositing kernels and layouts, the sort's scratch
    assert all(torch.equal(a, b) for a, b in zip(first, second))

    made = []
    for i in range(PLAN_CACHE_SIZE + 5):
        assert rt.plan(("test_entry", i), lambda i=i: made.append(i) or i) == i
    assert len(rt._plans) <= PLAN_CACHE_SIZE and len(made) == PLAN_CACHE_SIZE + 5
    assert rt.plan(("test_entry", PLAN_CACHE_SIZE + 4), lambda: -1) == PLAN_CACHE_SIZE + 4  # kept
    assert rt.plan(("test_entry", 0), lambda: -1) == -1  # the oldest was dropped, built again

    def refuse():
        raise ValueError("tile_size: refused")
    for _ in range(2):  # refused each time, never cached
        with pytest.raises(ValueError, match="tile_size: refused"):
            rt.plan(("test_refused",), refuse)
    assert ("test_refused",) not in rt._plans
    render()  # the render's own entries, evicted above, are built again


def test_scalar_arguments_declared_once_and_redeclared_on_change(rt):
    """Runtime.enqueue declares a kernel's numpy scalar arguments to pyopencl (its fast,
    struct-packed path) once per signature; launching with other scalar types redeclares."""
    import numpy as np
    k = rt.kernel("reduce", "reduce_slots", {"REAL_DOUBLE": False, "CHANNELS": 1, "GEOM_GRAD": False,
                                              "COLOR_GRAD": True, "ABSGRAD": False})
    rects = rt.array(torch.tensor([[0, 0, 1, 2], [0, 0, 1, 1]], dtype=torch.int32).reshape(1, 2, 4))
    offs = rt.array(torch.tensor([0, 2], dtype=torch.int32))
    slots = rt.array(torch.tensor([[1.5], [2.25], [4.0]]))
    outs = [rt.empty((1,), torch.float32) for _ in range(4)] + [rt.empty((1, 2, 1), torch.float32)]
    for n in (np.int32(2), np.uint32(2), np.int32(2)):
        outs[-1].tensor.zero_()
        rt.launch(k, 2, 64, n, rects.buffer, offs.buffer, slots.buffer, *(o.buffer for o in outs))
        assert rt._arg_dtypes[k.int_ptr][0] is type(n)
        assert outs[-1].host().flatten().tolist() == [3.75, 4.0]


def _reduce_kernel(rt):
    return rt.kernel("reduce", "reduce_slots", {"REAL_DOUBLE": False, "CHANNELS": 1, "GEOM_GRAD": False,
                                                "COLOR_GRAD": True, "ABSGRAD": False})


def test_array_pool_hands_out_only_arrays_nothing_holds(rt, monkeypatch):
    """Runtime.empty (the render plan's arrays kept per shape): a small array nothing holds any
    more is handed out again, zeroed when asked; one that a tensor, a view, a numpy array or a
    queued command still holds is not; large arrays and a pool turned off are never pooled;
    Runtime.array of a pooled array's memory gives that array."""
    import numpy as np
    from clsplat.runtime import POOL_ARRAY_BYTES, POOL_PER_SHAPE, POOL_SHAPES
    _skip_where_the_pool_is_off(rt)
    rt.release_pool()
    a = rt.empty((7, 3), torch.float32)
    a.tensor.fill_(5)
    ptr = a.tensor.data_ptr()
    del a
    b = rt.empty((7, 3), torch.float32)
    assert b.tensor.data_ptr() == ptr and not b.tensor.any()  # handed out again, zeroed
    assert rt.array(b.tensor) is b and rt.array(b.tensor.detach()) is b
    b.tensor.fill_(2)
    holders = {"tensor": lambda x: x.tensor, "view": lambda x: x.tensor[1:],
               "alias": lambda x: x.tensor.detach(), "numpy": lambda x: x.tensor.numpy(),
               "array": lambda x: x}
    for name, hold in holders.items():
        kept = hold(b)
        del b
        c = rt.empty((7, 3), torch.float32, zero=False)
        assert c.tensor.data_ptr() != ptr, name  # held: a fresh array
        del c, kept
        b = rt.empty((7, 3), torch.float32, zero=False)
        assert b.tensor.data_ptr() == ptr and float(b.tensor[0, 0]) == 2, name  # free again, not zeroed
    rt.hold(b.buffer)  # as a queued command holds it until the next finish()
    del b
    assert rt.empty((7, 3), torch.float32).tensor.data_ptr() != ptr
    rt.finish()
    assert rt.empty((7, 3), torch.float32).tensor.data_ptr() == ptr
    # at most POOL_PER_SHAPE arrays of one shape; large arrays never
    many = [rt.empty((5,), torch.int32) for _ in range(POOL_PER_SHAPE + 3)]
    assert len(rt._pool[((5,), torch.int32)]) == POOL_PER_SHAPE
    assert len({m.buffer.int_ptr for m in many}) == len(many)
    big = (POOL_ARRAY_BYTES // 4 + 1,)
    p = rt.empty(big, torch.float32).tensor.data_ptr()
    assert ((big, torch.float32)) not in rt._pool and p not in rt._pool_ptrs
    # bounded in bytes: the least recently used shapes are dropped first
    limit = rt.pool_limit
    try:
        rt.pool_limit = 64 << 10
        for i in range(40):
            rt.empty((1024 + i,), torch.float32)
        assert rt._pool_bytes <= rt.pool_limit and ((1024 + 39,), torch.float32) in rt._pool
        assert ((1024,), torch.float32) not in rt._pool
        rt.pool_limit = limit  # and in shapes: one small array each of many sizes (as the
        for i in range(POOL_SHAPES + 10):  # intersection arrays of calls whose counts differ)
            rt.empty((3000 + i,), torch.int64, zero=False)
        assert len(rt._pool) == POOL_SHAPES and ((3000 + POOL_SHAPES + 9,), torch.int64) in rt._pool
        assert len(rt._pool_ptrs) == sum(len(v) for v in rt._pool.values())
        rt.pool_limit = 0  # off: a fresh array every time
        assert rt.empty((7, 3), torch.float32).tensor.data_ptr() not in rt._pool_ptrs
    finally:
        rt.pool_limit = limit
    rt.release_pool()
    assert not rt._pool and not rt._pool_ptrs and rt._pool_bytes == 0
    # the copying path (what GPUs take, CLSPLAT_HOST_MEMORY=copy): arrays hold device copies that
    # a host-side zero or write would not reach, so nothing is pooled or kept
    from clsplat.runtime import Runtime
    monkeypatch.setattr(Runtime, "shares_host_memory", property(lambda self: False))
    monkeypatch.setattr(rt, "_pools_device", None)  # (worked out once per runtime: again)
    assert not rt.pools
    x = rt.empty((7, 3), torch.float32)
    assert not rt._pool and not x.zero_copy
    del many, np


def test_kept_input_arrays_follow_their_tensors(rt):
    """Runtime.array(keep=True): the same array for the same memory on the next call, reading
    the tensor's current values (changed in place, as by an optimiser); dropped once nothing
    else holds the memory, and never more than KEEP_INPUTS."""
    import numpy as np
    from clsplat.runtime import KEEP_INPUTS
    _skip_where_the_pool_is_off(rt)
    rt.release_pool()
    rt.empty((1,), torch.float32)  # (the pool on: keep needs it)
    k = _reduce_kernel(rt)
    rects = rt.array(torch.tensor([[0, 0, 1, 2], [0, 0, 1, 1]], dtype=torch.int32).reshape(1, 2, 4))
    offs = rt.array(torch.tensor([0, 2], dtype=torch.int32))
    slots = torch.tensor([[1.5], [2.25], [4.0]])
    got = []
    for _ in range(2):
        a = rt.array(slots, keep=True)
        outs = [rt.empty((1,), torch.float32) for _ in range(4)] + [rt.empty((1, 2, 1), torch.float32)]
        rt.launch(k, 2, 64, np.int32(2), rects.buffer, offs.buffer, a.buffer, *(o.buffer for o in outs))
        got.append(outs[-1].host().flatten().tolist())
        slots.mul_(2)  # in place: the kept array reads the new values
    assert got == [[3.75, 4.0], [7.5, 8.0]]
    assert rt.array(slots, keep=True) is a and len(rt._kept) == 1
    del a, outs
    slots = None  # the caller drops it: the next new input drops its kept array
    for i in range(KEEP_INPUTS + 5):
        rt.array(torch.full((3,), float(i)), keep=True)
    assert len(rt._kept) <= 2  # only the inputs of the last calls, not one per call
    held = [torch.full((2,), float(i)) for i in range(KEEP_INPUTS + 5)]
    for h in held:
        rt.array(h, keep=True)
    assert len(rt._kept) == KEEP_INPUTS  # all held: the oldest dropped
    rt.release_pool()


def test_small_renders_make_no_arrays_and_returned_tensors_stay_valid(make_scene):
    """The render plan's arrays: once warm, a small forward + backward makes no new device array
    (every one comes from the pool or the kept inputs), and tensors a caller keeps from one call
    are never overwritten by the next (which sees inputs changed in place)."""
    from clsplat import runtime as R
    rt = clsplat.get_runtime()
    _skip_where_the_pool_is_off(rt)
    scene = make_scene(0, N=60, C=1, width=48, height=32, dtype=torch.float32)
    for k in ("means", "quats", "scales", "opacities", "colors"):
        scene[k] = scene[k].clone().requires_grad_()

    def render():
        img, alpha, meta = clsplat.rasterization(**scene)
        (img.sum() + alpha.sum()).backward()
        out = (img, alpha, meta["isect_offsets"], scene["means"].grad)
        for k in ("means", "quats", "scales", "opacities", "colors"):
            scene[k].grad = None
        return out

    for _ in range(3):
        render()
    made = []
    init = R.DeviceArray.__init__
    R.DeviceArray.__init__ = lambda self, *a, **kw: (made.append(1), init(self, *a, **kw))[1]
    try:
        first = render()
    finally:
        R.DeviceArray.__init__ = init
    assert not made
    copies = [t.detach().clone() for t in first]
    with torch.no_grad():
        scene["colors"].mul_(0.5)
        scene["means"].add_(0.01)
    second = render()
    assert not torch.equal(second[0], copies[0])  # the change was seen
    assert all(torch.equal(a, b) for a, b in zip(first, copies))  # the first call's results intact


def test_tensors_moved_to_shared_memory_leave_the_pool_and_later_renders_right(make_scene):
    """``share_memory_()`` (what a ``torch.multiprocessing`` queue does to every tensor it sends)
    moves a returned image's or an input's memory away from the buffer the pool made over it:
    such arrays leave the pool, so a later render is what a fresh process renders. (Where the
    pool is off, the same must hold trivially: no skip.)"""
    scene = make_scene(1, N=60, C=1, width=48, height=32, dtype=torch.float32)
    other = make_scene(2, N=60, C=1, width=48, height=32, dtype=torch.float32)
    expected = clsplat.rasterization(**scene)[0].clone()
    for _ in range(2):
        clsplat.rasterization(**other)
    img, alpha, meta = clsplat.rasterization(**other)
    for t in (img, alpha, *(v for v in meta.values() if isinstance(v, torch.Tensor))):
        t.share_memory_()
    del img, alpha, meta
    shared = {k: (v.clone().share_memory_() if isinstance(v, torch.Tensor) and v.numel() else v)
              for k, v in scene.items()}  # inputs moved too, then changed in place
    assert torch.equal(clsplat.rasterization(**shared)[0], expected)
    with torch.no_grad():
        shared["colors"].mul_(0.5)
    again = clsplat.rasterization(**shared)[0]
    assert torch.equal(again, clsplat.rasterization(**{**scene, "colors": scene["colors"] * 0.5})[0])
    assert torch.equal(clsplat.rasterization(**scene)[0], expected)


def test_staged_gradients_copy_only_what_is_cheaper_to_copy(rt):
    """Runtime.staged: an incoming gradient that is a pooled array's memory is used as it is; a
    small or non-contiguous one is copied into a pooled array; a large contiguous one gets an
    array over its own memory (no copy, as before the pool); None gives zeros. Values equal."""
    from clsplat.runtime import STAGE_COPY_BYTES
    if not rt.pools:
        pytest.skip("the pool is on only where the device computes in host memory (PoCL's CPU device)")
    pooled = rt.empty((4, 3), torch.float32)
    assert rt.staged(pooled.tensor, (4, 3), torch.float32) is pooled
    small = torch.arange(12, dtype=torch.float32).reshape(4, 3)
    a = rt.staged(small, (4, 3), torch.float32)
    assert a.tensor.data_ptr() in rt._pool_ptrs and torch.equal(a.tensor, small)
    n = STAGE_COPY_BYTES // 4 + 1
    large = torch.arange(n, dtype=torch.float32)
    b = rt.staged(large, (n,), torch.float32)
    assert b.tensor.data_ptr() == large.data_ptr()
    wide = torch.ones(3, 1).expand(3, 4)  # as a sum's gradient comes: not contiguous
    c = rt.staged(wide, (3, 4), torch.float64)
    assert c.tensor.dtype == torch.float64 and torch.equal(c.tensor, torch.ones(3, 4, dtype=torch.float64))
    z = rt.staged(None, (2, 2), torch.float32)
    assert not z.tensor.any()


def test_arrays_on_the_copying_path_live_on_the_device(monkeypatch, rt):
    """Where the device keeps its own copies (GPUs, CLSPLAT_HOST_MEMORY=copy), an intermediate
    is a buffer with nothing uploaded, a zeroed one a fill on the device: it reads back as
    zeros, a kernel sees zeros; with every array nobody zeroes filled with a sentinel first
    (so that reading an entry before writing it would show), a render forward and backward
    gives the same bits as on the shared path."""
    import numpy as np
    import pyopencl as cl
    from clsplat.bench.scenes import random_frustum_scene, render_args
    from clsplat.runtime import DeviceArray, Runtime
    args = render_args(random_frustum_scene(300, 48, 32, seed=1))
    keys = ("means", "quats", "scales", "opacities", "colors")
    args_grad = dict(args) | {k: args[k].clone().requires_grad_() for k in keys}
    img, alpha, _ = clsplat.rasterization(**args_grad)
    (img.sum() + alpha.sum()).backward()
    want, want_grads = img.detach(), {k: args_grad[k].grad for k in keys}
    for k in keys:
        args_grad[k].grad = None
    monkeypatch.setattr(Runtime, "shares_host_memory", property(lambda self: False))
    monkeypatch.setattr(rt, "_pools_device", None)
    monkeypatch.setattr(rt, "_plans", type(rt._plans)())  # (kept arrays of the shared path)
    made = []
    real = DeviceArray.on_device.__func__

    def on_device(cls, rt_, shape, dtype, zero):
        a = real(cls, rt_, shape, dtype, zero)
        if not zero:  # 0xAB bytes: a NaN as a float, a large negative int
            cl.enqueue_fill_buffer(rt_.queue, a.buffer, np.full(1, 0xAB, np.uint8), 0, a.tensor.nbytes)
        made.append(a)
        return a
    monkeypatch.setattr(DeviceArray, "on_device", classmethod(on_device))
    z = rt.empty((1000,), torch.float32)
    assert made and z is made[-1] and torch.equal(z.host(), torch.zeros(1000))
    k = _reduce_kernel(rt)  # sums slots per pair: over a zeroed slot array, zeros
    rects = rt.array(torch.tensor([[0, 0, 1, 2]], dtype=torch.int32).reshape(1, 1, 4))
    offs, slots = rt.array(torch.tensor([0], dtype=torch.int32)), rt.empty((2, 1), torch.float32)
    outs = [rt.array(torch.full((1,), 7.0)) for _ in range(4)] + [rt.array(torch.full((1, 1, 1), 7.0))]
    rt.launch(k, 1, 64, np.int32(1), rects.buffer, offs.buffer, slots.buffer, *(o.buffer for o in outs))
    assert float(outs[-1].host()) == 0.0  # the two zeroed slots summed
    n_before = len(made)
    img, alpha, _ = clsplat.rasterization(**args_grad)
    (img.sum() + alpha.sum()).backward()
    assert len(made) - n_before > 10  # the render's intermediates took this path
    assert torch.equal(img.detach(), want)
    assert all(torch.equal(args_grad[k].grad, want_grads[k]) for k in want_grads)
