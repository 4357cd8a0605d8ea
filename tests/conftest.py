"""Shared fixtures of the engine tests: seeded random scenes and small helpers.

Tests run on PoCL's CPU device with POCL_MAX_WORK_GROUP_SIZE=256 (DESIGN.md §4), so a kernel
that needs more than a GPU allows fails here first. The variable must be set before pyopencl
creates a context, i.e. before clsplat is imported.
"""
from __future__ import annotations

import os

os.environ.setdefault("POCL_MAX_WORK_GROUP_SIZE", "256")

import math  # noqa: E402

import pytest  # noqa: E402

import clsplat  # noqa: E402  (before torch: clsplat.threads sets libgomp's short spin before torch loads it)
import torch  # noqa: E402, I100
from clsplat import reference as ref  # noqa: E402
from clsplat.config import RenderConfig  # noqa: E402

#: under pytest-xdist (``make test``, ``make check``) each worker takes its share of the cores for
#: torch: with every worker's torch on every core, the OpenMP threads outnumber the cores and spin
#: waiting on each other. With this and the import order above, the quick tier's DrivingForward,
#: autograd and gsplat-training tests on two workers took 77-88 s against 330-340 s (load 6-8)
if os.environ.get("PYTEST_XDIST_WORKER_COUNT"):
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"])))

F64 = torch.float64


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> torch.Tensor:
    """World-to-camera [4,4] (OpenCV: x right, y down, z forward) looking from eye at target."""
    eye, target, up = (torch.as_tensor(v, dtype=F64) for v in (eye, target, up))
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(z, up)
    if x.norm() < 1e-9:  # looking along up: pick another
        x = torch.linalg.cross(z, torch.tensor([1.0, 0.0, 0.0], dtype=F64))
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])  # rows: camera axes in world
    vm = torch.eye(4, dtype=F64)
    vm[:3, :3] = R
    vm[:3, 3] = -R @ eye
    return vm


def intrinsics(width: int, height: int, fov_deg: float = 60.0, jitter: float = 0.0,
               gen: torch.Generator | None = None) -> torch.Tensor:
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    cx, cy = width / 2, height / 2
    if jitter and gen is not None:
        j = (torch.rand(3, generator=gen, dtype=F64) - 0.5) * 2 * jitter
        f, cx, cy = f * (1 + j[0].item()), cx + j[1].item() * width, cy + j[2].item() * height
    return torch.tensor([[f, 0, cx], [0, f * 1.05, cy], [0, 0, 1]], dtype=F64)


