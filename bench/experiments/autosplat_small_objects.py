"""Why AutoSplat's small moving objects stay below the image (issue 36, helper s5;
bench/notes/autosplat_moving_objects.md, "Pedestrians and the built-in street's cars"): the
object pixels of a finished run split by what each candidate cause predicts, on the held-out and
on the training frames of the same run.

* ``class``: moving car / pedestrian / other and, as the control, the parked cars (which the
  background reconstructs and which do not move).
* ``size``: the track's pixels in that view (bins :data:`SIZE_BINS`): if pedestrians score as
  cars of the same pixel size do, what they lack is pixels, not anything of their class.
* ``band`` / ``interior``: within ``--band`` pixels of a pixel that is not the track's, or not.
* ``border``: within ``--border`` pixels of the image edge (where a held-out view may show what
  no training view showed).
* ``train`` against ``held-out``: an object that is as bad on the frames it was trained on is
  underfit (budget, points, learning rates, densification); one that is good there and bad on
  held-out frames does not generalise (box, appearance, views).
* ``aliasing`` (``--aliasing``): the generator's own held-out images (one ray per pixel, as the
  runs are scored against) against the same views rendered with ``s x s`` rays per pixel
  (``--supersample``) on the same pixels: how far a perfectly anti-aliased picture of the truth
  would score from the truth a run is scored against, a property of the data, not of a model.

    PYTHONPATH=<tree> .venv/bin/python bench/experiments/autosplat_small_objects.py RUN [RUN ...] [--aliasing] [--out DIR]
    .venv/bin/python bench/experiments/autosplat_small_objects.py --from-json DIR/small_objects.json ...   # the rows again

Each RUN is a finished ``clsplat train autosplat`` folder on generated data (instance masks are the
generator's). Prints one markdown row per run and writes ``small_objects.json`` into ``--out``
(default: print only).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

#: per-view track pixel counts: [lo, hi) bins
SIZE_BINS: tuple[tuple[int, int], ...] = ((1, 16), (16, 64), (64, 256), (256, 10 ** 9))
KINDS = ("car", "pedestrian", "other", "parked")


def _near(mask: np.ndarray, width: int) -> np.ndarray:
    """``[C, H, W]`` bool: pixels of ``mask`` within ``width`` pixels (Chebyshev) of a pixel outside it."""
    m = torch.from_numpy(mask).float()[:, None]
    near = torch.nn.functional.max_pool2d(1 - m, 2 * width + 1, 1, width)[:, 0].numpy() > 0
    return mask & near


def _border(shape: tuple[int, ...], width: int) -> np.ndarray:
    """``[C, H, W]`` bool: pixels within ``width`` pixels of the image edge."""
    b = np.zeros(shape, bool)
    b[:, :width], b[:, -width:], b[:, :, :width], b[:, :, -width:] = True, True, True, True
    return b


class _Acc:
    """Squared-error sums and pixel counts under string keys; ``psnr(key)`` pools them."""

    def __init__(self) -> None:
        self.e: dict[str, float] = {}
        self.n: dict[str, int] = {}

    def add(self, key: str, err: np.ndarray, sel: np.ndarray) -> None:
        self.e[key] = self.e.get(key, 0.0) + float(err[sel].sum())
        self.n[key] = self.n.get(key, 0) + int(sel.sum())

    def psnr(self, key: str) -> float | None:
        n = self.n.get(key, 0)
        return None if n == 0 else float(-10 * np.log10(max(self.e[key] / (3 * n), 1e-12)))

    def table(self) -> dict:
        return {k: {"psnr": self.psnr(k), "pixels": self.n[k]} for k in sorted(self.n)}


def _kinds(seq, moving: set[int]) -> dict[int, str]:
    """``{track: kind}`` over every labelled track of ``seq`` (:data:`KINDS`)."""
    from clsplat.models.autosplat.object_report import object_class
    out = {}
    for f in seq.frames:
        for b in f.boxes:
            if b.track_id not in out:
                c = object_class(b.label)
                out[b.track_id] = c if b.track_id in moving else ("parked" if c == "car" else "static_" + c)
    return out


def _score_frames(tr, frames, kinds: dict[int, str], acc: _Acc, split: str, band: int, border: int,
                  truths: dict[int, np.ndarray] | None = None) -> None:
    """Add ``split``'s frames to ``acc``: the run's render against the data's image (or, with
    ``truths``, the data's image against ``truths[frame]``)."""
    d = tr.data
    for i in frames:
        g = d.images[i].numpy().astype(np.float64)
        if truths is None:
            with torch.no_grad():
                r = tr.render_frame(i).numpy().astype(np.float64)
        else:
            r = truths[i]
        err = ((np.clip(r, 0, 1) - np.clip(g, 0, 1)) ** 2).sum(-1)
        acc.add(f"{split}/image", err, np.ones(err.shape, bool))
        inst = np.stack([d.seq.frames[i].instances[c] for c in d.cameras])
        edge = _border(inst.shape, border)
        for t in np.unique(inst[inst > 0]):
            kind = kinds.get(int(t))
            if kind not in KINDS:
                continue
            m = inst == t
            b = _near(m, band)
            for k in range(m.shape[0]):
                n = int(m[k].sum())
                if n == 0:
                    continue
                mk = np.zeros_like(m)
                mk[k] = m[k]
                lo, hi = next(bin_ for bin_ in SIZE_BINS if bin_[0] <= n < bin_[1])
                acc.add(f"{split}/{kind}/size{lo}", err, mk)
            acc.add(f"{split}/{kind}", err, m)
            acc.add(f"{split}/{kind}/band", err, b)
            acc.add(f"{split}/{kind}/interior", err, m & ~b)
            acc.add(f"{split}/{kind}/border", err, m & edge)
            acc.add(f"{split}/{kind}/inner", err, m & ~edge)


