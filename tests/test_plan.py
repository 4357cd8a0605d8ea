"""The render plan knows its memory (clsplat.plan): pixel and intersection estimates, and
requests that cannot fit refused up front with one line naming the sizes, in process (a
patched allowance) and in a child process under an 8 GiB address-space limit (``ulimit -v``).
"""
from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest
import torch

import clsplat
from clsplat import memory, plan
from clsplat.runtime import get_runtime

GIB = 2**30


def test_pixel_plan_counts_the_buffers_a_call_holds():
    # forward, RGB float32: 3 channels + T + alphas
    p = plan.pixel_plan(1, 1, 48, 64, 3, False, 4, grad=False, background=False, expected_depth=False)
    assert (p.images, p.pixels, p.real_values, p.int_values) == (1, 64 * 48, 5, 0)
    assert p.nbytes == 64 * 48 * 20 and p.bytes_per_pixel == 20
    # gradients wanted: the image and T gradients (CH + 1) and the int32 last contributor
    g = plan.pixel_plan(1, 1, 48, 64, 3, False, 4, grad=True, background=False, expected_depth=False)
    assert (g.real_values, g.int_values, g.bytes_per_pixel) == (9, 1, 40)
    # batch of 2, 3 cameras: every image, plus the stack's copy of CH + 1
    b = plan.pixel_plan(2, 3, 48, 64, 3, False, 8, grad=False, background=False, expected_depth=False)
    assert (b.images, b.real_values, b.real_bytes) == (6, 9, 8)
    # RGB+ED with a background: 4 channels; the blend (2 x 3 + 4) and the division (2 + 4)
    e = plan.pixel_plan(1, 1, 48, 64, 3, True, 4, grad=False, background=True, expected_depth=True)
    assert e.real_values == 6 + 10 + 6
    assert e.describe() == "1 x 3072 pixels x (22 values x 4 bytes)"
    assert g.describe() == "1 x 3072 pixels x (9 values x 4 bytes + 1 x 4)"


def test_intersection_bytes():
    assert plan.intersection_bytes(3, 4, grad=False, absgrad=False) == 16  # key + sort scratch
    assert plan.intersection_bytes(3, 4, grad=True, absgrad=False) == 8 + 9 * 4  # key + slots
    assert plan.intersection_bytes(3, 8, grad=True, absgrad=True) == 8 + 11 * 8
    assert plan.intersection_bytes(0, 4, grad=True, absgrad=False) == 8 + 24


def test_host_allowance_honours_the_address_space_limit(monkeypatch):
    monkeypatch.setattr(memory, "available_host_memory", lambda: 64 * GIB)
    monkeypatch.setattr(memory, "_address_space_limit", lambda: 8 * GIB)
    monkeypatch.setattr(memory, "address_space_in_use", lambda: GIB)
    allowed, why = memory.host_allowance()
    assert allowed == 7 * GIB and why == "the process's address-space limit (RLIMIT_AS 8.0 GiB, 1.0 GiB of it in use)"
    monkeypatch.setattr(memory, "_address_space_limit", lambda: None)
    assert memory.host_allowance() == (64 * GIB, "the host memory available now (64.0 GiB)")


def test_checks_refuse_with_the_sizes(monkeypatch):
    rt = get_runtime()
    monkeypatch.setattr(type(rt), "allowance", lambda self: (GIB, "a test's limit"))
    big = plan.pixel_plan(1, 1, 16384, 16384, 3, False, 4, grad=True, background=False,
                          expected_depth=False)
    with pytest.raises(ValueError, match=r"^width, height: the render's pixel buffers need about "
                       r"10\.0 GiB \(1 x 268435456 pixels x \(9 values x 4 bytes \+ 1 x 4\)\), "
                       r"over the 1\.0 GiB this process may allocate \(a test's limit\)"):
        plan.check_pixel_memory(rt, big)
    plan.check_pixel_memory(rt, plan.pixel_plan(1, 1, 1024, 1024, 3, False, 4, grad=True,
                                                background=False, expected_depth=False))
    with pytest.raises(ValueError, match=r"^means, scales: 100000000 \(camera, Gaussian, tile\) "
                       r"intersections need about 1\.5 GiB \(100000000 x 16 bytes\) besides about "
                       r"20 MiB of pixel buffers, over the 1\.0 GiB"):
        plan.check_intersection_memory(rt, 10**8, 16, reserve=20 << 20)
    plan.check_intersection_memory(rt, 10**6, 44, reserve=20 << 20)


