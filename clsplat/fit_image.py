"""Optimisation example: fit 2D-ish Gaussians to one image through :func:`clsplat.rasterization`.

N Gaussians sit in the plane ``z = depth`` in front of a single pinhole camera at the origin
(identity world-to-camera matrix, OpenCV axes). The optimised parameters are

* ``xy``          [N, 2] plane coordinates (the means are ``(x, y, depth)``),
* ``log_scales``  [N, 3] (scales = ``exp``),
* ``quats``       [N, 4] raw wxyz quaternions (the rasteriser normalises them),
* ``opacity_logits`` [N] (opacities = ``sigmoid``),
* ``color_logits`` [N, 3] (colours = ``sigmoid``, so the render stays in ``[0, 1]``),

all trained with :class:`torch.optim.Adam` on the mean squared error against the target.

Command line::

    python -m clsplat.fit_image OUT_DIR [--target image.png] [--gaussians 2000] [--iterations 300]
"""
from __future__ import annotations

import math
import numbers
import time
from pathlib import Path

import numpy as np
import torch

from .argparser import ArgumentParser
from .constants import MAX_IMAGE_SIDE
from .memory import check_host_memory

__all__ = ["fit_image", "main", "procedural_target"]

_DEPTH = 1.0  # distance of the Gaussian plane from the camera


def _check_int(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")
    return int(value)


def _check_target(target) -> torch.Tensor:
    if isinstance(target, np.ndarray):
        target = torch.from_numpy(np.ascontiguousarray(target))
    if not isinstance(target, torch.Tensor):
        raise ValueError(f"target must be a torch.Tensor [H, W, 3], got {type(target).__name__}")
    if target.ndim != 3 or target.shape[2] != 3 or target.shape[0] < 1 or target.shape[1] < 1:
        raise ValueError(f"target must have shape [H, W, 3] with H, W >= 1, got {list(target.shape)}")
    if not target.is_floating_point():
        raise ValueError(f"target must be a floating-point tensor with values in [0, 1], got dtype {target.dtype}")
    if not torch.isfinite(target).all():
        raise ValueError("target contains NaN or infinite values")
    lo, hi = float(target.min()), float(target.max())
    if lo < 0.0 or hi > 1.0:
        raise ValueError(f"target values must lie in [0, 1], got range [{lo:.4g}, {hi:.4g}]")
    return target.detach().to(dtype=torch.float32, device="cpu").contiguous()


def _camera(width: int, height: int) -> tuple[torch.Tensor, torch.Tensor, float, float]:
    """Identity view matrix and intrinsics; returns (viewmat [1,4,4], K [1,3,3], half-extent x, y)
    of the image footprint on the plane z = _DEPTH."""
    f = float(max(width, height))  # ~53 degree field of view across the long side
    K = torch.tensor([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]],
                     dtype=torch.float32)[None]
    viewmat = torch.eye(4, dtype=torch.float32)[None]
    return viewmat, K, _DEPTH * width / (2.0 * f), _DEPTH * height / (2.0 * f)


def fit_image(target: torch.Tensor, n_gaussians: int = 2000, iterations: int = 300,
              lr: float = 0.01, seed: int = 0, device=None, progress: bool = True, *,
              torch_threads: int | None = 1) -> dict:
    """Fit ``n_gaussians`` Gaussians to ``target`` with Adam on the MSE.

    Args:
        target: [H, W, 3] float tensor (or numpy array) with values in [0, 1].
        n_gaussians: number of Gaussians (>= 1).
        iterations: Adam steps (>= 1).
        lr: Adam learning rate for every parameter group (> 0).
        seed: seed of the random initialisation.
        device: OpenCL device passed to :func:`clsplat.rasterization` (default ``CLSPLAT_DEVICE``).
        progress: show a tqdm progress bar.
        torch_threads: ``torch.set_num_threads`` for the duration of the fit (restored after);
            None leaves it alone. The default 1 matters on PoCL's CPU device: torch's intra-op
            threads and PoCL's worker threads compete for the same cores, and on a 2-core
            machine the small per-step torch ops (activations, loss, input checks) then take
            milliseconds each; measured 3-10x slower steps with torch's default thread count.
    Returns:
        ``{"losses": [float] * iterations`` (MSE before each step), ``"psnr"``: PSNR in dB of
        the final render, ``"render"``: final [H, W, 3] float32 render, ``"seconds_per_step"``:
        mean wall time of a forward + backward + Adam step, the first step (OpenCL kernel build)
        excluded when there is more than one}.
    """
    target = _check_target(target)
    n_gaussians = _check_int("n_gaussians", n_gaussians, 1)
    iterations = _check_int("iterations", iterations, 1)
    if isinstance(lr, bool) or not isinstance(lr, numbers.Real) or not math.isfinite(lr) or lr <= 0:
        raise ValueError(f"lr must be a finite number > 0, got {lr!r}")
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise ValueError(f"seed must be an int, got {seed!r}")
    if torch_threads is not None:
        torch_threads = _check_int("torch_threads", torch_threads, 1)
    previous_threads = torch.get_num_threads()
    if torch_threads is not None:
        torch.set_num_threads(torch_threads)
    try:
        return _fit(target, n_gaussians, iterations, float(lr), int(seed), device, progress)
    finally:
        if torch_threads is not None:
            torch.set_num_threads(previous_threads)


