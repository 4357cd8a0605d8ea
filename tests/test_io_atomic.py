"""clsplat/io/atomic.py: ``staged_group`` publishes a group of files all or nothing (an
evaluation's metrics and sheets); ``write_atomically`` names the file a failed write was for."""
from __future__ import annotations

import errno
import os

import pytest

from clsplat.io.atomic import staged_group, write_atomically, write_text_atomic


def _files(folder):
    return {p.name: p.read_bytes() for p in folder.iterdir()}


def test_a_finished_group_replaces_its_names_and_leaves_other_files(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "metrics.json").write_text("old")
    (out / "notes.txt").write_text("mine")
    with staged_group(out) as stage:
        assert stage.parent == out and stage.name.startswith(".staging-")
        write_text_atomic(stage / "metrics.json", "new")
        write_text_atomic(stage / "sheet.png", "png")
        assert (out / "metrics.json").read_text() == "old"  # nothing moves before the group is complete
    assert _files(out) == {"metrics.json": b"new", "sheet.png": b"png", "notes.txt": b"mine"}


def test_a_failed_group_leaves_the_folder_as_it_was(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "metrics.json").write_text("old")
    (out / "sheet.png").write_text("old png")

    def full_disk(p):
        p.write_bytes(b"x" * 10)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with pytest.raises(OSError, match=r"writing '.*/\.staging-[^/]+/sheet\.png' failed \(No space left on device\); "
                                      r"no partial file is left") as e:
        with staged_group(out) as stage:
            write_text_atomic(stage / "metrics.json", "new")  # the first of the group is written ...
            write_atomically([(stage / "sheet.png", full_disk)])  # ... the second fails
    assert e.value.errno == errno.ENOSPC
    assert _files(out) == {"metrics.json": b"old", "sheet.png": b"old png"}  # no mixed group, no staging left


def test_the_folder_is_created_and_a_file_in_its_place_is_named(tmp_path):
    with staged_group(tmp_path / "a" / "b") as stage:
        write_text_atomic(stage / "m.json", "{}")
    assert (tmp_path / "a" / "b" / "m.json").read_text() == "{}"
    (tmp_path / "f").write_text("")
    with pytest.raises(ValueError, match=r"^--out: '.*/f' exists and is not a folder$"):
        with staged_group(tmp_path / "f"):
            pass


def test_only_plain_files_are_published(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(ValueError, match=r"sub' is not a plain file"):
        with staged_group(out) as stage:
            write_text_atomic(stage / "m.json", "{}")
            (stage / "sub").mkdir()
    assert list(out.iterdir()) == []  # refused before anything moved
