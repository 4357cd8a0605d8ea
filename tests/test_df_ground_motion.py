"""The road-flow ego-motion fit (``models/drivingforward/ground_motion.py``): it recovers a known
rig motion from a synthetic plane-induced flow (with and without outliers) and from images of a textured
ground (the direct form), and refuses bad input."""
from __future__ import annotations

import math

import pytest
import torch

from clsplat.models.common.geometry import axis_angle_to_matrix, se3_exp
from clsplat.models.drivingforward.depth import ground_prior_depth
from clsplat.models.drivingforward.ground_motion import (_sample, fit_ground_motion, fit_ground_motion_direct,
                                                         ground_points, plane_flow)


def _rig() -> tuple[torch.Tensor, torch.Tensor]:
    """Three cameras 1.6 m up (front, left, back), OpenCV axes, 16 x 28 pixels."""
    K = torch.tensor([[20.0, 0, 14], [0, 20.0, 8], [0, 0, 1]], dtype=torch.float64).expand(3, 3, 3).clone()
    base = torch.tensor([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=torch.float64)   # cam axes in ego (fwd)
    E = []
    for yaw in (0.0, math.pi / 2, math.pi):
        c, s = math.cos(yaw), math.sin(yaw)
        Rz = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=torch.float64)
        T = torch.eye(4, dtype=torch.float64)
        T[:3, :3] = Rz @ base
        T[:3, 3] = torch.tensor([1.5 * c, 0.9 * s, 1.6])
        E.append(T)
    return K, torch.stack(E)


def _truth() -> torch.Tensor:
    return torch.tensor([0.002, -0.003, 0.02, -1.1, 0.08, 0.01], dtype=torch.float64)


def test_the_grey_read_equals_the_three_channel_reads_first_channel() -> None:
    """The fit's search reads the grey image alone (a third of the samples); its motion is the same
    bit for bit only if bilinear sampling treats channels apart and ``inside`` keeps its bounds."""
    g = torch.Generator().manual_seed(0)
    img = torch.rand(2, 3, 9, 13, dtype=torch.float64, generator=g)
    uv = torch.rand(2, 2, 200, dtype=torch.float64, generator=g) * torch.tensor([[17.0], [13.0]], dtype=torch.float64) - 2
    three, inside = _sample(img, uv)
    grey, inside1 = _sample(img[:, :1].contiguous(), uv)
    assert torch.equal(grey, three[:, :1]) and torch.equal(inside, inside1)
    u, v = uv[:, 0], uv[:, 1]
    assert torch.equal(inside, (u > 0.5) & (u < 12.5) & (v > 0.5) & (v < 8.5))
    assert 0 < int(inside.sum()) < inside.numel()


@pytest.mark.parametrize("dof", [4, 6])
def test_recovers_a_known_motion_from_exact_plane_flow(dof: int) -> None:
    K, E = _rig()
    Z = ground_prior_depth(K, E, 16, 28, 20.0)
    road = Z < 20.0
    theta = _truth() if dof == 6 else _truth() * torch.tensor([0, 0, 1, 1, 1, 1.0])
    uv, X = ground_points(K, Z)
    flow = plane_flow(theta, K, E, uv, X).reshape(3, 2, 16, 28)
    M, _ = fit_ground_motion(flow, K, E, torch.where(road, Z, torch.full_like(Z, float("nan"))), dof=dof, loss="l2")
    assert torch.allclose(M[:3, 3], theta[3:], atol=1e-6)
    assert torch.allclose(M[:3, :3], axis_angle_to_matrix(theta[:3]), atol=1e-8)


def test_robust_fit_ignores_outliers_that_least_squares_does_not() -> None:
    K, E = _rig()
    Z = ground_prior_depth(K, E, 16, 28, 20.0)
    Zr = torch.where(Z < 20.0, Z, torch.full_like(Z, float("nan")))
    theta = _truth()
    uv, X = ground_points(K, Z)
    flow = plane_flow(theta, K, E, uv, X).reshape(3, 2, 16, 28)
    g = torch.Generator().manual_seed(0)
    flow = flow + 0.02 * torch.randn(flow.shape, generator=g, dtype=flow.dtype)
    bad = torch.rand(3, 1, 16, 28, generator=g) < 0.2                     # a fifth of the pixels: "zero flow"
    flow = torch.where(bad, torch.zeros_like(flow), flow)
    t_err = {}
    for loss in ("l2", "huber", "cauchy"):
        M, w = fit_ground_motion(flow, K, E, Zr, dof=6, loss=loss)
        t_err[loss] = float((M[:3, 3] - theta[3:]).norm() / theta[3:].norm())
    assert t_err["cauchy"] < 0.02 and t_err["huber"] < 0.05
    assert t_err["l2"] > 2 * t_err["huber"]


