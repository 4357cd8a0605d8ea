"""Where an AutoSplat run's error on a class of cars lies: silhouette or inside, coarse or fine (issue 36).

For a run on a street written by ``autosplat_pandaset.py`` (the generator's instance masks, as
``autosplat_pandaset_rescore.py`` regenerates them), the error on the cars' instance pixels of the
given frames is split two ways, each part as a PSNR over its own pixels:

* ``band``: pixels within ``--band`` pixels of the instance's edge (box fit, silhouettes, alpha);
  ``interior``: the rest of the instance;
* on the interior, ``coarse``: the error averaged over a ``--window`` × ``--window`` box inside the
  instance (colour and shading wrong over areas: appearance, lighting, a face's tone) and ``fine``:
  what remains (texture detail the model blurs). The two add up to the interior's squared error
  only approximately (the box average is not an orthogonal projection).

``--cars moving`` scores the truly moving cars (the object sets), ``parked`` the parked ones (the
background set): the same surfaces and grain, through the other half of the model.

Usage::

    .venv/bin/python bench/experiments/autosplat_error_anatomy.py RUN --frames 0 1 3 5 9 [--cars parked] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

PARTS = ("all", "band", "interior", "coarse", "fine")


def erode(mask: np.ndarray, pixels: int) -> np.ndarray:
    """``mask [H, W]`` eroded by ``pixels`` (3×3 steps)."""
    x = torch.from_numpy(mask.astype(np.float32))[None, None]
    for _ in range(pixels):
        x = -F.max_pool2d(-x, 3, 1, 1)
    return x[0, 0].numpy() > 0.5


def box_mean(a: np.ndarray, mask: np.ndarray, window: int) -> np.ndarray:
    """``a [H, W]`` averaged over a ``window``-wide box, counting only ``mask`` pixels."""
    def box(v):
        x = torch.from_numpy(np.ascontiguousarray(v, dtype=np.float64))[None, None]
        return F.avg_pool2d(x, window, 1, window // 2, count_include_pad=True)[0, 0].numpy()
    return box(a * mask) / np.maximum(box(mask.astype(np.float64)), 1e-12)


def split(e: np.ndarray, mask: np.ndarray, band: int, window: int) -> dict[str, tuple[float, int]]:
    """``{part: (squared error, values)}`` of one instance: error ``e [H, W, 3]`` on ``mask [H, W]``
    split into the module docstring's parts."""
    inner = erode(mask, band)
    coarse = np.stack([box_mean(e[..., c], inner, window) for c in range(3)], -1)
    parts = {"all": (e, mask), "band": (e, mask & ~inner), "interior": (e, inner),
             "coarse": (coarse, inner), "fine": (e - coarse, inner)}
    return {p: (float((v[mk] ** 2).sum()), 3 * int(mk.sum())) for p, (v, mk) in parts.items()}


