"""The sequence AutoSplat reconstructs: ``--data`` (the built-in street, PandaSet, nuScenes) cut
to ``--frames`` and scaled by ``--scale``, with each argument named when it is wrong."""
from __future__ import annotations

from clsplat.data.scene import DrivingSequence

from ..common.metrics import SSIM_WINDOW

__all__ = ["load_sequence", "parse_frames", "SYNTHETIC_DT"]

#: frame interval of the built-in street (seconds): 16 frames cover 3 s of driving.
SYNTHETIC_DT = 0.2
_SYNTHETIC_FRAMES = 16


def parse_frames(text: str | None) -> tuple[int, int] | None:
    """``"A:B"`` -> (A, B) with 0 <= A < B; ValueError naming ``--frames`` otherwise."""
    if text is None:
        return None
    try:
        a, b = (int(x) for x in text.split(":"))
    except ValueError:
        raise ValueError(f"--frames: expected A:B with integers A < B, got {text!r}") from None
    if a < 0 or b <= a:
        raise ValueError(f"--frames: the range {text!r} is empty or negative; expected 0 <= A < B")
    return a, b


def load_sequence(spec: str, cameras: list[str] | None, frames: tuple[int, int] | None, scale: float,
                  seed: int = 0, safe_pickle: bool = True) -> DrivingSequence:
    """The sequence named by ``--data``, cut to ``frames`` and scaled by ``scale`` (PandaSet's
    pickles allow-listed unless ``safe_pickle=False``, ``--trust-pickle``)."""
    if not (isinstance(scale, (int, float)) and 0 < scale <= 4):
        raise ValueError(f"--scale: expected a number in (0, 4], got {scale!r}")
    if spec == "synthetic":
        from clsplat.data.synthetic import SyntheticConfig, generate_sequence
        a, b = frames or (0, _SYNTHETIC_FRAMES)
        cfg = SyntheticConfig(height=max(8, round(176 * scale)), width=max(8, round(320 * scale)), num_frames=b,
                              seed=seed, dt=SYNTHETIC_DT)
        seq = generate_sequence(cfg)
        if a:
            seq = DrivingSequence(seq.cameras, seq.frames[a:b], seq.name, seq.metadata)
    elif spec.startswith("pandaset:"):
        from clsplat.data.pandaset import load_pandaset
        idx = None if frames is None else list(range(*frames))
        seq = load_pandaset(spec.split(":", 1)[1], cameras=cameras, frames=idx, safe_pickle=safe_pickle)
    elif spec.startswith("nuscenes:"):
        from clsplat.data.nuscenes import load_nuscenes_scene
        seq = load_nuscenes_scene(spec.split(":", 1)[1])
        if frames is not None:
            if frames[1] > len(seq.frames):
                raise ValueError(f"--frames: {frames[0]}:{frames[1]} is past the scene's {len(seq.frames)} frames")
            seq = DrivingSequence(seq.cameras, seq.frames[frames[0]:frames[1]], seq.name, seq.metadata)
    else:
        raise ValueError(f"--data: expected synthetic, pandaset:PATH or nuscenes:PATH, got {spec!r}")
    if frames is not None and spec != "synthetic" and not seq.frames:
        raise ValueError(f"--frames: {frames[0]}:{frames[1]} selects no frame")
    if spec != "synthetic" and scale != 1:
        from ..common.data import resize_sequence
        c0 = seq.cameras[0]
        seq = resize_sequence(seq, max(8, round(c0.height * scale)), max(8, round(c0.width * scale)))
    small = [c for c in seq.cameras if min(c.height, c.width) < SSIM_WINDOW]
    if small:
        raise ValueError(f"--scale: {scale:g} makes camera {small[0].name} {small[0].height}x{small[0].width} "
                         f"pixels, smaller than SSIM's {SSIM_WINDOW}-pixel window; use a larger --scale")
    return seq
