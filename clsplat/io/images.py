"""Image and depth-map I/O through OpenImageIO.

* ``read_image`` / ``write_image``: PNG (8 or 16 bit), JPEG (8 bit) and OpenEXR (float32).
  In memory images are float32 ``[H, W, C]``; integer formats are scaled to ``[0, 1]``.
* ``read_depth`` / ``write_depth``: float32 ``[H, W]`` z-depth maps (metres, ``inf`` allowed)
  stored as single-channel float32 OpenEXR, which keeps them bit-exact.

Every failure raises ``FileNotFoundError`` (missing file or folder) or ``ValueError`` (bad
argument, unsupported extension, corrupt or truncated file), naming the path.

Decompression bombs: a few kilobytes of PNG can declare 30000 x 30000 pixels. Readers check the
size the header declares against ``max_pixels`` (default :data:`MAX_IMAGE_PIXELS`, or the
``CLSPLAT_MAX_IMAGE_PIXELS`` environment variable) before decoding anything, and refuse a larger
image with a ValueError naming the file and its size.
"""
from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from ..memory import check_host_memory
from .atomic import atomic_write

__all__ = ["read_image", "write_image", "read_depth", "write_depth", "SUPPORTED_EXTENSIONS", "MAX_IMAGE_PIXELS",
           "max_image_pixels"]

SUPPORTED_EXTENSIONS = (".png", ".jpg", ".jpeg", ".exr")
#: Default limit on width x height of an image file to be decoded: 2**27 (134 million) pixels,
#: e.g. 16384 x 8192, about 1.6 GB as float32 RGB. Driving datasets' cameras are 2-3 Mpx.
MAX_IMAGE_PIXELS = 1 << 27


def max_image_pixels() -> int:
    """The pixel limit in force: ``CLSPLAT_MAX_IMAGE_PIXELS`` if set, else :data:`MAX_IMAGE_PIXELS`."""
    text = os.environ.get("CLSPLAT_MAX_IMAGE_PIXELS", "").strip()
    if not text:
        return MAX_IMAGE_PIXELS
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v < 1:
        raise ValueError(f"CLSPLAT_MAX_IMAGE_PIXELS: expected a positive integer, got {text!r}")
    return v


def _ext(path: Path, arg: str = "path") -> str:
    ext = path.suffix.lower()
    if ext not in SUPPORTED_EXTENSIONS:
        raise ValueError(f"{arg} {str(path)!r}: unsupported extension {ext!r}; use one of {SUPPORTED_EXTENSIONS}")
    return ext


def _path(path: object, arg: str = "path") -> Path:
    if not isinstance(path, (str, Path)) or not str(path):
        raise ValueError(f"{arg}: expected a file path, got {path!r}")
    return Path(path)


def _check_max_pixels(max_pixels: int | None) -> int | None:
    if max_pixels is None:
        return max_image_pixels()
    if isinstance(max_pixels, bool) or not isinstance(max_pixels, int) or max_pixels < 1:
        raise ValueError(f"max_pixels: expected a positive int or None (the default limit), got {max_pixels!r}")
    return max_pixels