def test_rasterization_refuses_before_allocating(monkeypatch, rt):
    """A 2048 x 2048 render against a 16 MiB allowance: refused from the plan, in process."""
    monkeypatch.setattr(memory, "available_host_memory", lambda: 16 << 20)
    monkeypatch.setattr(memory, "_address_space_limit", lambda: None)
    N = 4
    args = dict(means=torch.zeros(N, 3) + torch.tensor([0, 0, 5.0]), quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(N, 1),
                scales=torch.full((N, 3), 0.1), opacities=torch.full((N,), 0.5), colors=torch.rand(N, 3),
                viewmats=torch.eye(4)[None], Ks=torch.tensor([[[500.0, 0, 1024], [0, 500, 1024], [0, 0, 1]]]))
    with pytest.raises(ValueError, match=r"^width, height: .* \(1 x 4194304 pixels x \(5 values x 4 "
                       r"bytes\)\), over the 16 MiB this process may allocate \(the host memory"):
        clsplat.rasterization(**args, width=2048, height=2048)
    img, _, _ = clsplat.rasterization(**args, width=64, height=64)  # small: not even asked
    assert img.shape == (1, 64, 64, 3)


_CHILD = textwrap.dedent("""
    import os, resource, sys, torch
    os.environ.setdefault("POCL_MAX_WORK_GROUP_SIZE", "256")
    resource.setrlimit(resource.RLIMIT_AS, (8 << 30, 8 << 30))
    import clsplat
    case = sys.argv[1]
    if case == "pixels":  # 16384 x 16384, RGB, colours trained
        N, W, s = 4, 16384, 0.05
    else:  # 32000 Gaussians each covering the 2000 x 2000 image: 5e8 intersections
        N, W, s = 32000, 2000, 50.0
    colors = torch.rand(N, 3).requires_grad_(case == "pixels")
    try:
        clsplat.rasterization(torch.zeros(N, 3) + torch.tensor([0, 0, 5.0]),
                              torch.tensor([[1.0, 0, 0, 0]]).repeat(N, 1), torch.full((N, 3), s),
                              torch.full((N,), 0.5), colors, torch.eye(4)[None],
                              torch.tensor([[[1000.0, 0, W / 2], [0, 1000, W / 2], [0, 0, 1]]]), W, W)
    except ValueError as e:
        print("REFUSED", e)
    else:
        print("RENDERED")
""")


@pytest.mark.slow
@pytest.mark.parametrize("case,sizes", [
    ("pixels", r"width, height: the render's pixel buffers need about 10\.0 GiB \(1 x 268435456 pixels x "
               r"\(9 values x 4 bytes \+ 1 x 4\)\)"),
    ("intersections", r"means, scales: 500000000 \(camera, Gaussian, tile\) intersections need about "
                      r"7\.5 GiB \(500000000 x 16 bytes\) besides about \d+ MiB of pixel buffers"),
])
def test_refused_under_an_8_gib_address_space_limit(case, sizes):
    """The issue's two requests, which passed the size checks and then died of an allocation
    error under ``ulimit -v 8388608``: refused with one line naming the sizes and the limit."""
    out = subprocess.run([sys.executable, "-c", _CHILD, case], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    line = out.stdout.strip()
    assert line.startswith("REFUSED "), line
    assert "\n" not in line
    assert __import__("re").search(sizes, line), line
    assert "this process may allocate (the process's address-space limit (RLIMIT_AS 8.0 GiB" in line \
        or "the host memory available now" in line, line
