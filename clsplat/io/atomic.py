"""Writing output files so that a failed write never leaves a corrupt or half-replaced file.

Every writer in :mod:`clsplat.io` (images, depth maps, ``.ply``, contact sheets) and the
``clsplat fit`` outputs go through :func:`write_atomically`: each file is written to a
temporary name in its own folder (same extension, so format detection still works), and only
when every file of the group is complete are they renamed into place (``os.replace``, atomic
on POSIX within one file system). If a write fails -- a full disk, a file-size limit, an
interrupt -- the temporary files are removed, the earlier files keep their content, and an
``OSError`` names the file that failed.

:func:`staged_group` does the same for a group of files that different code writes (an
evaluation's metrics and sheets): they are written into a hidden folder beside their final
place and moved in together only when all of them are written.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterable, Iterator

__all__ = ["write_atomically", "atomic_write", "write_text_atomic", "temp_path", "staged_group"]


def temp_path(path: Path) -> Path:
    """The temporary name ``path`` is written to first: hidden, same folder, same extension."""
    return path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")


def write_atomically(items: Iterable[tuple[str | Path, Callable[[Path], object]]]) -> list[Path]:
    """Call each ``write_fn(tmp)`` on a temporary path, then rename all of them into place.

    Args:
        items: ``(path, write_fn)`` pairs; ``write_fn`` writes the whole file to the path it gets.
    Returns:
        the final paths. On failure nothing is renamed, and the error names the failing file.
    """
    pairs = [(Path(p), fn) for p, fn in items]
    for p, _ in pairs:
        if not p.parent.is_dir():
            raise FileNotFoundError(f"output folder does not exist: {str(p.parent)!r}")
    done: list[tuple[Path, Path]] = []
    try:
        for p, fn in pairs:
            tmp = temp_path(p)
            done.append((tmp, p))
            try:
                fn(tmp)
            except (OSError, ValueError) as e:  # ValueError: a library's "cannot write" report
                kept = " and the group's other files are" if len(pairs) > 1 else " is"
                prev = f"the previous {p.name}{kept} unchanged" if p.exists() else "no partial file is left"
                msg = f"writing {str(p)!r} failed ({getattr(e, 'strerror', None) or e}); {prev}"
                raise (OSError(e.errno, msg) if isinstance(e, OSError) else ValueError(msg)) from e
            if not tmp.is_file():
                raise OSError(f"writing {str(p)!r} failed: the writer produced no file")
        for tmp, p in done:
            os.replace(tmp, p)
    except BaseException:
        for tmp, _ in done:
            tmp.unlink(missing_ok=True)
        raise
    return [p for p, _ in pairs]


def atomic_write(path: str | Path, write_fn: Callable[[Path], object]) -> Path:
    """:func:`write_atomically` for one file."""
    return write_atomically([(path, write_fn)])[0]


def write_text_atomic(path: str | Path, text: str) -> Path:
    """``Path.write_text`` through :func:`atomic_write` (JSON tables, metrics)."""
    return atomic_write(path, lambda tmp: tmp.write_text(text))


@contextmanager
def staged_group(folder: str | Path, arg: str = "--out") -> Iterator[Path]:
    """Write a group of files into ``folder`` all or nothing.

    Yields a hidden staging folder inside ``folder`` (created, with ``folder`` if missing); the
    body writes the group's files there. When the body finishes, each file is renamed into
    ``folder`` (replacing a file of the same name, leaving other files alone); when it raises,
    the staging folder is removed and ``folder`` keeps its earlier files unchanged. Only plain
    files are moved (names starting with a dot, writers' temporaries, are not; a sub-folder is
    refused before anything moves). The renames take microseconds each; a process killed among
    them leaves the group partly moved, and one killed before them leaves a ``.staging-*``
    folder behind, which nothing reads.

    Args:
        folder: the output folder; arg: its argument name for error messages.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{arg}: {str(folder)!r} exists and is not a folder")
    folder.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=".staging-", dir=folder))
    try:
        yield stage
        files = sorted(p for p in stage.iterdir() if not p.name.startswith("."))  # not a writer's temporary
        for p in files:
            if not p.is_file() or p.is_symlink():
                raise ValueError(f"staged_group: {str(p)!r} is not a plain file; only files are published")
        for p in files:
            os.replace(p, folder / p.name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