def _read(path: str | Path, max_pixels: int | None) -> np.ndarray:
    """Decode ``path`` as float32 [H, W, C], refusing more than ``max_pixels`` (0: no limit)."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"image file not found: {str(p)!r}")
    inp = oiio.ImageInput.open(str(p))
    if inp is None:
        raise ValueError(f"cannot read image {str(p)!r}: {oiio.geterror() or 'unknown format or corrupt file'}")
    try:
        spec = inp.spec()
        if max_pixels and spec.width * spec.height > max_pixels:
            raise ValueError(f"image {str(p)!r} declares {spec.width}x{spec.height} pixels "
                             f"({spec.width * spec.height / 1e6:.0f} Mpx), over the {max_pixels}-pixel limit "
                             "(a decompression bomb?); raise it with max_pixels= or CLSPLAT_MAX_IMAGE_PIXELS")
        # decoded as float32, then up to two more copies (channel selection, clipping)
        check_host_memory(3 * 4 * spec.width * spec.height * spec.nchannels,
                          f"image {str(p)!r} ({spec.width}x{spec.height}x{spec.nchannels})")
        px = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        # A truncated JPEG decodes (padded with grey) and only sets the error flag.
        if px is None or inp.has_error:
            raise ValueError(f"cannot read image {str(p)!r} (corrupt or truncated): {inp.geterror().strip()}")
    finally:
        inp.close()
    px = np.asarray(px, dtype=np.float32)
    if px.ndim == 2:
        px = px[..., None]
    return px


def read_image(path: str | Path, channels: int | None = 3, max_pixels: int | None = None) -> np.ndarray:
    """Read an image as float32 ``[H, W, C]``.

    Args:
        path: PNG/JPEG/EXR file.
        channels: keep the first ``channels`` channels (grey is replicated to 3); None keeps all.
        max_pixels: refuse a file that declares more than this many pixels (width x height),
            before decoding; default :func:`max_image_pixels`.
    Returns:
        float32 ``[H, W, C]``; PNG/JPEG values in ``[0, 1]``, EXR values as stored.
    """
    if channels is not None and channels not in (1, 3, 4):
        raise ValueError(f"channels must be 1, 3, 4 or None, got {channels!r}")
    limit = _check_max_pixels(max_pixels)
    p = _path(path)
    _ext(p)
    px = _read(p, limit)
    if channels is None or px.shape[2] == channels:
        return px
    if px.shape[2] == 1:
        return np.repeat(px, channels, axis=2)
    if px.shape[2] < channels:
        raise ValueError(f"image {str(p)!r} has {px.shape[2]} channels, {channels} requested")
    return np.ascontiguousarray(px[..., :channels])


def write_image(path: str | Path, image, quality: int = 95, bits: int = 8) -> Path:
    """Write float ``[H, W, C]`` (C in 1, 3, 4) or ``[H, W]`` image.

    Args:
        path: destination; the extension picks the format (``.png``, ``.jpg``/``.jpeg``, ``.exr``).
            The parent folder must exist.
        image: array-like; values outside ``[0, 1]`` are clipped for PNG/JPEG, kept for EXR.
        quality: JPEG quality 1..100.
        bits: PNG bit depth, 8 or 16.
    Returns:
        the path written.
    """
    p = _path(path)
    ext = _ext(p)
    if not p.parent.is_dir():
        raise FileNotFoundError(f"output folder does not exist: {str(p.parent)!r}")
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4) or img.shape[0] == 0 or img.shape[1] == 0:
        raise ValueError(f"image must have shape [H, W], [H, W, 1], [H, W, 3] or [H, W, 4], got {list(np.shape(image))}")
    if not (isinstance(quality, int) and 1 <= quality <= 100):
        raise ValueError(f"quality must be an int in 1..100, got {quality!r}")
    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits!r}")
    h, w, c = img.shape
    if ext == ".exr":
        spec = oiio.ImageSpec(w, h, c, oiio.FLOAT)
        spec.attribute("compression", "zip")
        data = np.ascontiguousarray(img)
    else:
        if np.isnan(img).any():
            raise ValueError(f"image for {str(p)!r} contains NaN")
        if ext in (".jpg", ".jpeg") and c == 4:
            raise ValueError(f"JPEG cannot store 4 channels ({str(p)!r}); drop alpha or use PNG")
        b = 16 if (ext == ".png" and bits == 16) else 8
        scale = 65535.0 if b == 16 else 255.0
        dtype = np.uint16 if b == 16 else np.uint8
        data = np.ascontiguousarray(np.round(np.clip(img, 0.0, 1.0) * scale).astype(dtype))
        spec = oiio.ImageSpec(w, h, c, oiio.UINT16 if b == 16 else oiio.UINT8)
        if ext in (".jpg", ".jpeg"):
            spec.attribute("Compression", f"jpeg:{quality}")
            spec.attribute("jpeg:subsampling", "4:4:4")  # no chroma subsampling
    _check_free_space(p, data.nbytes)
    return atomic_write(p, lambda tmp: _write_oiio(tmp, spec, data))


def _check_free_space(p: Path, raw_bytes: int) -> None:
    """OSError(ENOSPC) naming ``p`` unless its file system has room for the uncompressed pixels
    (an upper bound on the encoded file, plus a margin). libjpeg, as OpenImageIO builds it, ends
    the whole process on a failed write instead of reporting it, so a full disk is found first."""
    need = raw_bytes + raw_bytes // 10 + (64 << 10)
    try:
        free = shutil.disk_usage(p.parent).free
    except OSError:
        return
    if free < need:
        raise OSError(errno.ENOSPC, f"not enough disk space to write {str(p)!r}: needs up to {need >> 10} KiB, "
                                    f"{free >> 10} KiB free; the previous {p.name} is unchanged")


def _write_oiio(p: Path, spec, data: np.ndarray) -> None:
    out = oiio.ImageOutput.create(str(p))
    if out is None:
        raise ValueError(f"cannot create writer for {str(p)!r}: {oiio.geterror()}")
    try:
        if not out.open(str(p), spec):
            raise ValueError(f"cannot open {str(p)!r} for writing: {out.geterror()}")
        if not out.write_image(data):
            raise OSError(errno.EIO, f"cannot write {str(p)!r}: {out.geterror()}")
    finally:
        if not out.close():
            raise OSError(errno.EIO, f"cannot finish {str(p)!r}: {out.geterror()}")
    # OpenImageIO's PNG and JPEG writers do not report a failed fwrite (a full disk, a file
    # size limit): read the file back, so that a truncated file is never renamed into place.
    try:
        back = _read(p, 0)  # our own file: no limit
    except ValueError as e:
        raise OSError(errno.EIO, f"the written file is incomplete (disk full?): {e}") from None
    if back.shape != (spec.height, spec.width, spec.nchannels):
        raise OSError(errno.EIO, f"the written file reads back as {list(back.shape)}, not "
                                 f"{[spec.height, spec.width, spec.nchannels]} (disk full?)")


def read_depth(path: str | Path, max_pixels: int | None = None) -> np.ndarray:
    """Read a float32 ``[H, W]`` depth map from a single-channel EXR written by :func:`write_depth`
    (``max_pixels`` as in :func:`read_image`)."""
    limit = _check_max_pixels(max_pixels)
    p = _path(path)
    if p.suffix.lower() != ".exr":
        raise ValueError(f"depth path {str(p)!r} must end in .exr")
    px = _read(p, limit)
    if px.shape[2] != 1:
        raise ValueError(f"depth file {str(p)!r} must have 1 channel, has {px.shape[2]}")
    d = px[..., 0]
    bad = np.isnan(d) | (d < 0)
    if bad.any():
        raise ValueError(f"depth file {str(p)!r}: {int(bad.sum())} NaN or negative depth(s); depth must be >= 0 "
                         "or inf")
    return d


def write_depth(path: str | Path, depth) -> Path:
    """Write a float32 ``[H, W]`` z-depth map (metres; ``inf`` allowed, NaN and negatives are not) as EXR."""
    p = _path(path)
    if p.suffix.lower() != ".exr":
        raise ValueError(f"depth path {str(p)!r} must end in .exr (float depth needs EXR)")
    d = np.asarray(depth, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f"depth must have shape [H, W], got {list(d.shape)}")
    if np.isnan(d).any() or (d < 0).any():
        raise ValueError("depth must be >= 0 or inf, got NaN or negative values")
    return write_image(p, d[..., None])
