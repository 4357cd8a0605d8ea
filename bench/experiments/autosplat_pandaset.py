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
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from clsplat.data.scene import CAMERA_NAMES
from clsplat.data.synthetic.world import WORLDS

CAMERAS = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT")


def write(out: Path, seed: int, frames: int, height: int, width: int, fine: float, supersample: int,
          cameras: tuple[str, ...] = CAMERAS, world: str = "classic") -> Path:
    """Generate the street and write it as a PandaSet folder; returns ``out``."""
    from clsplat.data.pandaset import write_pandaset
    from clsplat.data.synthetic import SyntheticConfig, generate_sequence

    cfg = SyntheticConfig(height=height, width=width, num_frames=frames, seed=seed, dt=0.1, cameras=cameras,
                          fine_texture=fine, supersample=supersample, world=world)
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
    p.add_argument("--fine-texture", type=float, default=0.3)
    p.add_argument("--supersample", type=int, default=2)
    p.add_argument("--cameras", nargs="+", default=list(CAMERAS), choices=list(CAMERA_NAMES),
                   help="generator cameras to write (PandaSet names: CAM_BACK_LEFT / CAM_BACK_RIGHT are written as "
                        "left_camera / right_camera, PandaSet's 90-degree side cameras' slots)")
    p.add_argument("--world", default="classic", choices=list(WORLDS),
                   help="the generated world (default classic; issue 36: busy, overtake)")
    a = p.parse_args()
    write(Path(a.out), a.seed, a.frames, a.height, a.width, a.fine_texture, a.supersample, tuple(a.cameras),
          a.world)


if __name__ == "__main__":
    main()