def random_scene(seed: int = 0, N: int = 60, C: int = 2, width: int = 64, height: int = 48,
                 dtype: torch.dtype = F64, D: int = 3, colors_per_camera: bool = False,
                 sh_degree: int | None = None, K_extra: int = 0, scale_range=(0.02, 0.35),
                 opacity_range=(0.05, 0.99)) -> dict:
    """N Gaussians in a ball of radius ~1.2 around the origin, seen by C cameras on a sphere of
    radius ~4 looking roughly at the origin (random poses). Returns rasterization kwargs."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=F64)  # noqa: E731
    means = (r(N, 3) - 0.5) * 2.4
    quats = torch.randn(N, 4, generator=g, dtype=F64)
    quats = quats + 0.05 * torch.sign(quats)  # keep away from zero norm
    lo, hi = scale_range
    scales = torch.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * r(N, 3))
    opacities = opacity_range[0] + (opacity_range[1] - opacity_range[0]) * r(N)
    vms, Ks = [], []
    for _ in range(C):
        d = torch.randn(3, generator=g, dtype=F64)
        d = d / d.norm()
        eye = d * (3.5 + r(1).item())
        target = (r(3) - 0.5) * 0.4
        up = torch.randn(3, generator=g, dtype=F64)
        vms.append(look_at(eye, target, up))
        Ks.append(intrinsics(width, height, 50 + 20 * r(1).item(), jitter=0.05, gen=g))
    if sh_degree is not None:
        K = (sh_degree + 1) ** 2 + K_extra
        colors = torch.randn(N, K, 3, generator=g, dtype=F64) * 0.5
    elif colors_per_camera:
        colors = r(C, N, D)
    else:
        colors = r(N, D)
    out = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
               viewmats=torch.stack(vms), Ks=torch.stack(Ks), width=width, height=height)
    if sh_degree is not None:
        out["sh_degree"] = sh_degree
    return {k: (v.to(dtype) if isinstance(v, torch.Tensor) else v) for k, v in out.items()}


def single_camera(width: int = 64, height: int = 48, fov: float = 60.0, dtype=F64):
    """Identity pose (camera at origin looking down +z) and a centred pinhole."""
    return torch.eye(4, dtype=dtype)[None], intrinsics(width, height, fov).to(dtype)[None]


def torchrun_two(tmp_path, family: str, args: list[str], timeout: int = 600) -> tuple[dict, dict]:
    """Train ``family`` with ``args`` in one fresh process into ``tmp_path/one`` and under
    ``torchrun --nproc_per_node 2`` into ``tmp_path/two`` (one thread per process, the same
    environment); the two checkpoints, after asserting that both runs succeeded and the second ran
    two processes. The one-process run is not this interpreter's: torch state an earlier test left
    here changed DrivingForward's gradients by ~1e-6 of their size, which two fresh processes never
    showed (a fresh one-process run and the two-process run agree bit for bit)."""
    import socket
    import subprocess
    import sys

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    script = tmp_path / f"{family}_train.py"
    script.write_text(f"import sys; from clsplat.cli import console; sys.exit(console(['train', '{family}', *sys.argv[1:]]))")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run([sys.executable, str(script), *args, "--out", str(tmp_path / "one")],
                       capture_output=True, text=True, timeout=timeout, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    r = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port",
                        str(port), str(script), *args, "--out", str(tmp_path / "two")],
                       capture_output=True, text=True, timeout=timeout, env=env)
    # torchrun's own report fills the tail of stderr: the ranks' output (where a rank died) is before it
    assert r.returncode == 0, f"stdout: ...{r.stdout[-1500:]}\nstderr: {r.stderr[:2500]}\n...{r.stderr[-800:]}"
    assert "2 process(es)" in r.stdout
    return (torch.load(tmp_path / "one" / "checkpoint.pt", weights_only=True),
            torch.load(tmp_path / "two" / "checkpoint.pt", weights_only=True))


#: the Gaussian parameters a rasterization call differentiates, in its argument order
GRAD_PARAMS = ("means", "quats", "scales", "opacities", "colors")


def weighted_loss_grads(fn, sc: dict, absgrad: bool = False, **kw) -> dict:
    """``fn(means, quats, scales, opacities, colors, viewmats, Ks, W, H, **kw)`` on scene ``sc``
    and the gradients of a fixed loss, sum(render * ramp(-1, 1)) + sum(alpha^2), which weights
    every pixel and channel differently: ``render``, ``alpha``, each parameter's gradient, and
    ``absgrad`` (``means2d.absgrad``) when asked for."""
    leaves = {k: sc[k].clone().requires_grad_() for k in GRAD_PARAMS}
    if absgrad:
        kw["absgrad"] = True
    r, a, meta = fn(*(leaves[k] for k in GRAD_PARAMS), sc["viewmats"], sc["Ks"], sc["W"], sc["H"], **kw)
    w = torch.linspace(-1, 1, r.numel(), dtype=r.dtype).reshape(r.shape)
    ((r * w).sum() + a.square().sum()).backward()
    out = {"render": r.detach(), "alpha": a.detach()} | {k: v.grad for k, v in leaves.items()}
    if absgrad:
        out["absgrad"] = meta["means2d"].absgrad
    return out


@pytest.fixture(scope="session")
def bench_script():
    """``load(name)``: the module of ``bench/experiments/<name>.py`` (scripts, not a package)."""
    import importlib.util
    from pathlib import Path
    root = Path(__file__).resolve().parents[1] / "bench" / "experiments"

    def load(name: str):
        spec = importlib.util.spec_from_file_location(name, root / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod
    return load


@pytest.fixture(scope="session")
def loss_grads():
    """:func:`weighted_loss_grads`: images and gradients of one fixed loss, for comparing two renderers."""
    return weighted_loss_grads


@pytest.fixture(scope="session")
def two_process_run():
    """:func:`torchrun_two`: a family's one-process run beside its ``torchrun`` two-process run."""
    return torchrun_two


@pytest.fixture(scope="session")
def rt():
    return clsplat.get_runtime()


