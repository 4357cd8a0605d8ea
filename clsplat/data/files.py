"""Checked reading of dataset files: JSON, paths confined to a data root, pickled DataFrames.

The dataset loaders (:mod:`.nuscenes`, :mod:`.pandaset`) read files written by others, so every
read here turns a malformed or hostile file into a ``ValueError`` (or ``FileNotFoundError``)
that names the file, before it can crash, hang, exhaust memory or run code:

* :func:`read_json`: invalid JSON, deeply nested JSON (``RecursionError``), integers too long
  to convert and files over a size limit are refused.
* :func:`path_inside`: a relative path taken from a table (nuScenes ``filename``) must stay
  inside the data root; absolute paths and ``..`` that climb out are refused.
* :func:`read_pickled_dataframe`: PandaSet stores DataFrames as gzip pickles, and unpickling
  runs whatever the file says. By default (``safe=True``) only the numpy and pandas
  constructors a DataFrame of numbers and strings needs are allowed; anything else is refused
  unrun. ``safe=False`` is the explicit opt-out for trusted files. The safe path uses the C
  unpickler (``pickle.Unpickler`` with an allow-listing ``find_class``), falling back to
  pandas' pure-Python compatibility unpickler (same allow-list) only for old pandas formats the
  C unpickler cannot read, as ``pd.read_pickle`` does; either way the unpickler reads straight
  from the gzip stream, bounded by :data:`MAX_PICKLE_BYTES` (a gzip bomb stops there).
"""
from __future__ import annotations

import gzip
import json
import os
import pickle
from pathlib import Path

__all__ = ["read_json", "path_inside", "read_pickled_dataframe", "MAX_JSON_BYTES", "MAX_PICKLE_BYTES",
           "SAFE_PICKLE_GLOBALS"]

#: JSON table files larger than this are refused (nuScenes v1.0-trainval's largest table,
#: sample_data.json, is about 450 MB).
MAX_JSON_BYTES = 4 << 30
#: decompressed pickles larger than this are refused (a PandaSet LiDAR sweep of ~170k points
#: with six float64 columns is about 8 MB; 1 GiB leaves a margin of two orders of magnitude).
#: Override per call with ``read_pickled_dataframe(..., max_bytes=)``.
MAX_PICKLE_BYTES = 1 << 30