def _fit(target: torch.Tensor, n_gaussians: int, iterations: int, lr: float, seed: int, device,
         progress: bool) -> dict:
    from tqdm.auto import tqdm

    from .rendering import rasterization

    height, width = int(target.shape[0]), int(target.shape[1])
    viewmat, K, hx, hy = _camera(width, height)

    g = torch.Generator().manual_seed(int(seed))
    xy = torch.stack([(torch.rand(n_gaussians, generator=g) * 2 - 1) * hx,
                      (torch.rand(n_gaussians, generator=g) * 2 - 1) * hy], dim=1)
    # one Gaussian per ~ (4 hx hy / N) of plane area; start with sigma about half the spacing
    spacing = math.sqrt(4.0 * hx * hy / n_gaussians)
    log_scales = torch.full((n_gaussians, 3), math.log(0.5 * spacing))
    log_scales += 0.1 * torch.randn(n_gaussians, 3, generator=g)
    quats = torch.randn(n_gaussians, 4, generator=g)
    opacity_logits = torch.zeros(n_gaussians)  # opacity 0.5
    color_logits = 0.5 * torch.randn(n_gaussians, 3, generator=g)
    params = [p.requires_grad_() for p in (xy, log_scales, quats, opacity_logits, color_logits)]
    depth = torch.full((n_gaussians, 1), _DEPTH)
    opt = torch.optim.Adam(params, lr=float(lr))

    def render() -> torch.Tensor:
        means = torch.cat([xy, depth], dim=1)
        colors, _, _ = rasterization(means, quats, torch.exp(log_scales),
                                     torch.sigmoid(opacity_logits), torch.sigmoid(color_logits),
                                     viewmat, K, width, height, device=device)
        return colors[0]

    losses: list[float] = []
    step_times: list[float] = []
    bar = tqdm(range(iterations), disable=not progress, desc="fit_image", leave=False)
    for it in bar:
        t0 = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        try:
            img = render()
        except ValueError as e:
            if it == 0:
                raise
            # the parameters left the range the renderer accepts: the step size is to blame
            raise ValueError(f"lr: the fit diverged at iteration {it} with lr={lr:g} ({e}); "
                             "use a smaller lr") from None
        loss = torch.nn.functional.mse_loss(img, target)
        loss.backward()
        opt.step()
        step_times.append(time.perf_counter() - t0)
        value = float(loss.detach())
        if not (math.isfinite(value) and all(bool(torch.isfinite(p).all()) for p in params)):
            raise ValueError(f"lr: the fit diverged at iteration {it} with lr={lr:g} (loss {value}, "
                             "parameters no longer finite); use a smaller lr")
        losses.append(value)
        bar.set_postfix(loss=f"{value:.5f}")
    bar.close()

    with torch.no_grad():
        final = render().clamp(0.0, 1.0).detach().to(torch.float32)
    mse = float(torch.mean((final - target) ** 2))
    psnr = float("inf") if mse == 0.0 else -10.0 * math.log10(mse)
    timed = step_times[1:] if len(step_times) > 1 else step_times
    return {"losses": losses, "psnr": psnr, "render": final,
            "seconds_per_step": float(sum(timed) / len(timed))}


