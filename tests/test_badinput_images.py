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


@pytest.mark.slow   # spawns a child that fills a small filesystem
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


# --- decompression bombs: the declared size is checked before anything is decoded -----------
def _huffman(code, n):  # a fixed-Huffman code, most significant bit first
    return [(code >> (n - 1 - i)) & 1 for i in range(n)]


def _pack_bits(bits):
    out = bytearray((len(bits) + 7) // 8)
    for i, b in enumerate(bits):
        out[i >> 3] |= b << (i & 7)
    return bytes(out)


def _zeros_zlib(n):
    """A zlib stream of ``n`` (> 259) zero bytes built directly, in milliseconds: fixed-Huffman
    DEFLATE, one literal 0, then <length 258, distance 1> copies (13 bits per 258 bytes)."""
    lit0, copy, eob = _huffman(0x30, 8), _huffman(0b11000101, 8) + _huffman(0, 5), _huffman(0, 7)
    head = [1, 1, 0] + lit0 + copy  # BFINAL, BTYPE=01, 1 + 258 bytes: 24 bits, byte aligned
    k, rest = divmod(n - 259, 8 * 258)
    tail = copy * (rest // 258) + lit0 * (rest % 258) + eob
    body = _pack_bits(head) + _pack_bits(copy * 8) * k + _pack_bits(tail)
    return b"\x78\x01" + body + struct.pack(">I", ((n % 65521) << 16) | 1)  # adler32 of zeros


def _black_png(path, width, height):
    """A valid 8-bit grey PNG of ``width x height`` black pixels (any size: 5.7 MB for 30000^2)."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", _zeros_zlib(height * (1 + width)))
                     + chunk(b"IEND", b""))
    return path


def test_the_bomb_builder_makes_a_real_png(tmp_path):
    img = read_image(_black_png(tmp_path / "b.png", 300, 200))
    assert img.shape == (200, 300, 3) and not img.any()


def test_a_30000_by_30000_png_is_refused_before_decoding(tmp_path, monkeypatch):
    monkeypatch.delenv("CLSPLAT_MAX_IMAGE_PIXELS", raising=False)
    p = _black_png(tmp_path / "bomb.png", 30000, 30000)  # decodes to 10.8 GB as float32 RGB
    assert p.stat().st_size < 6 << 20
    with pytest.raises(ValueError, match=r"bomb\.png' declares 30000x30000 pixels \(900 Mpx\), over the "
                                         r"134217728-pixel limit"):
        read_image(p)


def test_the_pixel_limit_is_overridable_per_call_and_by_environment(tmp_path, monkeypatch):
    from clsplat.io.images import write_image

    monkeypatch.delenv("CLSPLAT_MAX_IMAGE_PIXELS", raising=False)
    p = write_image(tmp_path / "small.png", np.zeros((10, 20, 3), np.float32))
    with pytest.raises(ValueError, match=r"small\.png' declares 20x10 pixels.*over the 199-pixel limit"):
        read_image(p, max_pixels=199)
    assert read_image(p, max_pixels=200).shape == (10, 20, 3)
    monkeypatch.setenv("CLSPLAT_MAX_IMAGE_PIXELS", "100")
    with pytest.raises(ValueError, match="over the 100-pixel limit"):
        read_image(p)
    assert read_image(p, max_pixels=1000).shape == (10, 20, 3)  # the argument wins
    monkeypatch.setenv("CLSPLAT_MAX_IMAGE_PIXELS", "lots")
    with pytest.raises(ValueError, match="^CLSPLAT_MAX_IMAGE_PIXELS: expected a positive integer, got 'lots'"):
        read_image(p)
    with pytest.raises(ValueError, match="^max_pixels: expected a positive int"):
        read_image(p, max_pixels=0)