def read_json(path: Path, what: str = "JSON file"):
    """Parse ``path`` as JSON; FileNotFoundError or ValueError naming ``path`` on any failure."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {str(path)!r}")
    size = path.stat().st_size
    if size > MAX_JSON_BYTES:
        raise ValueError(f"{what} {str(path)!r} has {size} bytes, over the {MAX_JSON_BYTES}-byte limit")
    try:
        return json.loads(path.read_bytes())
    except RecursionError:
        raise ValueError(f"{what} {str(path)!r} is nested too deeply to parse") from None
    except (ValueError, UnicodeDecodeError) as exc:  # JSONDecodeError, giant integers
        raise ValueError(f"{what} {str(path)!r} is not valid JSON: {exc}") from None


def path_inside(root: Path, rel: object, what: str) -> Path:
    """``root / rel`` for a relative ``rel`` that stays inside ``root`` (symlinks resolved).

    ValueError naming ``what`` and the path for a non-string, absolute or escaping path.
    """
    if not isinstance(rel, str) or not rel or "\x00" in rel:
        raise ValueError(f"{what}: expected a relative file name, got {rel!r}")
    if os.path.isabs(rel) or Path(rel).is_absolute() or rel.startswith(("/", "\\")):
        raise ValueError(f"{what}: {rel!r} is an absolute path; paths must be relative to the data root")
    base = Path(root).resolve()
    p = (base / rel).resolve()
    if p != base and base not in p.parents:
        raise ValueError(f"{what}: {rel!r} points outside the data root {str(base)!r}")
    return p


#: (module, name) pairs the safe unpickler allows: what pandas (0.25 to 3.x) and numpy write
#: for a DataFrame of numeric, string and object-string columns.
SAFE_PICKLE_GLOBALS = frozenset({
    ("numpy", "ndarray"), ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer"),
    ("builtins", "slice"), ("builtins", "range"), ("builtins", "object"),
    ("copyreg", "_reconstructor"),
    ("pandas", "DataFrame"), ("pandas", "Series"), ("pandas", "Index"), ("pandas", "RangeIndex"),
    ("pandas", "StringDtype"), ("pandas", "Categorical"), ("pandas", "CategoricalDtype"),
    ("pandas.core.arrays.categorical", "Categorical"), ("pandas.core.dtypes.dtypes", "CategoricalDtype"),
    ("pandas.core.frame", "DataFrame"), ("pandas.core.series", "Series"),
    ("pandas.core.internals.managers", "BlockManager"),
    ("pandas.core.internals.managers", "SingleBlockManager"),
    ("pandas.core.internals.blocks", "new_block"), ("pandas.core.internals.blocks", "Block"),
    ("pandas.core.internals.blocks", "NumpyBlock"), ("pandas.core.internals.blocks", "ObjectBlock"),
    ("pandas.core.internals.blocks", "FloatBlock"), ("pandas.core.internals.blocks", "IntBlock"),
    ("pandas.core.internals.blocks", "NumericBlock"), ("pandas.core.internals.blocks", "BoolBlock"),
    ("pandas.core.internals.blocks", "ExtensionBlock"),
    ("pandas._libs.internals", "_unpickle_block"), ("pandas._libs.internals", "BlockPlacement"),
    ("pandas.core.indexes.base", "_new_Index"), ("pandas.core.indexes.base", "Index"),
    ("pandas.core.indexes.range", "RangeIndex"), ("pandas.core.indexes.numeric", "Int64Index"),
    ("pandas.core.indexes.numeric", "Float64Index"),
    ("pandas.core.arrays.string_", "StringArray"), ("pandas.core.arrays.string_", "StringDtype"),
    ("pandas.arrays", "StringArray"), ("pandas.core.arrays.numpy_", "NumpyExtensionArray"),
    ("pandas._libs.arrays", "__pyx_unpickle_NDArrayBacked"),
})


class _PickleRefused(Exception):
    """A global outside :data:`SAFE_PICKLE_GLOBALS` (turned into a ValueError naming the file)."""


def _allowed(module: str, name: str) -> tuple[str, str]:
    """The (module, name) to import for an allowed global; raises :class:`_PickleRefused` otherwise.

    Old pandas names are mapped to their current location (pandas' own rename table) after the
    check, so a renamed constructor is allowed only when its old or new name is on the list.
    """
    from pandas.compat.pickle_compat import _class_locations_map

    key = _class_locations_map.get((module, name), (module, name))
    if (module, name) not in SAFE_PICKLE_GLOBALS and key not in SAFE_PICKLE_GLOBALS:
        raise _PickleRefused(f"{module}.{name}")
    return key


class _SafeUnpickler(pickle.Unpickler):
    """The C unpickler, resolving globals only through the allow-list."""

    def find_class(self, module: str, name: str):
        return super().find_class(*_allowed(module, name))


def _safe_compat_unpickler():
    """pandas' pure-Python compatibility unpickler (old pandas layouts), same allow-list."""
    from pandas.compat.pickle_compat import Unpickler

    class SafeCompatUnpickler(Unpickler):
        def find_class(self, module: str, name: str):
            _allowed(module, name)
            return super().find_class(module, name)

    return SafeCompatUnpickler


class _TooBig(ValueError):
    """The decompressed stream passed its limit."""


class _BoundedReader:
    """A read-only file object over a decompressing stream that raises :class:`_TooBig` once more
    than ``limit`` bytes have been read: the unpickler reads straight from the stream (no copy of
    the whole content, as fast as pandas' own reader) and a gzip bomb stops at the limit."""

    def __init__(self, fh, limit: int, path: Path) -> None:
        self.fh, self.limit, self.path, self.count = fh, limit, path, 0

    def _count(self, n: int) -> None:
        self.count += n
        if self.count > self.limit:
            raise _TooBig(f"{str(self.path)!r}: decompresses to more than {self.limit} bytes (the limit; pass "
                          "max_bytes= to read_pickled_dataframe to raise it)")

    def _room(self, n: int | None) -> int:
        room = self.limit + 1 - self.count
        return room if n is None or n < 0 else min(n, room)

    def read(self, n: int | None = -1) -> bytes:
        data = self.fh.read(self._room(n))
        self._count(len(data))
        return data

    def readinto(self, buf) -> int:
        view = memoryview(buf).cast("B")
        n = self.fh.readinto(view[: self._room(len(view))])
        self._count(n)
        return n

    def readline(self, n: int | None = -1) -> bytes:
        data = self.fh.readline(self._room(n))
        self._count(len(data))
        return data


def _unpickle_gzip(path: Path, max_bytes: int, unpickler) -> object:
    with gzip.open(path, "rb") as fh:
        return unpickler(_BoundedReader(fh, max_bytes, path)).load()


def read_pickled_dataframe(path: Path, safe: bool = True, max_bytes: int = MAX_PICKLE_BYTES):
    """Read a gzip-pickled pandas DataFrame (PandaSet's format).

    Unpickling a file runs code the file names. ``safe=True`` (the default) allows only
    :data:`SAFE_PICKLE_GLOBALS` and refuses the file otherwise, before running anything;
    ``safe=False`` is the explicit opt-out for trusted files (pandas' own reader). The
    decompressed size is bounded by ``max_bytes`` either way. Raises FileNotFoundError, or
    ValueError naming the file.
    """
    import pandas as pd

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PandaSet file not found: {str(path)!r}")
    if not isinstance(safe, bool):
        raise ValueError(f"safe_pickle: expected True (allow-listed unpickling, the default) or False "
                         f"(trusted files), got {safe!r}")
    if isinstance(max_bytes, bool) or not isinstance(max_bytes, int) or max_bytes < 1:
        raise ValueError(f"max_bytes: expected a positive int, got {max_bytes!r}")
    from pandas.compat.pickle_compat import Unpickler as CompatUnpickler

    # As pd.read_pickle does: the C unpickler first, pandas' compatibility unpickler for old layouts.
    first, second = (_SafeUnpickler, _safe_compat_unpickler()) if safe else (pickle.Unpickler, CompatUnpickler)
    try:
        try:
            obj = _unpickle_gzip(path, max_bytes, first)
        except (_PickleRefused, _TooBig, MemoryError):
            raise
        except Exception:
            obj = _unpickle_gzip(path, max_bytes, second)
    except _PickleRefused as exc:
        raise ValueError(f"{str(path)!r}: safe mode refuses this pickle, it calls {exc}, which is not a "
                         "DataFrame constructor (load with safe_pickle=False, or --trust-pickle on the "
                         "command line, only if you trust the file)") from None
    except MemoryError:
        raise ValueError(f"{str(path)!r}: pickled DataFrame does not fit in memory") from None
    except _TooBig as exc:
        raise ValueError(str(exc)) from None
    except Exception as exc:  # corrupt gzip / pickle: any error the unpickler raises
        raise ValueError(f"cannot read pickled DataFrame {str(path)!r}: {type(exc).__name__}: {exc}") from None
    if not isinstance(obj, pd.DataFrame):
        raise ValueError(f"{str(path)!r} holds a {type(obj).__name__}, not a pandas DataFrame")
    return obj
