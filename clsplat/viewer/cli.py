"""``clsplat view PATH`` and ``clsplat render PATH --cameras FILE --out DIR``.

PATH is an INRIA-layout ``.ply``, a checkpoint written by ``clsplat train`` (any family) or a run
folder. A ``.ply`` is read here; checkpoints and run folders become a scene through a reader
that a package registers in the ``clsplat.scene_readers`` entry-point group (setup.cfg: this
distribution's models register ``clsplat.models.registry:scene_from_checkpoint``), so the
engine does not depend on the models.
A user's mistake is one line on stderr and exit status 2.
"""
from __future__ import annotations

import argparse
import sys
from importlib.metadata import entry_points
from pathlib import Path

from ..argparser import ArgumentParser
from .scene import ViewScene, scene_from_ply

__all__ = ["view_main", "render_main", "load_scene"]

#: the entry-point group of checkpoint readers: ``NAME = module:function``, where
#: ``function(path, data=, device=, sample=)`` returns a :class:`ViewScene` or raises ValueError
#: (and with ``--trust-pickle``, ``trust_pickle=True`` too: the reader may unpickle its data trusting it)
SCENE_READERS = "clsplat.scene_readers"

_NOT_A_SCENE = "expected an INRIA .ply, a checkpoint.pt written by clsplat train, or a run folder holding one"


def _is_ply(p: Path) -> bool:
    try:
        with open(p, "rb") as fh:
            head = fh.read(5)
        return head.startswith(b"ply\n") or head == b"ply\r\n"
    except OSError:
        return False


def load_scene(path: str, data: str | None = None, device=None, sample: int = 0,
               trust_pickle: bool = False) -> ViewScene:
    """The :class:`ViewScene` of PATH; ValueError naming PATH when it is not a scene.
    ``trust_pickle``: the explicit opt-out of allow-listed unpickling of ``data`` (PandaSet)."""
    p = Path(path)
    if not p.exists():
        raise ValueError(f"PATH {path!r}: no such file or folder")
    if p.is_file() and (p.suffix.lower() == ".ply" or _is_ply(p)):
        try:
            return scene_from_ply(p)
        except (ValueError, FileNotFoundError) as e:
            raise ValueError(f"PATH {path!r} is not a Gaussian scene: {e}") from None
    readers = sorted(entry_points(group=SCENE_READERS), key=lambda ep: ep.name)
    if p.is_dir() and not readers:
        if (p / "scene.ply").is_file():
            return load_scene(str(p / "scene.ply"))
        raise ValueError(f"PATH {path!r}: a folder without scene.ply; {_NOT_A_SCENE}")
    if not readers:
        raise ValueError(f"PATH {path!r}: reading a checkpoint needs a package that registers a "
                         f"{SCENE_READERS!r} entry point (this one's models: pip install 'clsplat[models]')")
    error: ValueError | None = None
    for ep in readers:  # the first reader that takes the checkpoint
        try:
            opt_out = {"trust_pickle": True} if trust_pickle else {}  # readers that never unpickle need not know it
            return ep.load()(p, data=data, device=device, sample=sample, **opt_out)
        except ValueError as e:
            error = e
    raise error


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", metavar="PATH", help="a .ply (INRIA layout), a checkpoint.pt or a run folder")
    p.add_argument("--device", default=None, help="OpenCL device of the exact render (default: CLSPLAT_DEVICE, "
                   "else GPU, else PoCL)")
    p.add_argument("--data", default=None, help="for a DrivingForward/PGT/AutoSplat checkpoint: the data to run it on "
                   "(synthetic | pandaset:PATH | nuscenes:PATH; default: the run's own where its metrics.json "
                   "records it, else synthetic)")
    p.add_argument("--sample", type=int, default=0, help="for DrivingForward/PGT: which held-out sample (default 0)")
    p.add_argument("--trust-pickle", action="store_true",
                   help="trust --data's pickled files (PandaSet): unpickle them without the allow-list, which can "
                        "run code they carry (default: allow-listed, safe)")


