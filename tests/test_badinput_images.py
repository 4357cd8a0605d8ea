"""Bad image and depth files and arguments: a clear error naming the file or the argument; a
failed write (full disk) leaves the previous file whole."""
import errno
import struct
import subprocess
import sys
import zlib
from collections import namedtuple

import numpy as np
import pytest

from clsplat.io.images import read_depth, read_image, write_depth, write_image

IMG = np.random.default_rng(0).random((48, 64, 3)).astype(np.float32)


@pytest.mark.parametrize("ext", [".jpg", ".png"])
def test_truncated_file_refused(tmp_path, ext):
    p = write_image(tmp_path / f"a{ext}", IMG)
    t = tmp_path / f"t{ext}"
    t.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    with pytest.raises(ValueError, match=rf"t\{ext}.*corrupt or truncated"):
        read_image(t)


def test_30000_square_png_refused_before_decoding(tmp_path):
    """A PNG whose header claims 30000x30000 (10 GB as float32) is refused from its header."""
    raw = bytearray(write_image(tmp_path / "a.png", IMG[:4, :4]).read_bytes())
    ihdr = bytearray(raw[16:29])  # width, height, bit depth, colour type, ...
    ihdr[0:8] = struct.pack(">II", 30000, 30000)
    raw[16:29] = ihdr
    raw[29:33] = struct.pack(">I", zlib.crc32(b"IHDR" + bytes(ihdr)))
    (tmp_path / "huge.png").write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=r"huge\.png"):  # OpenImageIO: implausible for the file size
        read_image(tmp_path / "huge.png")


def test_image_larger_than_available_memory_refused_before_decoding(tmp_path, monkeypatch):
    p = write_image(tmp_path / "a.png", IMG)
    monkeypatch.setattr("clsplat.memory.available_host_memory", lambda: 10000)
    with pytest.raises(ValueError, match=r"a\.png.*64x48x3.*host memory"):
        read_image(p)


def test_depth_with_nan_refused_on_read(tmp_path):
    d = np.ones((4, 5, 1), np.float32)
    d[1, 2] = np.nan
    p = write_image(tmp_path / "d.exr", d)  # a foreign writer: write_depth refuses NaN itself
    with pytest.raises(ValueError, match=r"d\.exr.*1 NaN or negative"):
        read_depth(p)
    with pytest.raises(ValueError, match="^depth must be >= 0"):
        write_depth(tmp_path / "e.exr", d[..., 0])


@pytest.mark.parametrize("path", [None, 3, b"a.png", ""])
def test_path_of_the_wrong_type(tmp_path, path):
    with pytest.raises(ValueError, match="^path: expected a file path"):
        read_image(path)
    with pytest.raises(ValueError, match="^path: expected a file path"):
        write_image(path, IMG)


def test_missing_and_non_image_files(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"nope\.png"):
        read_image(tmp_path / "nope.png")
    (tmp_path / "x.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match=r"x\.png"):
        read_image(tmp_path / "x.png")


_FILL = r"""
import resource, signal, sys
import numpy as np
from clsplat.io.images import write_image
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG
resource.setrlimit(resource.RLIMIT_FSIZE, (20000, resource.RLIM_INFINITY))
try:
    write_image(sys.argv[1], np.random.default_rng(1).random((200, 200, 3)).astype(np.float32))
except OSError as e:
    print("OSError", e)
"""


@pytest.mark.parametrize("ext", [".png", ".exr"])
def test_write_that_runs_out_of_space_keeps_the_previous_file(tmp_path, ext):
    """The file system refuses the write part way (a file-size limit, as a full disk would):
    OpenImageIO does not report it for PNG, so the file is read back before it is renamed."""
    p = write_image(tmp_path / f"o{ext}", IMG)
    before = p.read_bytes()
    r = subprocess.run([sys.executable, "-c", _FILL, str(p)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("OSError"), r.stdout
    assert f"o{ext}" in r.stdout and "unchanged" in r.stdout
    assert p.read_bytes() == before
    assert sorted(x.name for x in tmp_path.iterdir()) == [f"o{ext}"]


def test_full_disk_found_before_a_jpeg_is_written(tmp_path, monkeypatch):
    """libjpeg would end the process on a failed write: the free space is checked first."""
    p = write_image(tmp_path / "o.jpg", IMG)
    before = p.read_bytes()
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr("shutil.disk_usage", lambda _: usage(1 << 30, (1 << 30) - 4096, 4096))
    with pytest.raises(OSError, match=r"not enough disk space to write .*o\.jpg.*unchanged") as e:
        write_image(p, IMG)
    assert e.value.errno == errno.ENOSPC
    assert p.read_bytes() == before
