"""The ``clsplat`` console command.

    clsplat info                      OpenCL platforms, devices and the features clsplat uses
    clsplat fit --out DIR [...]       fit Gaussians to an image (the optimisation example)
    clsplat view PATH [...]           look at a .ply, checkpoint or run folder in the browser
    clsplat render PATH --cameras FILE --out DIR   render a list of cameras to images
    clsplat data synth --count N --out DIR        a cache of synthetic streets
    clsplat COMMAND [...]             a command another package registers (see below)

The engine owns ``info``, ``fit``, ``view``, ``render`` and ``data``. Every other command is
registered by the package that implements it, through the ``clsplat.commands`` entry-point group (setup.cfg): an entry point
``NAME = module:function`` makes ``clsplat NAME ARGS...`` call ``function(ARGS)`` (a list of
strings; it returns the exit status, and the first line of its docstring is its help). This
distribution registers ``demo``, ``train`` and ``eval`` (clsplat.models) and ``bench``
(clsplat.bench), so ``import clsplat`` never imports a model or a benchmark, and a model family
could live in a distribution of its own.
"""
from __future__ import annotations

import sys
from importlib.metadata import EntryPoint, entry_points

from .argparser import ArgumentParser

__all__ = ["main", "console", "COMMAND_GROUP", "registered_commands"]

#: the entry-point group through which packages add ``clsplat`` commands
COMMAND_GROUP = "clsplat.commands"

#: optional packages and the setup.cfg extra that installs each
_EXTRAS = {"OpenImageIO": "io", "matplotlib": "io", "pandas": "data", "kornia": "models", "tqdm": "models",
           "viser": "view"}

_BUILTIN = {"info": "list OpenCL devices and features",
            "fit": "fit Gaussians to an image (see clsplat fit --help)",
            "view": "look at a .ply, checkpoint or run folder in the browser (see clsplat view --help)",
            "render": "render a list of cameras to images (see clsplat render --help)",
            "data": "data tools: clsplat data synth --count N --out DIR (a cache of synthetic streets)"}


def registered_commands() -> dict[str, EntryPoint]:
    """Commands other packages register, by name (the first of a name wins; built-ins cannot be
    replaced)."""
    found: dict[str, EntryPoint] = {}
    for ep in entry_points(group=COMMAND_GROUP):
        if ep.name not in _BUILTIN:
            found.setdefault(ep.name, ep)
    return found


def _help_line(ep: EntryPoint) -> str:
    """The first docstring line of a registered command (loading it), or where it comes from."""
    try:
        doc = (ep.load().__doc__ or "").strip()
    except Exception as e:  # a broken plugin must not break `clsplat --help`
        return f"(from {ep.value}; cannot be loaded: {type(e).__name__}: {e})"
    return doc.splitlines()[0] if doc else f"(from {ep.value})"


def _info() -> int:
    from .runtime import describe_devices
    print(describe_devices())
    return 0


def _one_line(e: BaseException) -> str:
    """``e`` as one line; an ``OSError(errno, message)`` without a file name is its message
    (clsplat's write errors name the file themselves), without the "[Errno N]" prefix."""
    text = str(e)
    if isinstance(e, OSError) and e.filename is None and e.strerror:
        text = e.strerror
    return " ".join(text.split()) or type(e).__name__


def console(argv: list[str] | None = None) -> int:
    """The console entry point: :func:`main`, with a user's mistake (ValueError, a missing input
    file) as one line on stderr and exit status 2, and a failed write (a full disk, a file-size
    limit, no permission) as one line naming the file and the cause and exit status 1, never a
    traceback. (:func:`main` raises them, for callers that want the exception.)"""
    argv = sys.argv[1:] if argv is None else argv
    prog = f"clsplat {' '.join(argv[:2] if argv[:1] in (['train'], ['eval']) else argv[:1])}".strip()
    try:
        return main(argv)
    except (ValueError, FileNotFoundError) as e:
        print(f"{prog}: {_one_line(e)}", file=sys.stderr)
        return 2
    except OSError as e:  # after FileNotFoundError (a subclass)
        print(f"{prog}: {_one_line(e)}", file=sys.stderr)
        return 1


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:
        return _main(argv)
    except ModuleNotFoundError as e:
        top = (e.name or "").split(".")[0]
        if top not in _EXTRAS:
            raise
        raise SystemExit(f"clsplat {' '.join(argv[:1])}: needs the optional package {top!r}, "
                         f"installed by: pip install 'clsplat[{_EXTRAS[top]}]'") from None


def _main(argv: list[str]) -> int:
    plugins = registered_commands()
    if argv[:1] == ["fit"]:
        from .fit_image import _cli
        _cli(argv[1:])
        return 0
    if argv[:1] == ["data"]:
        from .data.synthetic_cache import main as data
        return data(argv[1:])
    if argv[:1] in (["view"], ["render"]):
        from .viewer.cli import render_main, view_main
        return (view_main if argv[0] == "view" else render_main)(argv[1:])
    if argv and argv[0] in plugins:
        return int(plugins[argv[0]].load()(argv[1:]) or 0)
    p = ArgumentParser(prog="clsplat", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    for name, text in _BUILTIN.items():
        sub.add_parser(name, help=text)
    for name, ep in sorted(plugins.items()):
        sub.add_parser(name, help=_help_line(ep))
    a = p.parse_args(argv)
    assert a.cmd == "info"  # fit and the registered commands returned above
    return _info()


if __name__ == "__main__":
    sys.exit(console())
