"""Image / depth I/O through OpenImageIO, and the contact sheet."""
import numpy as np
import pytest

from clsplat.io.contact_sheet import make_contact_sheet
from clsplat.io.images import read_depth, read_image, write_depth, write_image

rng = np.random.default_rng(0)
IMG = rng.uniform(0, 1, (20, 30, 3)).astype(np.float32)


def test_png_jpeg_exr_roundtrip(tmp_path):
    write_image(tmp_path / "a.png", IMG)
    assert np.abs(read_image(tmp_path / "a.png") - IMG).max() <= 0.5 / 255 + 1e-6
    write_image(tmp_path / "b.png", IMG, bits=16)
    assert np.abs(read_image(tmp_path / "b.png") - IMG).max() <= 0.5 / 65535 + 1e-6
    smooth = np.repeat(np.linspace(0, 1, 30, dtype=np.float32)[None, :, None], 20, 0).repeat(3, 2)
    write_image(tmp_path / "c.jpg", smooth, quality=95)
    assert np.abs(read_image(tmp_path / "c.jpg") - smooth).mean() < 0.01
    hdr = IMG * 7 - 2
    write_image(tmp_path / "d.exr", hdr)
    assert np.array_equal(read_image(tmp_path / "d.exr"), hdr)
    write_image(tmp_path / "g.png", IMG[..., 0])
    assert read_image(tmp_path / "g.png").shape == (20, 30, 3)
    assert read_image(tmp_path / "g.png", channels=None).shape == (20, 30, 1)


def test_depth_exr_exact_with_inf(tmp_path):
    d = rng.uniform(0.5, 80, (20, 30)).astype(np.float32)
    d[:3] = np.inf
    write_depth(tmp_path / "d.exr", d)
    back = read_depth(tmp_path / "d.exr")
    assert back.dtype == np.float32 and np.array_equal(back, d)
    with pytest.raises(ValueError, match="must end in .exr"):
        write_depth(tmp_path / "d.png", d)
    with pytest.raises(ValueError, match="NaN or negative"):
        write_depth(tmp_path / "e.exr", -d)


def test_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="image file not found"):
        read_image(tmp_path / "missing.png")
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really a png")
    with pytest.raises(ValueError, match="cannot read image .*bad.png"):
        read_image(tmp_path / "bad.png")
    write_image(tmp_path / "ok.png", IMG)
    raw = (tmp_path / "ok.png").read_bytes()
    (tmp_path / "trunc.png").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ValueError, match="trunc.png"):
        read_image(tmp_path / "trunc.png")
    with pytest.raises(ValueError, match="unsupported extension '.bmp'"):
        write_image(tmp_path / "x.bmp", IMG)
    with pytest.raises(FileNotFoundError, match="output folder does not exist"):
        write_image(tmp_path / "no" / "x.png", IMG)
    with pytest.raises(ValueError, match=r"image must have shape"):
        write_image(tmp_path / "x.png", np.zeros((4, 4, 2)))
    with pytest.raises(ValueError, match="JPEG cannot store 4 channels"):
        write_image(tmp_path / "x.jpg", np.zeros((4, 4, 4)))
    with pytest.raises(ValueError, match="quality must be"):
        write_image(tmp_path / "x.jpg", IMG, quality=0)


def test_contact_sheet(tmp_path):
    r = rng.uniform(0, 1, (6, 24, 40, 3)).astype(np.float32)
    g = np.clip(r + 0.1, 0, 1)
    p = make_contact_sheet(r, g, tmp_path / "sheet.png", names=[f"c{i}" for i in range(6)], title="t")
    img = read_image(p)
    strip, gap = 18, 4
    assert img.shape == (2 * strip + 6 * (strip + 24) + 5 * gap, 3 * 40 + 2 * gap, 3)
    # first row's ground-truth panel is stored verbatim (8-bit)
    y0 = 2 * strip + strip
    assert np.abs(img[y0:y0 + 24, 44:84] - g[0]).max() < 1.0 / 255 + 1e-6
    with pytest.raises(ValueError, match="same shape"):
        make_contact_sheet(r, g[:5], tmp_path / "s.png")
    with pytest.raises(ValueError, match="names has 2 entries for 6 cameras"):
        make_contact_sheet(r, g, tmp_path / "s.png", names=["a", "b"])