def anatomy(run: Path, frames: list[int], cars: str, band: int, window: int, min_pixels: int) -> dict:
    """``{"psnr": {part: dB}, "pixels": {part: n}, ...}`` of one run (module docstring)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import autosplat_pandaset_rescore as rs
    from clsplat.models.autosplat.evaluate import trainer_from_checkpoint
    from clsplat.models.autosplat.init import moving_track_ids
    from clsplat.models.autosplat.object_report import object_class
    from clsplat.models.common.train import load_checkpoint

    if not (run / "checkpoint.pt").is_file():
        raise ValueError(f"run: no checkpoint.pt in {str(run)!r} (a finished AutoSplat run folder)")
    m = json.loads((run / "metrics.json").read_text())
    spec = m.get("protocol", m).get("data", "")
    if not spec.startswith("pandaset:"):
        raise ValueError(f"run: {run} is not a run on pandaset:DIR data ({spec!r})")
    folder = Path(spec.split(":", 1)[1])
    seed = int(folder.name.rsplit("_s", 1)[1]) if "_s" in folder.name else None
    if seed is None:
        raise ValueError(f"run: its data folder {folder.name!r} does not end _sSEED as autosplat_pandaset.py's")
    ck = load_checkpoint(run / "checkpoint.pt", "autosplat")
    tr = trainer_from_checkpoint(ck, run / "checkpoint.pt", run, None, out_dir=Path("/tmp"))
    d = tr.data
    n = len(d.seq.frames)
    bad = [f for f in frames if not 0 <= f < n]
    if bad:
        raise ValueError(f"--frames: {bad} outside the run's 0..{n - 1}")
    dt = (d.seq.frames[-1].timestamp - d.seq.frames[0].timestamp) / max(1, n - 1)
    world = "classic" if "classic" in folder.name else "busy"
    gen = rs._street(seed, world, d.height, d.width, n, round(dt, 6), tuple(d.cameras))
    moving = set(moving_track_ids(gen, tr.preset.dynamic_threshold))
    ids = {b.track_id for f in gen.frames for b in f.boxes
           if object_class(b.label) == "car" and (b.track_id in moving) == (cars == "moving")}
    sse = {p: 0.0 for p in PARTS}
    num = {p: 0 for p in PARTS}
    for i in frames:
        with torch.no_grad():
            r = np.clip(tr.render_frame(i).numpy().astype(np.float64), 0, 1)
        t = np.clip(d.images[i].numpy().astype(np.float64), 0, 1)
        for ci, cam in enumerate(d.cameras):
            inst = gen.frames[i].instances[cam]
            e = r[ci] - t[ci]
            for tid in ids:
                msk = inst == tid
                if msk.sum() < min_pixels:
                    continue
                for p, (s2, k) in split(e, msk, band, window).items():
                    sse[p] += s2
                    num[p] += k
    psnr = {p: (None if num[p] == 0 else float(10 * np.log10(num[p] / max(sse[p], 1e-20)))) for p in PARTS}
    return {"run": str(run), "frames": frames, "cars": cars, "band": band, "window": window,
            "train_frames": [f for f in frames if f in d.train_frames], "psnr": psnr,
            "pixels": {p: num[p] // 3 for p in PARTS}}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run", help="a finished AutoSplat run on a folder written by autosplat_pandaset.py")
    p.add_argument("--frames", type=int, nargs="+", default=[0, 1, 3, 5, 9], help="frame indices to score")
    p.add_argument("--cars", choices=("moving", "parked"), default="moving")
    p.add_argument("--band", type=int, default=2, help="the silhouette band's width, pixels (default 2)")
    p.add_argument("--window", type=int, default=5, help="the coarse part's box, pixels, odd (default 5)")
    p.add_argument("--min-pixels", type=int, default=200, help="skip instances smaller in a view (default 200)")
    p.add_argument("--json", help="write the figures here too")
    a = p.parse_args(argv)
    try:
        if a.band < 1:
            raise ValueError(f"--band: expected an integer >= 1, got {a.band}")
        if a.window < 3 or a.window % 2 == 0:
            raise ValueError(f"--window: expected an odd integer >= 3, got {a.window}")
        if not Path(a.run).is_dir():
            raise ValueError(f"run: no such directory {a.run!r}")
        o = anatomy(Path(a.run), a.frames, a.cars, a.band, a.window, a.min_pixels)
    except (ValueError, FileNotFoundError) as e:
        sys.exit(f"autosplat_error_anatomy.py: {e}")
    print(f"{a.run}: {a.cars} cars, frames {a.frames} (training frames among them: {o['train_frames']})")
    print("| PSNR dB | " + " | ".join(PARTS) + " |\n" + "|---" * (len(PARTS) + 1) + "|")
    print("| error | " + " | ".join("–" if o["psnr"][q] is None else f"{o['psnr'][q]:.2f}" for q in PARTS) + " |")
    print("| pixels | " + " | ".join(str(o["pixels"][q]) for q in PARTS) + " |")
    if a.json:
        Path(a.json).write_text(json.dumps(o, indent=1))


if __name__ == "__main__":
    main()