def _supersampled(tr, run: Path, frames, s: int) -> dict[int, np.ndarray]:
    """``{frame: [C, H, W, 3]}``: the run's generated street rendered again at ``frames`` with
    ``s x s`` rays a pixel (the same config and seed otherwise; LiDAR off)."""
    from dataclasses import replace

    from clsplat.data.synthetic import SyntheticConfig, generate_sequence
    from clsplat.models.autosplat.data import _SYNTHETIC_FRAMES, _WORLD_SPECS, SYNTHETIC_DT
    d = tr.data
    m = json.loads((run / "metrics.json").read_text())
    spec = m.get("protocol", m).get("data", "synthetic")
    views = spec in ("synthetic:views", "synthetic:views-exact")
    c0 = d.seq.camera(d.cameras[0])
    cfg = SyntheticConfig(height=c0.height, width=c0.width, num_frames=_SYNTHETIC_FRAMES, seed=tr.preset.seed,
                          dt=SYNTHETIC_DT, signals=views, shadow=views, world=_WORLD_SPECS.get(spec, "classic"))
    hi = generate_sequence(replace(cfg, supersample=s, lidar=False))
    lo = generate_sequence(replace(cfg, lidar=False))
    out = {}
    for i in frames:
        a = np.stack([lo.frames[i].images[c] for c in d.cameras]).astype(np.float64)
        g = d.images[i].numpy().astype(np.float64)
        if np.abs(a - g).max() > 1e-3:
            raise ValueError(f"{run}: the regenerated frame {i} is not the run's (max diff {np.abs(a - g).max():.3g})")
        out[i] = np.stack([hi.frames[i].images[c] for c in d.cameras]).astype(np.float64)
    return out