@pytest.fixture(scope="session")
def make_scene():
    return random_scene


@pytest.fixture(scope="session")
def camera():
    return single_camera


@pytest.fixture(scope="session")
def cfg64():
    return RenderConfig(precision="float64")


@pytest.fixture(scope="session")
def cfg32():
    return RenderConfig(precision="float32")


@pytest.fixture(scope="session")
def reference():
    return ref


#: the tiny AutoSplat run several files read (tests/test_autosplat_cli.py's ARGS, without --out)
AUTOSPLAT_TINY_RUN = ["train", "autosplat", "--preset", "tiny", "--frames", "0:4", "--scale", "0.2", "--cameras",
                      "CAM_FRONT", "CAM_BACK", "--no-progress", "--threads", "1"]   # one thread: see DF_TINY_RUN


@pytest.fixture(scope="session")
def autosplat_tiny_run(tmp_path_factory):
    """The run folder of ``clsplat AUTOSPLAT_TINY_RUN``, trained once per test session for every
    file that reads it. Read-only: a test that writes into a run copies it first."""
    from clsplat.cli import console
    out = tmp_path_factory.mktemp("autosplat_tiny") / "run"
    assert console([*AUTOSPLAT_TINY_RUN, "--out", str(out)]) == 0
    return out


#: the DrivingForward run read by the CLI and contract tests: tiny, 2 steps, checkpoints every
#: step, the validation curve every step, one held-out window scored; one torch thread, as every
#: tiny DrivingForward run the tests compare it with bit for bit (the default follows the load,
#: and another thread count sums the convolutions in another order)
DF_TINY_RUN = ["train", "drivingforward", "--preset", "tiny", "--steps", "2", "--no-progress", "--checkpoint-every",
               "1", "--eval-scenes", "1", "--val-every", "1", "--val-scenes", "1", "--threads", "1"]


@pytest.fixture(scope="session")
def df_tiny_run(tmp_path_factory):
    """The run folder of ``clsplat DF_TINY_RUN``, trained once per test session for every file
    that reads it. Read-only: a test that writes into a run copies it first."""
    from clsplat.cli import console
    out = tmp_path_factory.mktemp("df_tiny") / "run"
    assert console([*DF_TINY_RUN, "--out", str(out)]) == 0
    return out


def engine_project(rt, cfg: RenderConfig, scene: dict, tile_size: int = 16, near_plane=0.01,
                   far_plane=1e10, eps2d=0.3, radius_clip=0.0, antialiased=False) -> dict:
    """Run kernels/project.cl through clsplat.stages.project; host tensors keyed like the reference."""
    from clsplat import stages
    dt = cfg.dtype
    a = lambda k: rt.array(scene[k].to(dt).contiguous())  # noqa: E731
    p = stages.project(rt, cfg, a("means"), a("quats"), a("scales"), a("opacities"), a("viewmats"),
                       a("Ks"), scene["width"], scene["height"], tile_size, near_plane=near_plane,
                       far_plane=far_plane, eps2d=eps2d, radius_clip=radius_clip,
                       antialiased=antialiased)
    out = {k: getattr(p, k).host().clone() for k in
           ("means2d", "conics", "depths", "radii", "opacities", "rects")}
    out["_proj"] = p
    return out


def reference_project(scene: dict, cfg: RenderConfig = RenderConfig(), tile_size: int = 16,
                      near_plane=0.01, far_plane=1e10, eps2d=0.3, radius_clip=0.0,
                      antialiased=False) -> dict:
    f = lambda k: scene[k].to(F64)  # noqa: E731
    return ref.project(f("means"), f("quats"), f("scales"), f("opacities"), f("viewmats"), f("Ks"),
                       scene["width"], scene["height"], near_plane, far_plane, eps2d, radius_clip,
                       tile_size, antialiased, cfg)


@pytest.fixture(scope="session")
def run_project():
    return engine_project


@pytest.fixture(scope="session")
def ref_project():
    return reference_project