def _fail(prog: str, e: Exception) -> int:
    print(f"{prog}: {str(e).splitlines()[0] if str(e) else type(e).__name__}", file=sys.stderr)
    return 2


def view_main(argv: list[str]) -> int:
    """``clsplat view``: serve the scene until Ctrl-C."""
    p = ArgumentParser(prog="clsplat view", description="Look at a reconstruction in the browser (viser).")
    _common(p)
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default: 127.0.0.1, this machine only)")
    p.add_argument("--port", type=int, default=8080, help="port (default: 8080; 0 picks a free one)")
    p.add_argument("--render-width", type=int, default=480, help="width of the exact render in pixels (default 480)")
    p.add_argument("--up", default="+z", choices=("+z", "-z", "+y", "-y", "+x", "-x"),
                   help="the world's up axis (default +z, driving scenes; COLMAP scenes are usually -y)")
    a = p.parse_args(argv)
    try:
        import viser  # noqa: F401  (named as the view extra by clsplat.cli when missing)
        from .server import Viewer, check_port_free
        check_port_free(a.host, a.port)   # before a possibly slow model load
        from ..runtime import get_runtime
        get_runtime(a.device)             # an unknown --device now, not at the first exact render
        scene = load_scene(a.path, a.data, a.device, a.sample, a.trust_pickle)
        viewer = Viewer(scene, host=a.host, port=a.port, device=a.device, render_width=a.render_width, up=a.up)
    except ValueError as e:
        return _fail("clsplat view", e)
    try:  # the address inside: a Ctrl-C as soon as it shows still stops cleanly
        print(f"clsplat view: {scene.title}, {len(scene)} Gaussians; open {viewer.url} (Ctrl-C stops)", flush=True)
        viewer.wait()
    except KeyboardInterrupt:
        viewer.stop()
        print("clsplat view: stopped", flush=True)
    return 0


def render_main(argv: list[str]) -> int:
    """``clsplat render``: render every camera of a camera file into a folder."""
    p = ArgumentParser(prog="clsplat render", description="Render a scene from a list of cameras "
                                "(see clsplat/viewer/cameras.py or the README for the camera file format).")
    _common(p)
    p.add_argument("--cameras", required=True, help="camera JSON: clsplat's list, INRIA cameras.json or "
                   "nerfstudio transforms.json")
    p.add_argument("--out", required=True, help="output folder (created); one image per camera, render_times.json")
    p.add_argument("--format", default="png", choices=("png", "jpg", "exr"), help="image format (default png)")
    p.add_argument("--background", default="0,0,0", help="background colour r,g,b in [0, 1] (default 0,0,0)")
    a = p.parse_args(argv)
    try:
        try:
            bg = tuple(float(x) for x in a.background.split(","))
        except ValueError:
            bg = ()
        if len(bg) != 3 or not all(0 <= x <= 1 for x in bg):
            raise ValueError(f"--background: expected r,g,b with each in [0, 1], got {a.background!r}")
        from .cameras import read_cameras
        from .render import render_cameras
        cams = read_cameras(a.cameras)
        out = Path(a.out)
        if out.exists() and not out.is_dir():
            raise ValueError(f"--out {a.out!r}: exists and is not a folder")
        scene = load_scene(a.path, a.data, a.device, a.sample, a.trust_pickle)
        rows = render_cameras(scene, cams, out, ext=f".{a.format}", device=a.device, background=bg)
    except (ValueError, FileNotFoundError) as e:
        return _fail("clsplat render", e)
    times = sorted(r["render_s"] for r in rows)
    print(f"clsplat render: {len(rows)} views of {len(scene)} Gaussians in {a.out} "
          f"(median {times[len(times) // 2] * 1e3:.1f} ms per view; render_times.json)")
    return 0
