"""The engine's named constants, mirrored from ``kernels/common.h`` (the one place they are set).

The values are parsed from the header's ``#define CLS_*`` lines, so Python and OpenCL cannot
drift apart.
"""
from __future__ import annotations

import re
from importlib import resources

_HEADER = resources.files("clsplat.kernels").joinpath("common.h").read_text()
_NUMBER = re.compile(r"^[\d\s.eE+\-*/()]+$")


def _parse(name: str) -> float:
    m = re.search(rf"^#define\s+{name}\s+(.+)$", _HEADER, re.MULTILINE)
    if m is None or not _NUMBER.match(m.group(1).strip()):
        raise RuntimeError(f"kernels/common.h does not define {name} as a number")
    return float(eval(m.group(1), {"__builtins__": {}}))  # digits and arithmetic only (checked)


ALPHA_MIN: float = _parse("CLS_DEFAULT_ALPHA_MIN")
ALPHA_MAX: float = _parse("CLS_DEFAULT_ALPHA_MAX")
T_MIN: float = _parse("CLS_DEFAULT_T_MIN")
RADIUS_SIGMA: float = _parse("CLS_DEFAULT_RADIUS_SIGMA")
EPS2D: float = _parse("CLS_DEFAULT_EPS2D")
FRUSTUM_MARGIN: float = _parse("CLS_FRUSTUM_MARGIN")
PIXEL_CENTRE: float = _parse("CLS_PIXEL_CENTRE")
EXTENT_WORD: int = int(_parse("CLS_WORD"))  # samples per extent-bit word (tuned compositing)

RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
RADIUS_RULES = ("3.33sigma", "opacity", "4sigma")
MAX_IMAGE_SIDE = 16384