def analyse(run: Path, band: int, border: int, aliasing: bool, supersample: int) -> dict:
    """The split of ``run``'s object error (module docstring), ``{"run", "acc": {key: {psnr, pixels}}}``."""
    from clsplat.models.autosplat.evaluate import trainer_from_checkpoint
    from clsplat.models.autosplat.init import moving_track_ids
    from clsplat.models.common.train import load_checkpoint

    ck = load_checkpoint(run / "checkpoint.pt", "autosplat")
    tr = trainer_from_checkpoint(ck, run / "checkpoint.pt", run, None, out_dir=Path("/tmp"))
    d = tr.data
    kinds = _kinds(d.seq, set(moving_track_ids(d.seq, tr.preset.dynamic_threshold)))
    acc = _Acc()
    _score_frames(tr, d.test_frames, kinds, acc, "test", band, border)
    _score_frames(tr, d.train_frames, kinds, acc, "train", band, border)
    if aliasing:
        _score_frames(tr, d.test_frames, kinds, acc, "alias", band, border,
                      truths=_supersampled(tr, run, d.test_frames, supersample))
    return {"run": run.name, "acc": acc.table()}


def _row(o: dict) -> str:
    a = o["acc"]

    def p(k: str) -> str:
        v = a.get(k)
        return "–" if v is None or v["psnr"] is None else f"{v['psnr']:.2f}"

    def share(k: str, whole: str) -> str:
        return "–" if whole not in a or k not in a else f"{a[k]['pixels'] / a[whole]['pixels']:.2f}"

    cells = [o["run"], p("test/image"), p("train/image")]
    for kind in KINDS:
        cells.append(f"{p(f'test/{kind}')} / {p(f'train/{kind}')}")
    for kind in ("car", "pedestrian", "parked"):
        cells.append(f"{p(f'test/{kind}/band')} / {p(f'test/{kind}/interior')} ({share(f'test/{kind}/band', f'test/{kind}')})")
        cells.append(f"{p(f'test/{kind}/border')} / {p(f'test/{kind}/inner')} ({share(f'test/{kind}/border', f'test/{kind}')})")
    for kind in ("car", "pedestrian", "parked"):
        cells.append(" / ".join(p(f"test/{kind}/size{lo}") for lo, _ in SIZE_BINS))
    cells.append(" / ".join(p(f"alias/{k}") for k in ("image", "car", "pedestrian", "parked")))
    return "| " + " | ".join(cells) + " |"


HEADER = ("| run | held-out image | train image | moving cars: held-out / train | pedestrians: held-out / train "
          "| other | parked cars | cars: band / interior (band share) | cars: border / inner (border share) "
          "| pedestrians: band / interior | pedestrians: border / inner | parked: band / interior "
          "| parked: border / inner | cars by pixels in the view: " + " / ".join(f"{lo}+" for lo, _ in SIZE_BINS)
          + " | pedestrians by size | parked by size | truth vs anti-aliased truth: image / cars / pedestrians / parked |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--band", type=int, default=1, help="silhouette band width in pixels (default 1)")
    p.add_argument("--border", type=int, default=4, help="image border width in pixels (default 4)")
    p.add_argument("--aliasing", action="store_true", help="also score the truth against its anti-aliased render")
    p.add_argument("--supersample", type=int, default=4, help="rays per pixel side for --aliasing (default 4)")
    p.add_argument("--out", type=Path, default=None, help="write small_objects.json here")
    p.add_argument("--from-json", action="store_true",
                   help="RUN arguments are small_objects.json files written before: print their rows only")
    a = p.parse_args()
    if a.from_json:
        print(HEADER)
        print("|" + "---|" * HEADER.count(" | ") + "---|")
        for f in a.runs:
            for o in json.loads(f.read_text()):
                print(_row(o))
        return
    for name, v in (("--band", a.band), ("--border", a.border), ("--supersample", a.supersample)):
        if v < 1:
            p.error(f"{name}: expected an integer >= 1, got {v}")
    print(HEADER)
    print("|" + "---|" * HEADER.count(" | ") + "---|")
    res = []
    for run in a.runs:
        o = analyse(run, a.band, a.border, a.aliasing, a.supersample)
        res.append(o)
        print(_row(o), flush=True)
        if a.out is not None:
            a.out.mkdir(parents=True, exist_ok=True)
            (a.out / "small_objects.json").write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
