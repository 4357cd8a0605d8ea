"""Bad input to ``clsplat.rasterization``: each case gets the right result or a ValueError that
names the argument, never a crash, a hang or a silently wrong image.

Kinds (issue 12, item 4): crash / out of memory, silently wrong, unclear errors. Allocation
limits (30,000 huge Gaussians at 2000x2000, int32 pair range) are in test_portability_limits.py.
"""
import pytest
import torch

import clsplat
from clsplat import reference as ref

F64 = torch.float64


def scene(n=4, d=3, dtype=torch.float32, W=16, H=12):
    g = torch.Generator().manual_seed(0)
    means = (torch.randn(n, 3, generator=g, dtype=F64) * 0.3 + torch.tensor([0, 0, 3.0], dtype=F64))
    s = dict(means=means, quats=torch.randn(n, 4, generator=g, dtype=F64),
             scales=torch.rand(n, 3, generator=g, dtype=F64) * 0.2 + 0.05,
             opacities=torch.rand(n, generator=g, dtype=F64), colors=torch.rand(n, d, generator=g, dtype=F64),
             viewmats=torch.eye(4, dtype=F64)[None],
             Ks=torch.tensor([[[12.0, 0, W / 2], [0, 12, H / 2], [0, 0, 1]]], dtype=F64))
    return {**{k: v.to(dtype) for k, v in s.items()}, "width": W, "height": H}


# --- crash, hang, out of memory -------------------------------------------------------------
@pytest.mark.slow   # an extreme width: 4096 channels through every compositing build
def test_4096_channels_render_instead_of_crashing():
    """D = 4096 overflowed composite_bwd's local buffer and segfaulted; now channels are chunked."""
    s = scene(n=2, d=4096, W=8, H=8)
    s["colors"].requires_grad_()
    img, _, _ = clsplat.rasterization(**s)
    img.sum().backward()
    small, _, _ = clsplat.rasterization(**dict(s, colors=s["colors"].detach()[:, :3]))
    assert torch.equal(img[..., :3], small)
    assert torch.isfinite(s["colors"].grad).all()


def test_huge_image_refused_before_allocation():
    with pytest.raises(ValueError, match="width"):
        clsplat.rasterization(**dict(scene(), width=10**6, height=10**6))


# --- silently wrong -------------------------------------------------------------------------
@pytest.mark.parametrize("factor", [1e19, 1e30])
def test_huge_quaternion_norm_renders_like_the_unit_quaternion(factor):
    s = scene()
    want, _, _ = clsplat.rasterization(**s)
    got, _, _ = clsplat.rasterization(**dict(s, quats=s["quats"] * factor))
    assert (got - want).abs().max() <= 1e-6


def test_huge_quaternion_gradient_is_the_chain_rule():
    s = scene(dtype=F64)
    q = (s["quats"] * 1e19).requires_grad_()
    img, _, _ = clsplat.rasterization(**dict(s, quats=q))
    img.sum().backward()
    q1 = s["quats"].clone().requires_grad_()
    img1, _, _ = clsplat.rasterization(**dict(s, quats=q1))
    img1.sum().backward()
    torch.testing.assert_close(q.grad * 1e19, q1.grad, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("factor", [1e19, 1e30])
def test_huge_scales_refused_in_float32_and_right_in_float64(factor):
    s = scene()
    with pytest.raises(ValueError, match=r"^scales: .*overflows float32.*precision='float64'"):
        clsplat.rasterization(**dict(s, scales=s["scales"] * factor))
    s64 = scene(dtype=F64)
    s64["scales"] = s64["scales"] * factor
    got, _, _ = clsplat.rasterization(**s64)
    want, _, _ = ref.rasterization(**s64)
    assert (got - want).abs().max() <= 1e-9
    assert got.abs().max() > 0.1  # the image is covered, not empty


@pytest.mark.parametrize("dtype,focal", [(torch.float32, 1e30), (torch.float64, 1e80)])
def test_an_absurd_focal_length_is_named_as_Ks_not_scales(dtype, focal):
    s = scene(dtype=dtype)
    s["Ks"] = s["Ks"].clone()
    s["Ks"][0, 0, 0] = focal
    with pytest.raises(ValueError, match=r"^Ks: camera 0 has focal length 1e\+\d+ px, over the .* px that "
                                         r"float(32|64) can project with"):
        clsplat.rasterization(**s)


def test_large_but_representable_scales_match_float64():
    s = scene(dtype=F64)
    s["scales"] = s["scales"] * 1e6
    want, _, _ = clsplat.rasterization(**s)
    got, _, _ = clsplat.rasterization(**{k: (v.float() if torch.is_tensor(v) else v) for k, v in s.items()})
    assert (got.double() - want).abs().max() <= 1e-5


@pytest.mark.parametrize("value", [float("inf"), float("nan"), -1.0])
def test_eps2d_must_be_finite_and_non_negative(value):
    with pytest.raises(ValueError, match="^eps2d: "):
        clsplat.rasterization(**dict(scene(), eps2d=value))


# --- unclear errors -------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["means", "quats", "scales", "opacities", "colors", "viewmats", "Ks"])
def test_sparse_tensors_named(name):
    with pytest.raises(ValueError, match=f"^{name}: expected a dense"):
        s = scene()
        clsplat.rasterization(**dict(s, **{name: s[name].to_sparse()}))


@pytest.mark.parametrize("name,value", [("config", "fast"), ("config", {"precision": "float32"}),
                                        ("events", "x"), ("events", 3)])
def test_config_and_events_of_the_wrong_type(name, value):
    with pytest.raises(ValueError, match=f"^{name}: expected"):
        clsplat.rasterization(**dict(scene(), **{name: value}))


@pytest.mark.parametrize("name,value", [("width", 16.0), ("height", "12"), ("width", None), ("tile_size", 16.0),
                                        ("means", None), ("colors", [[0.0, 0, 0]]), ("Ks", None),
                                        ("near_plane", None), ("sh_degree", 1.0), ("render_mode", None)])
def test_wrong_types_named(name, value):
    with pytest.raises(ValueError, match=f"^{name}"):
        clsplat.rasterization(**dict(scene(), **{name: value}))


def test_half_and_integer_tensors_named():
    s = scene()
    with pytest.raises(ValueError, match="^means: expected dtype"):
        clsplat.rasterization(**dict(s, means=s["means"].half()))
    with pytest.raises(ValueError, match="^opacities: expected dtype"):
        clsplat.rasterization(**dict(s, opacities=torch.ones(4, dtype=torch.int64)))


@pytest.mark.parametrize("kw,name", [({"pix": 2.0}, "pix"), ({"pix": True}, "pix"), ({"sort_local": "8"}, "sort_local"),
                                     ({"alpha_min": "0.1"}, "alpha_min"), ({"t_min": None}, "t_min"),
                                     ({"fast_math": "yes"}, "fast_math")])
def test_render_config_field_types(kw, name):
    with pytest.raises(ValueError, match=f"^{name}: expected"):
        clsplat.RenderConfig(**kw)