def engine_forward(rt, cfg: RenderConfig, scene: dict, feats: torch.Tensor, tile_size: int = 16,
                   save_last: bool = True, **proj_kw) -> dict:
    """project -> bin -> sort -> composite through the stage drivers; feats [C,N,CH]."""
    from clsplat import stages
    W, H = scene["width"], scene["height"]
    pr = engine_project(rt, cfg, scene, tile_size, **proj_kw)
    p = pr["_proj"]
    offsets, keys = stages.tile_lists(rt, cfg, p.rects, p.depths, W, H, tile_size)
    f = rt.array(feats.to(cfg.dtype).contiguous())
    out, T, last = stages.composite(rt, cfg, p.means2d, p.conics, p.opacities, p.extents, f, offsets, keys,
                                    W, H, tile_size, save_last)
    res = dict(pr)
    res.update(out=out.host().clone(), T=T.host().clone(),
               last=None if last is None else last.host().clone(),
               offsets=offsets.host().clone(), keys=keys.host().clone())
    return res


@pytest.fixture(scope="session")
def run_forward():
    return engine_forward


@pytest.fixture
def two_colour_ply(tmp_path):
    """A small INRIA .ply: a red cluster at x = -0.8 and a blue one at x = +0.8 (z up), and a camera
    (``look_at_viewmat([0, -4, 0.5], [0, 0, 0])``, 64x48) that sees red on its left, blue on its right.
    Returns (ply path, ViewCamera)."""
    from clsplat.io.ply import rgb_to_sh, write_ply
    from clsplat.viewer.scene import ViewCamera, look_at_viewmat

    g = torch.Generator().manual_seed(0)
    n = 400
    means = torch.randn(n, 3, generator=g) * 0.3
    means[: n // 2, 0] -= 0.8
    means[n // 2:, 0] += 0.8
    rgb = torch.zeros(n, 3)
    rgb[: n // 2, 0] = 0.9
    rgb[n // 2:, 2] = 0.9
    q = torch.zeros(n, 4)
    q[:, 0] = 1
    path = write_ply(tmp_path / "two.ply", means, q, torch.full((n, 3), 0.08), torch.full((n,), 0.9), rgb_to_sh(rgb))
    cam = ViewCamera("front", [[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]], look_at_viewmat([0, -4, 0.5], [0, 0, 0]), 64, 48)
    return path, cam


@pytest.fixture
def full_disk_on(monkeypatch):
    """``full_disk_on(part)``: from then on, matplotlib's ``savefig`` of a file whose name contains
    ``part`` writes a few bytes and fails with ENOSPC (a disk that fills during the write); other
    figures save normally."""
    import errno
    import os

    from matplotlib.figure import Figure

    savefig = Figure.savefig

    def arm(part: str) -> None:
        def full_disk(self, fname, *a, **k):
            if part not in str(fname):
                return savefig(self, fname, *a, **k)
            with open(fname, "wb") as fh:
                fh.write(b"\x89PNG")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        monkeypatch.setattr(Figure, "savefig", full_disk)

    return arm


#: session fixtures that train a model: every module that takes one runs on the same xdist worker
SHARED_RUNS = ("df_tiny_run", "autosplat_tiny_run")


def pytest_collection_modifyitems(config, items) -> None:
    """Under pytest-xdist's ``--dist loadgroup`` (``make test``, ``make check``): one group per test
    module, so that a module's fixtures are built once, on one worker; the modules that take the
    same session-trained run (:data:`SHARED_RUNS`) share a group, so that run is trained once. The
    groups holding the most ``slow`` tests go first, so that the longest work does not start last
    and leave the other worker idle."""
    if not config.pluginmanager.hasplugin("xdist") or config.getoption("dist", "no") != "loadgroup":
        return
    parent: dict[str, str] = {}

    def find(key: str) -> str:
        while parent.setdefault(key, key) != key:
            key = parent[key]
        return key

    for item in items:    # union each module with the shared runs its tests take
        module = item.nodeid.split("::")[0]
        for run in SHARED_RUNS:
            if run in getattr(item, "fixturenames", ()):
                parent[find(module)] = find(run)
    groups: dict[str, list] = {}
    for item in items:
        groups.setdefault(find(item.nodeid.split("::")[0]), []).append(item)
    order = sorted(groups, key=lambda g: -sum(1 for i in groups[g] if i.get_closest_marker("slow")))
    items[:] = [item for g in order for item in groups[g]]
    for item in items:
        item.add_marker(pytest.mark.xdist_group(find(item.nodeid.split("::")[0]).replace("/", ".")))
