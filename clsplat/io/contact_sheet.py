"""Contact sheet: one PNG showing, for each camera, the render, the ground truth and |error|.

Layout: one row per camera (rig order), three columns ``render | ground truth | |error|``,
a 4-pixel gap between panels, a text strip above each row naming the camera and its PSNR, column headings (and an
optional title line) at the top.
The error panel shows the per-pixel mean absolute error over RGB, multiplied by
``error_gain`` and mapped through matplotlib's ``inferno`` colour map (black = 0).
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from .atomic import atomic_write

__all__ = ["make_contact_sheet", "psnr"]


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two images in [0, 1] (inf if identical)."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


def _to_numpy(x, name: str) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    a = np.asarray(x, dtype=np.float32)
    if a.ndim != 4 or a.shape[3] != 3:
        raise ValueError(f"{name} must have shape [C, H, W, 3], got {list(a.shape)}")
    return a


def make_contact_sheet(
    renders,
    targets,
    path: str | Path,
    names: Sequence[str] | None = None,
    error_gain: float = 4.0,
    title: str | None = None,
) -> Path:
    """Write the contact sheet PNG.

    Args:
        renders: ``[C, H, W, 3]`` rendered images in [0, 1] (numpy or torch).
        targets: ``[C, H, W, 3]`` ground-truth images, same shape.
        path: output ``.png``; the parent folder must exist.
        names: C camera names (default ``cam0..``).
        error_gain: factor applied to |error| before the colour map.
        title: optional line at the top of the sheet.
    Returns:
        the path written.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib import colormaps
    from matplotlib.figure import Figure

    r = _to_numpy(renders, "renders")
    g = _to_numpy(targets, "targets")
    if r.shape != g.shape:
        raise ValueError(f"renders {list(r.shape)} and targets {list(g.shape)} must have the same shape")
    c, h, w, _ = r.shape
    if names is None:
        names = [f"cam{i}" for i in range(c)]
    names = list(names)
    if len(names) != c:
        raise ValueError(f"names has {len(names)} entries for {c} cameras")
    if not (np.isfinite(error_gain) and error_gain > 0):
        raise ValueError(f"error_gain must be a positive number, got {error_gain!r}")
    p = Path(path)
    if p.suffix.lower() != ".png":
        raise ValueError(f"contact sheet path {str(p)!r} must end in .png")
    if not p.parent.is_dir():
        raise FileNotFoundError(f"output folder does not exist: {str(p.parent)!r}")
    gap, strip = 4, 18
    top = strip * (2 if title else 1)
    sheet_h = top + c * (strip + h) + (c - 1) * gap
    sheet_w = 3 * w + 2 * gap
    sheet = np.ones((sheet_h, sheet_w, 3), dtype=np.float32)
    cmap = colormaps["inferno"]
    labels = []
    for i in range(c):
        y = top + i * (strip + h + gap) + strip
        rc = np.clip(r[i], 0, 1)
        gc = np.clip(g[i], 0, 1)
        err = np.abs(rc - gc).mean(axis=2)
        emap = cmap(np.clip(err * error_gain, 0, 1))[..., :3]
        for j, panel in enumerate((rc, gc, emap)):
            x = j * (w + gap)
            sheet[y:y + h, x:x + w] = panel
        labels.append((y - strip, f"{names[i]}  PSNR {psnr(rc, gc):.2f} dB"))
    dpi = 100
    fig = Figure(figsize=(sheet_w / dpi, sheet_h / dpi), dpi=dpi)
    fig.figimage(sheet, xo=0, yo=0, origin="upper")
    for y0, text in labels:
        fig.text(3 / sheet_w, 1 - (y0 + strip - 4) / sheet_h, text, fontsize=8, color="black")
    for j, head in enumerate(("render", "ground truth", f"|error| x{error_gain:g}")):
        fig.text((j * (w + gap) + 3) / sheet_w, 1 - (top - 4) / sheet_h, head, fontsize=8, color="black",
                 weight="bold")
    if title:
        fig.text(3 / sheet_w, 1 - (strip - 4) / sheet_h, title, fontsize=8, color="black", weight="bold")
    return atomic_write(p, lambda tmp: fig.savefig(str(tmp), dpi=dpi, format="png"))
