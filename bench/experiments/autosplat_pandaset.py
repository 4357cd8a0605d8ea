"""Write a PandaSet-format sequence from a generated street (issue 19's "sharp on recorded data").

A quarter of PandaSet's resolution (1920 x 1080 -> 480 x 270), PandaSet's three front cameras
(front, front-left, front-right), 40 frames at PandaSet's 10 Hz, with the generator's fine texture
(``SyntheticConfig.fine_texture``) so that a blurred reconstruction costs SSIM, and each LiDAR
point's class written as PandaSet semseg (the road labels AutoSplat's road set and flatness need
on data without image masks). The folder is then trained on exactly as a real PandaSet sequence:

    .venv/bin/python bench/experiments/autosplat_pandaset.py --out bench/out/pandaset_q/001
    .venv/bin/clsplat train autosplat --data pandaset:bench/out/pandaset_q/001 --preset small \\
        --cameras CAM_FRONT CAM_FRONT_LEFT CAM_FRONT_RIGHT --out RUN

``--world busy`` (issue 36) writes a street of the ``busy`` world instead (20 and more movers: cars,
trucks, pedestrians; ``overtake``: one car overtaking close beside the ego) on flat ground (its
drawn gradient and crossfall set to 0: PandaSet's cuboids hold a yaw alone), the PandaSet-format
sequence with many moving objects:

    .venv/bin/python bench/experiments/autosplat_pandaset.py --world busy --cameras CAM_FRONT \\
        CAM_FRONT_LEFT CAM_FRONT_RIGHT CAM_BACK_LEFT CAM_BACK_RIGHT CAM_BACK --out bench/out/pandaset_busy/001

``--tracker-noise`` (issue 36, "exact and noisy boxes side by side") perturbs every box with
:class:`clsplat.data.synthetic.views.TrackerNoise`'s defaults (the noise of ``synthetic:busy-noisy``,
one seeded draw per track, ``--seed``) before writing: the written cuboids are the noisy ones, as a
recording's tracker boxes are, and the exact boxes are not written anywhere (a run on the folder
scores its objects on the pixels of the boxes it has). The busy street at the ``demo`` preset's
geometry (six cameras at 176 x 320, which ``demo`` halves; 16 frames at 0.2 s; the generator's
defaults otherwise), as ``synthetic:busy[-noisy]`` generates it, on flat ground:

    .venv/bin/python bench/experiments/autosplat_pandaset.py --world busy --seed 3 --frames 16 --dt 0.2 \
        --height 176 --width 320 --fine-texture 0 --supersample 1 --cameras CAM_FRONT CAM_FRONT_LEFT \
        CAM_FRONT_RIGHT CAM_BACK_LEFT CAM_BACK_RIGHT CAM_BACK [--tracker-noise] --out DIR
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from clsplat.data.scene import CAMERA_NAMES
from clsplat.data.synthetic.world import WORLDS

CAMERAS = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT")


def write(out: Path, seed: int, frames: int, height: int, width: int, fine: float, supersample: int,
          cameras: tuple[str, ...] = CAMERAS, world: str = "classic", dt: float = 0.1,
          tracker_noise: bool = False) -> Path:
    """Generate the street and write it as a PandaSet folder (with ``tracker_noise`` the boxes
    perturbed first, module docstring); returns ``out``."""
    from clsplat.data.pandaset import write_pandaset
    from clsplat.data.synthetic import SyntheticConfig, generate_sequence

    cfg = SyntheticConfig(height=height, width=width, num_frames=frames, seed=seed, dt=dt, cameras=cameras,
                          fine_texture=fine, supersample=supersample, world=world)
    if not (isinstance(dt, (int, float)) and dt > 0):
        raise ValueError(f"--dt: expected a frame interval > 0 seconds, got {dt!r}")
    t0 = time.perf_counter()
    if world == "classic":
        seq = generate_sequence(cfg)
    else:   # flat ground: PandaSet's cuboids hold a yaw alone, and a drawn gradient or crossfall tilts the boxes
        from dataclasses import replace

        from clsplat.data.synthetic import draw_world
        seq = generate_sequence(cfg, world_params=replace(draw_world(seed, world), grade=0.0, vcurv=0.0,
                                                          crossfall=0.0))
    scene = seq.metadata["scene"]
    seq.metadata["lidar_semantics"] = [scene.lidar(f.ego_to_world, f.timestamp, with_semantics=True)[1]
                                       for f in seq.frames]
    if tracker_noise:   # as load_sequence does for synthetic:busy-noisy: the defaults, one draw per track
        from clsplat.data.synthetic.views import TrackerNoise, add_tracker_noise
        add_tracker_noise(seq, TrackerNoise(), seed=seed)
    t1 = time.perf_counter()
    write_pandaset(seq, out)
    print(f"generated {frames} frames x {len(cameras)} cameras at {width}x{height} in {t1 - t0:.1f} s, "
          f"wrote {out} in {time.perf_counter() - t1:.1f} s", flush=True)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", required=True, help="the sequence folder to write (e.g. .../001)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--height", type=int, default=270)
    p.add_argument("--width", type=int, default=480)
    p.add_argument("--dt", type=float, default=0.1, help="frame interval, seconds (PandaSet: 0.1)")
    p.add_argument("--fine-texture", type=float, default=0.3)
    p.add_argument("--supersample", type=int, default=2)
    p.add_argument("--cameras", nargs="+", default=list(CAMERAS), choices=list(CAMERA_NAMES),
                   help="generator cameras to write (PandaSet names: CAM_BACK_LEFT / CAM_BACK_RIGHT are written as "
                        "left_camera / right_camera, PandaSet's 90-degree side cameras' slots)")
    p.add_argument("--world", default="classic", choices=list(WORLDS),
                   help="the generated world (default classic; issue 36: busy, overtake)")
    p.add_argument("--tracker-noise", action="store_true",
                   help="write boxes perturbed with TrackerNoise's defaults (seeded by --seed), as a tracker's")
    a = p.parse_args()
    write(Path(a.out), a.seed, a.frames, a.height, a.width, a.fine_texture, a.supersample, tuple(a.cameras),
          a.world, a.dt, a.tracker_noise)


if __name__ == "__main__":
    main()
