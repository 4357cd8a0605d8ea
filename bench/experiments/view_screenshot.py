"""Screenshot of ``clsplat view`` in headless Chromium (the README's viewer figure).

    .venv/bin/python bench/experiments/view_screenshot.py /tmp/demo/scene.ply bench/figures/viewer_demo.png

Serves PATH (a .ply, checkpoint or run folder) like ``clsplat view``, opens it in headless
Chromium (WebGL through SwiftShader), optionally moves the browser's camera to one of the viewer's
named views (a recorded camera, "lane change 2 m (...)", ...), waits for clsplat's exact render of
that camera, and saves a screenshot of the page.
"""
from __future__ import annotations

import argparse
import time

from clsplat.io.images import write_image
from clsplat.viewer.browser import HeadlessChromium
from clsplat.viewer.cli import load_scene
from clsplat.viewer.server import Viewer


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("path")
    p.add_argument("out", help="PNG to write")
    p.add_argument("--view", default=None, help="a named view of the viewer (default: its initial camera)")
    p.add_argument("--size", default="1280x720")
    p.add_argument("--render-width", type=int, default=480)
    a = p.parse_args(argv)
    w, h = (int(x) for x in a.size.split("x"))
    scene = load_scene(a.path)
    viewer = Viewer(scene, port=0, render_width=a.render_width)
    try:
        views = viewer.views()
        if a.view is not None and a.view not in views:
            raise SystemExit(f"--view: {a.view!r} is not one of {sorted(views)}")
        with HeadlessChromium(viewer.url, w, h) as b:
            t0 = time.time()
            while not viewer.clients() and time.time() - t0 < 120:
                time.sleep(0.2)
            cid = next(iter(viewer.clients()))
            while cid not in viewer.last and time.time() - t0 < 300:
                time.sleep(0.2)
            if a.view is not None:
                n = viewer.renders
                viewer.set_client_camera(viewer.clients()[cid], views[a.view])
                while viewer.renders <= n and time.time() - t0 < 300:
                    time.sleep(0.2)
            time.sleep(4)   # software WebGL: let the splats settle
            img = b.screenshot()
            r = viewer.last[cid]
        write_image(a.out, img / 255.0)
        print(f"wrote {a.out} ({img.shape[1]}x{img.shape[0]}); exact render {r['seconds'] * 1e3:.0f} ms "
              f"of {len(scene)} Gaussians at {r['image'].shape[1]}x{r['image'].shape[0]}")
    finally:
        viewer.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