def procedural_target(height: int = 96, width: int = 128) -> torch.Tensor:
    """Built-in [H, W, 3] float32 target in [0, 1]: a smooth colour gradient, a checkerboard
    patch and three coloured discs."""
    height = _check_int("height", height, 1)
    width = _check_int("width", width, 1)
    if max(height, width) > MAX_IMAGE_SIDE:
        raise ValueError(f"height, width: at most {MAX_IMAGE_SIDE} pixels a side, got {height}x{width}")
    check_host_memory(10 * 3 * 4 * height * width, f"height, width: a {height}x{width} target")
    y, x = torch.meshgrid((torch.arange(height, dtype=torch.float32) + 0.5) / height,
                          (torch.arange(width, dtype=torch.float32) + 0.5) / width, indexing="ij")
    img = torch.stack([0.2 + 0.6 * x, 0.3 + 0.4 * y, 0.8 - 0.5 * x * y], dim=-1)
    checker = ((torch.floor(x * 8) + torch.floor(y * 8)) % 2).unsqueeze(-1)
    in_patch = ((x > 0.6) & (y > 0.55)).unsqueeze(-1)
    img = torch.where(in_patch, 0.15 + 0.7 * checker.expand_as(img), img)
    aspect = width / height
    for cx, cy, r, rgb in ((0.25, 0.3, 0.16, (0.9, 0.15, 0.1)), (0.55, 0.25, 0.1, (0.1, 0.7, 0.2)),
                           (0.3, 0.72, 0.12, (0.95, 0.85, 0.1))):
        disc = (((x - cx) * aspect) ** 2 + (y - cy) ** 2 < r * r).unsqueeze(-1)
        img = torch.where(disc, torch.tensor(rgb), img)
    return img.clamp(0.0, 1.0).contiguous()


def _save_loss_curve(path: Path, losses: list[float]) -> None:
    import matplotlib
    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4), dpi=100)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(np.arange(len(losses)), losses)
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("MSE loss")
    ax.set_title("clsplat fit_image")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(str(path), format="png")


def main(out_dir, target_path: str | None = None, n_gaussians: int = 2000, iterations: int = 300,
         lr: float = 0.01, seed: int = 0, device=None, progress: bool = True,
         size: tuple[int, int] = (96, 128), torch_threads: int | None = 1) -> dict:
    """Fit an image and write ``target.png``, ``fit.png`` and ``loss_curve.png`` into ``out_dir``.

    Args:
        out_dir: output folder (created if missing).
        target_path: PNG/JPEG/EXR to fit; None uses :func:`procedural_target` of ``size``
            (height, width).
        n_gaussians, iterations, lr, seed, device, progress, torch_threads: as in
            :func:`fit_image`.
    Returns:
        metrics: ``initial_loss``, ``final_loss``, ``losses``, ``psnr``, ``seconds_per_step``,
        ``n_gaussians``, ``iterations``, ``height``, ``width`` and the written ``paths``.
    """
    from .io.atomic import write_atomically
    from .io.images import read_image, write_image

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"out_dir: {str(out)!r} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    if target_path is None:
        if not (isinstance(size, (tuple, list)) and len(size) == 2):
            raise ValueError(f"size must be (height, width), got {size!r}")
        target = procedural_target(size[0], size[1])
    else:
        target = torch.from_numpy(np.clip(read_image(target_path, channels=3), 0.0, 1.0))
    result = fit_image(target, n_gaussians=n_gaussians, iterations=iterations, lr=lr, seed=seed,
                       device=device, progress=progress, torch_threads=torch_threads)
    paths = {"target": out / "target.png", "fit": out / "fit.png",
             "loss_curve": out / "loss_curve.png"}
    # all three or none: a failed write (full disk) leaves the previous run's files whole
    write_atomically([(paths["target"], lambda p: write_image(p, target.numpy())),
                      (paths["fit"], lambda p: write_image(p, result["render"].numpy())),
                      (paths["loss_curve"], lambda p: _save_loss_curve(p, result["losses"]))])
    return {"initial_loss": result["losses"][0], "final_loss": result["losses"][-1],
            "losses": result["losses"], "psnr": result["psnr"],
            "seconds_per_step": result["seconds_per_step"], "n_gaussians": n_gaussians,
            "iterations": iterations, "height": int(target.shape[0]),
            "width": int(target.shape[1]), "paths": {k: str(v) for k, v in paths.items()}}


def _cli(argv=None) -> None:
    ap = ArgumentParser(prog="clsplat fit", description="Fit Gaussians to an image with clsplat.")
    ap.add_argument("--out", required=True, help="output folder (fit.png, loss_curve.png, metrics.json)")
    ap.add_argument("--target", default=None, help="image to fit (default: built-in pattern)")
    ap.add_argument("--gaussians", type=int, default=2000)
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--lr", type=float, default=0.01)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default=None)
    ap.add_argument("--threads", type=int, default=1,
                    help="torch threads during the fit (default 1; 0: leave torch's default)")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    a = ap.parse_args(argv)
    m = main(a.out, a.target, n_gaussians=a.gaussians, iterations=a.iterations, lr=a.lr,
             seed=a.seed, device=a.device, progress=not a.no_progress,
             torch_threads=a.threads or None)
    print(f"loss {m['initial_loss']:.5f} -> {m['final_loss']:.5f}, PSNR {m['psnr']:.2f} dB, "
          f"{m['seconds_per_step'] * 1e3:.1f} ms/step; wrote {', '.join(m['paths'].values())}")


if __name__ == "__main__":
    _cli()
