"""Checked reading of dataset files: JSON, paths confined to a data root, pickled DataFrames.

The dataset loaders (:mod:`.nuscenes`, :mod:`.pandaset`) read files written by others, so every
read here turns a malformed or hostile file into a ``ValueError`` (or ``FileNotFoundError``)
that names the file, before it can crash, hang, exhaust memory or run code:

* :func:`read_json`: invalid JSON, deeply nested JSON (``RecursionError``), integers too long
  to convert and files over a size limit are refused.
* :func:`path_inside`: a relative path taken from a table (nuScenes ``filename``) must stay
  inside the data root; absolute paths and ``..`` that climb out are refused.
* :func:`read_pickled_dataframe`: PandaSet stores DataFrames as gzip pickles, and unpickling
  runs whatever the file says. With ``safe=True`` only the numpy and pandas constructors a
  DataFrame of numbers and strings needs are allowed; anything else is refused unrun.
"""
from __future__ import annotations

import gzip
import json
import os
from pathlib import Path

__all__ = ["read_json", "path_inside", "read_pickled_dataframe", "safe_pickle_default",
           "MAX_JSON_BYTES", "SAFE_PICKLE_GLOBALS"]

#: JSON table files larger than this are refused (nuScenes v1.0-trainval's largest table,
#: sample_data.json, is about 450 MB).
MAX_JSON_BYTES = 4 << 30


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


def safe_pickle_default() -> bool:
    """The default of ``safe``: on when the environment sets ``CLSPLAT_SAFE_PICKLE=1``."""
    return os.environ.get("CLSPLAT_SAFE_PICKLE", "") not in ("", "0")


class _PickleRefused(Exception):
    """A global outside :data:`SAFE_PICKLE_GLOBALS` (turned into a ValueError naming the file)."""


def _safe_unpickler():
    from pandas.compat.pickle_compat import Unpickler, _class_locations_map

    class SafeUnpickler(Unpickler):
        def find_class(self, module: str, name: str):
            key = _class_locations_map.get((module, name), (module, name))
            if (module, name) not in SAFE_PICKLE_GLOBALS and key not in SAFE_PICKLE_GLOBALS:
                raise _PickleRefused(f"{module}.{name}")
            return super().find_class(module, name)

    return SafeUnpickler


def read_pickled_dataframe(path: Path, safe: bool | None = None):
    """Read a gzip-pickled pandas DataFrame (PandaSet's format).

    Unpickling a file runs code the file names. ``safe=True`` (default: ``CLSPLAT_SAFE_PICKLE``)
    allows only :data:`SAFE_PICKLE_GLOBALS` and refuses the file otherwise; ``safe=False`` uses
    pandas' reader and trusts the file. Raises FileNotFoundError, or ValueError naming the file.
    """
    import pandas as pd

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PandaSet file not found: {str(path)!r}")
    if safe is None:
        safe = safe_pickle_default()
    try:
        if safe:
            with gzip.open(path, "rb") as fh:
                obj = _safe_unpickler()(fh).load()
        else:
            obj = pd.read_pickle(path, compression="gzip")
    except _PickleRefused as exc:
        raise ValueError(f"{str(path)!r}: safe mode refuses this pickle, it calls {exc}, which is not a "
                         "DataFrame constructor (load with safe_pickle=False only if you trust the file)") from None
    except MemoryError:
        raise ValueError(f"{str(path)!r}: pickled DataFrame does not fit in memory") from None
    except Exception as exc:  # corrupt gzip / pickle: any error the unpickler raises
        raise ValueError(f"cannot read pickled DataFrame {str(path)!r}: {type(exc).__name__}: {exc}") from None
    if not isinstance(obj, pd.DataFrame):
        raise ValueError(f"{str(path)!r} holds a {type(obj).__name__}, not a pandas DataFrame")
    return obj
