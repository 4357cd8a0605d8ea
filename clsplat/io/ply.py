"""Gaussian export / import in the INRIA 3D Gaussian Splatting ``.ply`` layout.

One ``vertex`` element, every property ``float``, in this order::

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  f_rest_0 .. f_rest_{3(K-1)-1}  opacity
    scale_0 scale_1 scale_2  rot_0 rot_1 rot_2 rot_3

* ``nx, ny, nz`` are written as zeros (ignored on read).
* ``f_dc_c = sh[:, 0, c]``; ``f_rest`` is **channel-major**: ``f_rest_{c*(K-1) + (k-1)} = sh[:, k, c]``
  for ``k = 1..K-1`` (K = (degree+1)^2 SH coefficients).
* ``opacity`` is stored as a logit, ``scale_*`` as natural logs, ``rot_*`` as a wxyz quaternion
  (stored as given; not normalised).

The writer emits ``binary_little_endian 1.0``; the reader accepts binary little or big endian,
extra properties (ignored) and any property order, but only ``float``/``float32`` properties
(as the layout prescribes).  In memory the API uses torch tensors with post-activation values:
means ``[N,3]``, quats ``[N,4]``, scales ``[N,3]`` (> 0), opacities ``[N]`` (in (0, 1)), sh ``[N,K,3]``.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from ..memory import check_host_memory
from .atomic import atomic_write

__all__ = ["write_ply", "read_ply", "GaussianPly", "SH_C0", "rgb_to_sh", "sh_to_rgb"]

#: zeroth-order real spherical-harmonic constant: colour = 0.5 + SH_C0 * f_dc.
SH_C0 = 0.28209479177387814
_OPACITY_EPS = 1e-7


class GaussianPly(NamedTuple):
    """Gaussians read from a .ply (float32 CPU tensors, post-activation)."""

    means: torch.Tensor  # [N, 3]
    quats: torch.Tensor  # [N, 4] wxyz
    scales: torch.Tensor  # [N, 3]
    opacities: torch.Tensor  # [N]
    sh: torch.Tensor  # [N, K, 3]


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """RGB ``[N, 3]`` in [0, 1] -> degree-0 SH ``[N, 1, 3]`` (inverse of :func:`sh_to_rgb`)."""
    rgb = torch.as_tensor(rgb)
    if rgb.ndim != 2 or rgb.shape[1] != 3:
        raise ValueError(f"rgb must have shape [N, 3], got {list(rgb.shape)}")
    return ((rgb - 0.5) / SH_C0)[:, None, :]


def sh_to_rgb(sh: torch.Tensor) -> torch.Tensor:
    """View-independent colour ``[N, 3]`` from SH ``[N, K, 3]`` (DC term only)."""
    sh = torch.as_tensor(sh)
    if sh.ndim != 3 or sh.shape[2] != 3:
        raise ValueError(f"sh must have shape [N, K, 3], got {list(sh.shape)}")
    return sh[:, 0, :] * SH_C0 + 0.5


def _np(t, name: str, shape: tuple) -> np.ndarray:
    if not isinstance(t, (torch.Tensor, np.ndarray)):
        raise ValueError(f"{name} must be a torch tensor, got {type(t).__name__}")
    a = t.detach().cpu().numpy() if isinstance(t, torch.Tensor) else t
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != len(shape) or any(s != -1 and s != d for s, d in zip(shape, a.shape)):
        want = "[" + ", ".join("*" if s == -1 else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {want}, got {list(a.shape)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains non-finite values")
    return a


def _property_names(k: int) -> list[str]:
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (k - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def write_ply(path: str | Path, means, quats, scales, opacities, sh) -> Path:
    """Write Gaussians to ``path`` in the INRIA 3DGS layout (binary little endian).

    Args:
        means: ``[N, 3]``; quats: ``[N, 4]`` wxyz; scales: ``[N, 3]`` > 0; opacities: ``[N]`` in
            (0, 1) (clamped to ``[1e-7, 1 - 1e-7]`` before the logit); sh: ``[N, K, 3]`` with K a
            perfect square (1, 4, 9, 16), or ``[N, 3]`` RGB in [0, 1] (converted with :func:`rgb_to_sh`).
    Returns:
        the path written.  The parent folder must exist.
    """
    p = Path(path)
    if p.suffix.lower() != ".ply":
        raise ValueError(f"path {str(p)!r} must end in .ply")
    if not p.parent.is_dir():
        raise FileNotFoundError(f"output folder does not exist: {str(p.parent)!r}")
    m = _np(means, "means", (-1, 3))
    n = m.shape[0]
    q = _np(quats, "quats", (n, 4))
    s = _np(scales, "scales", (n, 3))
    o = _np(opacities, "opacities", (n,))
    if isinstance(sh, (torch.Tensor, np.ndarray)) and np.ndim(sh) == 2:
        sh = rgb_to_sh(torch.as_tensor(np.asarray(sh.detach().cpu() if isinstance(sh, torch.Tensor) else sh)))
    f = _np(sh, "sh", (n, -1, 3))
    k = f.shape[1]
    if k < 1 or int(math.isqrt(k)) ** 2 != k:
        raise ValueError(f"sh must have K = (degree+1)^2 coefficients (1, 4, 9, 16, ...), got K={k}")
    if np.any(s <= 0):
        raise ValueError("scales must be > 0 (post-activation); they are stored as logs")
    if np.any((o < 0) | (o > 1)):
        raise ValueError("opacities must lie in [0, 1] (post-activation); they are stored as logits")
    oc = np.clip(o, _OPACITY_EPS, 1 - _OPACITY_EPS)
    cols = [m, np.zeros((n, 3)), f[:, 0, :], f[:, 1:, :].transpose(0, 2, 1).reshape(n, -1),
            np.log(oc / (1 - oc))[:, None], np.log(s), q]
    data = np.concatenate(cols, axis=1).astype("<f4")
    names = _property_names(k)
    assert data.shape[1] == len(names)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {nm}" for nm in names]
    header += ["end_header"]

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            fh.write(np.ascontiguousarray(data).tobytes())

    return atomic_write(p, write)


_FLOAT_TYPES = {"float", "float32"}
_TYPE_SIZES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
               "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


#: the header may be at most this long (real headers are a few hundred bytes)
_MAX_HEADER_BYTES = 1 << 20
#: exp(88.7) is float32's largest finite value
_MAX_LOG_SCALE = 88.0


def _read_header(p: Path) -> tuple[list[str], int]:
    """The header lines after ``ply`` up to (without) the ``end_header`` line, and the header's
    size in bytes. ``end_header`` counts only as a line of its own, not inside a comment."""
    lines: list[str] = []
    size = 0
    with open(p, "rb") as fh:
        first = fh.readline(64)
        size += len(first)
        if first.rstrip(b"\r\n") != b"ply":
            raise ValueError(f"{str(p)!r} is not a PLY file (missing 'ply' magic)")
        while True:
            ln = fh.readline(_MAX_HEADER_BYTES)
            size += len(ln)
            if not ln.endswith(b"\n"):
                raise ValueError(f"{str(p)!r}: PLY header has no 'end_header' line (truncated or corrupt)")
            if size > _MAX_HEADER_BYTES:
                raise ValueError(f"{str(p)!r}: PLY header longer than {_MAX_HEADER_BYTES} bytes")
            try:
                text = ln.decode("ascii").rstrip("\r\n")
            except UnicodeDecodeError:
                raise ValueError(f"{str(p)!r}: PLY header is not ASCII") from None
            if text.strip() == "end_header":
                return lines, size
            lines.append(text)


def read_ply(path: str | Path) -> GaussianPly:
    """Read Gaussians from an INRIA-layout ``.ply``; returns post-activation float32 tensors.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: not a PLY, ASCII format, missing/non-float properties, f_rest count not
            ``3 * (K - 1)`` with K a perfect square, or truncated data.
    """
    if not isinstance(path, (str, Path)):
        raise ValueError(f"path: expected a file path, got {type(path).__name__}")
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"ply file not found: {str(p)!r}")
    lines, header_bytes = _read_header(p)
    fmt = None
    elements: list[list] = []  # [name, count, [(type, name)]]
    for ln in lines:
        tok = ln.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1] if len(tok) > 1 else None
        elif tok[0] == "element":
            if len(tok) != 3 or not tok[2].isdigit() or len(tok[2]) > 15:
                raise ValueError(f"{str(p)!r}: bad PLY element line {ln!r}")
            elements.append([tok[1], int(tok[2]), []])
        elif tok[0] == "property":
            if not elements:
                raise ValueError(f"{str(p)!r}: PLY property before any element: {ln!r}")
            if tok[1] == "list":
                raise ValueError(f"{str(p)!r}: list property {ln!r} not supported in a Gaussian PLY")
            if len(tok) != 3 or tok[1] not in _TYPE_SIZES:
                raise ValueError(f"{str(p)!r}: bad PLY property line {ln!r}")
            elements[-1][2].append((tok[1], tok[2]))
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        raise ValueError(f"{str(p)!r}: PLY format {fmt!r} not supported; need binary_little_endian or binary_big_endian")
    if not elements or elements[0][0] != "vertex":
        raise ValueError(f"{str(p)!r}: first PLY element must be 'vertex', got {[e[0] for e in elements]}")
    _, n, props = elements[0]
    bad = [nm for t, nm in props if t not in _FLOAT_TYPES]
    if bad:
        raise ValueError(f"{str(p)!r}: vertex properties must be float32, these are not: {bad}")
    names = [nm for _, nm in props]
    if len(set(names)) != len(names):
        raise ValueError(f"{str(p)!r}: duplicate vertex property names")
    rest = sorted((nm for nm in names if nm.startswith("f_rest_")), key=lambda s: int(s[7:]) if s[7:].isdigit() else -1)
    nrest = len(rest)
    if rest and rest != [f"f_rest_{i}" for i in range(nrest)]:
        raise ValueError(f"{str(p)!r}: f_rest_* properties must be numbered 0..{nrest - 1}")
    if nrest % 3:
        raise ValueError(f"{str(p)!r}: number of f_rest_* properties ({nrest}) is not a multiple of 3")
    k = nrest // 3 + 1
    if int(math.isqrt(k)) ** 2 != k:
        raise ValueError(f"{str(p)!r}: {nrest} f_rest_* properties give K={k} SH coefficients, not a perfect square")
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [r for r in required if r not in names]
    if missing:
        raise ValueError(f"{str(p)!r}: missing vertex properties {missing}")
    stride = 4 * len(names)
    need = n * stride
    body = p.stat().st_size - header_bytes
    if body < need:
        raise ValueError(f"{str(p)!r}: truncated PLY, header declares {n} vertices ({need} bytes), file has {body} bytes")
    check_host_memory(3 * need, f"{str(p)!r}: {n} vertices of {len(names)} properties")
    dt = np.dtype("<f4" if fmt == "binary_little_endian" else ">f4")
    arr = np.fromfile(p, dtype=dt, count=n * len(names), offset=header_bytes).reshape(n, len(names)).astype(np.float32)
    col = {nm: i for i, nm in enumerate(names)}
    used = [col[nm] for nm in required + rest]  # other properties (normals, extras) are ignored
    finite = np.isfinite(arr[:, used])
    if not finite.all():
        rows, cols = np.nonzero(~finite)
        raise ValueError(f"{str(p)!r}: {rows.size} NaN or Inf value(s), first in vertex {rows[0]} "
                         f"property {names[used[cols[0]]]!r}")

    def get(*nms: str) -> np.ndarray:
        return arr[:, [col[x] for x in nms]]

    means = get("x", "y", "z")
    dc = get("f_dc_0", "f_dc_1", "f_dc_2")
    sh = np.empty((n, k, 3), dtype=np.float32)
    sh[:, 0, :] = dc
    if k > 1:
        sh[:, 1:, :] = get(*rest).reshape(n, 3, k - 1).transpose(0, 2, 1)
    logit = get("opacity")[:, 0].astype(np.float64)
    opac = (1.0 / (1.0 + np.exp(-logit))).astype(np.float32)
    log_s = get("scale_0", "scale_1", "scale_2")
    if log_s.size and float(log_s.max()) > _MAX_LOG_SCALE:
        raise ValueError(f"{str(p)!r}: scale_* (natural log) up to {float(log_s.max()):g}, whose exp overflows "
                         f"float32 (limit {_MAX_LOG_SCALE})")
    scales = np.exp(log_s.astype(np.float64)).astype(np.float32)
    quats = get("rot_0", "rot_1", "rot_2", "rot_3")
    t = torch.from_numpy
    return GaussianPly(t(np.ascontiguousarray(means)), t(np.ascontiguousarray(quats)), t(scales), t(opac),
                       t(np.ascontiguousarray(sh)))