def test_zero_flow_gives_zero_motion_and_bad_input_is_refused() -> None:
    K, E = _rig()
    Z = ground_prior_depth(K, E, 16, 28, 20.0)
    M, _ = fit_ground_motion(torch.zeros(3, 2, 16, 28, dtype=torch.float64), K, E, Z)
    assert torch.allclose(M, torch.eye(4, dtype=torch.float64), atol=1e-9)
    with pytest.raises(ValueError, match="dof"):
        fit_ground_motion(torch.zeros(3, 2, 16, 28), K, E, Z, dof=5)
    with pytest.raises(ValueError, match="loss"):
        fit_ground_motion(torch.zeros(3, 2, 16, 28), K, E, Z, loss="tukey")
    with pytest.raises(ValueError, match="ground_depth"):
        fit_ground_motion(torch.zeros(3, 2, 16, 28), K, E, Z[:, :, :8])
    for bad in (-1, 2.5, True):
        with pytest.raises(ValueError, match="iters"):
            fit_ground_motion(torch.zeros(3, 2, 16, 28), K, E, Z, iters=bad)


def _render_ground(K: torch.Tensor, E: torch.Tensor, M: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """``[V, 3, h, w]`` images of a textured ground plane seen after the ego motion ``M`` (earlier ->
    later ego coordinates): each pixel's ground point is taken back to the earlier ego frame and
    the texture read there; the sky (no ground within 200 m) is a constant grey."""
    Z = ground_prior_depth(K, E, h, w, 200.0)
    uv, X = ground_points(K, Z)
    P = E[:, :3, :3] @ X + E[:, :3, 3:]                                   # later ego frame
    Minv = torch.linalg.inv(M)
    Q = Minv[:3, :3] @ P + Minv[:3, 3:].unsqueeze(0)                      # earlier ego frame
    x, y = Q[:, 0], Q[:, 1]
    tex = 0.5 + 0.2 * torch.sin(0.8 * x) * torch.cos(0.7 * y) + 0.12 * torch.sin(0.45 * x + 1.7 * y) \
        + 0.08 * torch.cos(1.3 * x - 0.4 * y)
    img = torch.where(Z.reshape(Z.shape[0], -1) < 200.0, tex, torch.full_like(tex, 0.8))
    return img.reshape(-1, 1, h, w).expand(-1, 3, h, w).clamp(0, 1)


@pytest.mark.parametrize("forward", [0.9, -0.4])
def test_direct_fit_recovers_a_known_motion_from_images_of_a_textured_ground(forward: float) -> None:
    K, E = _rig()
    K = K.clone()
    K[:, :2] *= 2.0                                                        # 32 x 56 images
    theta = torch.tensor([0.0, 0.0, 0.015, forward, 0.05, 0.0], dtype=torch.float64)
    M = se3_exp(theta[:3], theta[3:])
    earlier = _render_ground(K, E, torch.eye(4, dtype=torch.float64), 32, 56)
    later = _render_ground(K, E, M, 32, 56)
    fit = fit_ground_motion_direct(earlier, later, K, E, 12.0, levels=(1,), dof=3)
    assert float((fit[:3, 3] - theta[3:]).norm()) < 0.01 * abs(forward), fit[:3, 3]
    standing = fit_ground_motion_direct(earlier, earlier, K, E, 20.0, levels=(1,), dof=3)
    assert float(standing[:3, 3].norm()) < 1e-3
    with pytest.raises(ValueError, match="tau"):
        fit_ground_motion_direct(earlier, later, K, E, 20.0, tau=0.0)
    for name, kw in (("iters", {"iters": -1}), ("search", {"search": (3.0, -3.0, 61)}),
                     ("search", {"search": (-3.0, 3.0, 1)}), ("search", {"search": (-3.0, 3.0)}),
                     ("levels", {"levels": ()}), ("levels", {"levels": (0,)})):
        with pytest.raises(ValueError, match=name):
            fit_ground_motion_direct(earlier, later, K, E, 20.0, **kw)
    with pytest.raises(ValueError, match="earlier / later"):
        fit_ground_motion_direct(earlier, later.clone().index_fill_(-1, torch.tensor([3]), float("nan")), K, E, 20.0)


def test_direct_fit_without_a_ground_pixel_returns_no_motion() -> None:
    """Every pixel weighted out: nothing to align, so the identity, not the search grid's first value."""
    K, E = _rig()
    img = torch.rand(3, 3, 16, 28, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    M = fit_ground_motion_direct(img, img.flip(-1), K, E, cap=20.0, weight=torch.zeros(3, 1, 16, 28))
    assert torch.equal(M, torch.eye(4, dtype=torch.float64))


def _ground_pair(theta: list[float]):
    """The rig at 32 x 56 and its ground rendered before and after the motion ``theta`` (rotation,
    translation): ``(K, E, earlier, later)``."""
    K, E = _rig()
    K = K.clone()
    K[:, :2] *= 2.0                                                        # 32 x 56 images
    t = torch.tensor(theta, dtype=torch.float64)
    earlier = _render_ground(K, E, torch.eye(4, dtype=torch.float64), 32, 56)
    later = _render_ground(K, E, se3_exp(t[:3], t[3:]), 32, 56)
    return K, E, earlier, later


def test_keep_trims_pixels_that_keep_pace_with_the_ego_so_a_crawl_is_not_read_short() -> None:
    """A crawl (0.15 m) over a low-contrast ground, a fifth of whose pixels show a pattern that keeps
    pace with the ego (a car driving alongside: fixed in the image, so the plane's flow misplaces it
    at the true motion and not at zero). The plain mean reads the crawl short (toward standing);
    ``keep`` 0.75 drops the misfit pixels from the search and the refinement and reads it."""
    K, E, earlier, later = _ground_pair([0.0, 0.0, 0.0, 0.15, 0.0, 0.0])
    ground = ground_prior_depth(K, E, 32, 56, 12.0) < 12.0                 # [3, 1, 32, 56]
    car = torch.zeros_like(ground)
    car[..., 20:32] = True
    car &= ground
    assert 0.18 < float(car.sum() / ground.sum()) < 0.25
    v, u = torch.meshgrid(torch.arange(32, dtype=torch.float64), torch.arange(56, dtype=torch.float64), indexing="ij")
    pattern = 0.5 + 0.45 * torch.sign(torch.sin(1.3 * u) * torch.sin(1.1 * v))
    a, b = torch.where(car, pattern, earlier), torch.where(car, pattern, later)
    kw = {"dof": 3, "search": (-3.0, 3.0, 301)}
    plain = float(fit_ground_motion_direct(a, b, K, E, 12.0, **kw)[0, 3])
    trimmed = float(fit_ground_motion_direct(a, b, K, E, 12.0, keep=0.75, **kw)[0, 3])
    assert plain < 0.1, plain                                              # the failure keep is for
    assert abs(trimmed - 0.15) < 0.01, trimmed
    # keep 1 is the plain mean, bit for bit (the field's default leaves every fit as it was)
    assert torch.equal(fit_ground_motion_direct(a, b, K, E, 12.0, keep=1.0, **kw),
                       fit_ground_motion_direct(a, b, K, E, 12.0, **kw))
    for bad in (0.0, 1.5, True, float("nan")):
        with pytest.raises(ValueError, match="keep"):
            fit_ground_motion_direct(a, b, K, E, 12.0, keep=bad)


def test_a_yaw_search_reads_a_turn_and_leaves_the_fit_unchanged_when_off() -> None:
    """A turn of 1.5 degrees a frame at 0.8 m over a smooth textured ground: with the yaw searched first
    the fit reads the turn and the translation (the varied world's turning windows, which the fit
    without it reads as driving straight, are tests/test_df_geometric_pose.py's). Without the search
    the fit is the same as before, bit for bit; a bad grid is refused."""
    K, E = _rig()
    K = K.clone()
    K[:, :2] *= 2.0                                                        # 32 x 56 images
    yaw = math.radians(1.5)
    theta = torch.tensor([0.0, 0.0, yaw, 0.8, 0.0, 0.0], dtype=torch.float64)
    earlier = _render_ground(K, E, torch.eye(4, dtype=torch.float64), 32, 56)
    later = _render_ground(K, E, se3_exp(theta[:3], theta[3:]), 32, 56)
    kw = {"dof": 6, "search": (-3.0, 3.0, 301), "keep": 0.75}

    def yaw_of(M):
        return float(torch.atan2(M[1, 0], M[0, 0]))
    plain = fit_ground_motion_direct(earlier, later, K, E, 12.0, **kw)
    searched = fit_ground_motion_direct(earlier, later, K, E, 12.0, yaw_search=(-0.05, 0.05, 41), **kw)
    assert abs(yaw_of(searched) - yaw) < 0.1 * yaw, yaw_of(searched)
    assert float((searched[:3, 3] - theta[3:]).norm()) < 0.05 * 0.8, searched[:3, 3]
    assert torch.equal(fit_ground_motion_direct(earlier, later, K, E, 12.0, yaw_search=None, **kw), plain)
    for bad in ((0.05, -0.05, 41), (-0.05, 0.05, 1), (-0.05, 0.05), (-0.05, 0.05, True)):
        with pytest.raises(ValueError, match="yaw_search"):
            fit_ground_motion_direct(earlier, later, K, E, 12.0, yaw_search=bad)


def test_a_depth_in_place_of_the_plane_gives_the_planes_motion_where_the_ground_is_the_plane() -> None:
    """``depth`` (a probe's upper bound: the data's own depth) places the prior's pixels in 3D; on a
    ground that is the calibrated plane it is the plane's depth, so the fit is the same; a bad map is
    refused by name."""
    K, E = _rig()
    K = K.clone()
    K[:, :2] *= 2.0
    theta = torch.tensor([0.0, 0.0, 0.01, 0.6, 0.0, 0.0], dtype=torch.float64)
    earlier = _render_ground(K, E, torch.eye(4, dtype=torch.float64), 32, 56)
    later = _render_ground(K, E, se3_exp(theta[:3], theta[3:]), 32, 56)
    Z = ground_prior_depth(K, E, 32, 56, 12.0)
    Zs = torch.where(Z < 12.0, Z, torch.full_like(Z, 1e4))                # the sky set far, as a probe does
    a = fit_ground_motion_direct(earlier, later, K, E, 12.0, dof=3)
    b = fit_ground_motion_direct(earlier, later, K, E, 12.0, dof=3, depth=Zs)
    assert torch.allclose(a, b, atol=1e-9)
    for bad in (Zs[:, :, :10], Zs.clone().fill_(float("nan")), -Zs):
        with pytest.raises(ValueError, match="depth"):
            fit_ground_motion_direct(earlier, later, K, E, 12.0, depth=bad)


@pytest.mark.parametrize("keep", [1.0, 0.75])
def test_the_search_picks_the_grid_value_its_definition_ranks_lowest(keep: float) -> None:
    """The search's cost reads the later image through one folded matrix a camera (a faster path than
    :func:`plane_flow` and :func:`_sample`): with no Gauss-Newton step the fit's forward translation
    is the grid value that the definition, computed here the plain way, ranks lowest. Half of one
    camera is weighted out, so the cameras' prior pixels differ in number and the padding counts."""
    K, E, earlier, later = _ground_pair([0.0, 0.0, 0.01, 0.7, 0.03, 0.0])
    cap, tau, search = 12.0, 0.05, (-3.0, 3.0, 61)
    weight = torch.ones(3, 1, 32, 56, dtype=torch.float64)
    weight[1, :, :, :28] = 0
    fit = fit_ground_motion_direct(earlier, later, K, E, cap, levels=(1,), iters=0, search=search, keep=keep, tau=tau,
                                   weight=weight)
    Z = ground_prior_depth(K, E, 32, 56, cap)
    uv, X = ground_points(K, Z)
    used = ((Z < cap) & (weight > 0)).reshape(3, -1)
    a, b = earlier.mean(1).reshape(3, -1), later.mean(1, keepdim=True)

    def cost(tx: float) -> float:
        th = torch.zeros(6, dtype=torch.float64)
        th[3] = tx
        s, inside = _sample(b, uv + plane_flow(th, K, E, uv, X))
        e = torch.where(inside, (s[:, 0] - a).abs().clamp(max=tau), torch.full_like(a, tau))[used]
        k = max(1, int(keep * e.numel()))
        return float(e.sort().values[:k].mean())

    grid = torch.linspace(*search[:2], search[2], dtype=torch.float64).tolist()
    best = min(grid, key=cost)
    step = (search[1] - search[0]) / (search[2] - 1)
    best = min(torch.linspace(best - step, best + step, 21, dtype=torch.float64).tolist() + [best], key=cost)
    assert abs(cost(float(fit[0, 3])) - cost(best)) < 1e-12, (float(fit[0, 3]), best)
    assert abs(float(fit[0, 3]) - 0.7) < 0.1                               # and it is near the motion
