"""Render times of ``clsplat render`` (and so of the viewer's exact render, the same call) on a
scene: a camera file of views down the scene's street, rendered through the command.

    python bench/experiments/view_render.py /tmp/demo/scene.ply --out /tmp/view_render [--views 12]
        [--size 480x270] [--device DEV]

Writes ``OUT/cameras.json`` (clsplat's camera layout: the viewer's default camera of the scene,
then moved 0..20 m forward along its view), runs ``clsplat render PATH --cameras OUT/cameras.json
--out OUT/images`` twice (the first pass builds the OpenCL programs and fills caches; the second
is the one reported), and prints one JSON line: the median, min and max seconds per view of the
second pass, the Gaussians and the image size.
"""
from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python bench/experiments/view_render.py", description=__doc__.split("\n")[0])
    p.add_argument("path", help="a .ply, checkpoint or run folder")
    p.add_argument("--out", required=True)
    p.add_argument("--views", type=int, default=12)
    p.add_argument("--size", default="480x270", help="WxH of each view (default 480x270, the viewer's width)")
    p.add_argument("--device", default=None)
    a = p.parse_args(argv)
    import numpy as np

    from clsplat.cli import main as clsplat
    from clsplat.viewer.cameras import cameras_to_json
    from clsplat.viewer.cli import load_scene
    from clsplat.viewer.scene import ViewCamera, default_camera

    w, h = (int(x) for x in a.size.split("x"))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    c0 = default_camera(load_scene(a.path), w, h)
    cams = []
    for i, d in enumerate(np.linspace(0, 20, a.views)):
        V = c0.viewmat.copy()
        V[2, 3] -= d   # d metres forward along the view
        cams.append(ViewCamera(f"street_{i:02d}", c0.K, V, w, h))
    (out / "cameras.json").write_text(cameras_to_json(cams))
    args = ["render", a.path, "--cameras", str(out / "cameras.json"), "--out", str(out / "images")]
    if a.device:
        args += ["--device", a.device]
    for _ in range(2):
        if clsplat(args) != 0:
            return 1
    rec = json.loads((out / "images" / "render_times.json").read_text())
    t = [v["render_s"] for v in rec["views"]]
    print(json.dumps({"path": a.path, "gaussians": rec["gaussians"], "size": a.size, "views": len(t),
                      "median_s": round(statistics.median(t), 4), "min_s": round(min(t), 4),
                      "max_s": round(max(t), 4)}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
