"""clsplat's exact render of a :class:`~.scene.ViewScene` through :func:`clsplat.rasterization`:
one camera (the viewer's server-side render) or a list of cameras written to a folder
(``clsplat render``).

The render is the engine's: per-tile depth sort of the Gaussians (ties by id), gsplat's 2D
covariance with eps2d 0.3, front-to-back compositing, full SH of the scene's degree. It differs
from the browser's splats (viser) where the two sort differently: viser sorts once per frame by
view depth of the centres for the whole image, clsplat per 16x16 tile; where Gaussians overlap
closely in depth the blend order differs. viser also shows only the DC colour (no
view-dependent SH) and stores covariances in float16.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from .scene import ViewCamera, ViewScene

__all__ = ["render_view", "render_cameras"]


def render_view(scene: ViewScene, camera: ViewCamera, device=None, background=(0.0, 0.0, 0.0),
                max_pixels: int = 4096 * 4096) -> tuple[np.ndarray, float]:
    """Render ``camera``; returns (float32 [H, W, 3] in [0, 1], seconds the render took)."""
    from ..rendering import rasterization

    if camera.width * camera.height > max_pixels:
        raise ValueError(f"camera {camera.name!r}: {camera.width}x{camera.height} is more than {max_pixels} pixels")
    t0 = time.perf_counter()
    V = torch.as_tensor(camera.viewmat, dtype=torch.float32)[None]
    K = torch.as_tensor(camera.K, dtype=torch.float32)[None]
    bg = torch.tensor([list(background)], dtype=torch.float32)
    with torch.no_grad():
        if len(scene) == 0:
            img = bg[0].expand(camera.height, camera.width, 3).clone()
        else:
            out, _, _ = rasterization(scene.means, scene.quats, scene.scales, scene.opacities, scene.sh, V, K,
                                      camera.width, camera.height, sh_degree=scene.sh_degree, backgrounds=bg,
                                      device=device)
            img = out[0]
    return img.clamp(0, 1).numpy().astype(np.float32), time.perf_counter() - t0


def _bar(i: int, n: int, width: int = 24) -> str:
    k = round(width * i / n)
    return "[" + "#" * k + "." * (width - k) + f"] {i}/{n}"


def render_cameras(scene: ViewScene, cameras: list[ViewCamera], out_dir: str | Path, ext: str = ".png",
                   device=None, background=(0.0, 0.0, 0.0), stream=None) -> list[dict]:
    """Render every camera to ``out_dir/<name><ext>`` (written atomically through
    :func:`clsplat.io.images.write_image`), printing a progress bar and each view's render time on
    ``stream`` (default stderr); writes ``out_dir/render_times.json``.

    Returns:
        one ``{"name", "file", "render_s"}`` per camera.
    """
    from ..io.atomic import write_text_atomic
    from ..io.images import write_image

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stream = sys.stderr if stream is None else stream
    rows = []
    for i, cam in enumerate(cameras):
        img, secs = render_view(scene, cam, device=device, background=background)
        f = write_image(out / f"{cam.name}{ext}", img)
        rows.append({"name": cam.name, "file": f.name, "width": cam.width, "height": cam.height, "render_s": secs})
        print(f"{_bar(i + 1, len(cameras))}  {cam.name}: {secs * 1e3:.1f} ms", file=stream, flush=True)
    times = [r["render_s"] for r in rows]
    summary = {"views": rows, "median_render_s": float(np.median(times)), "total_render_s": float(sum(times)),
               "gaussians": len(scene)}
    write_text_atomic(out / "render_times.json", json.dumps(summary, indent=1))
    return rows
