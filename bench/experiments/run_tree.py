"""Run a script or module with ``clsplat`` imported from another tree (an older commit, for
before/after figures measured side by side in one sitting).

    git archive COMMIT clsplat kernels models bench | tar -x -C /tmp/tree-src   # then lay it out
    python bench/experiments/run_tree.py TREE SCRIPT.py|MODULE [args...]

``TREE`` holds the ``clsplat`` package to import (with its kernels and models as that commit laid
them out). The editable install's finder is removed from ``sys.meta_path`` so that ``import
clsplat`` resolves to ``TREE/clsplat``. A name ending in ``.py`` runs as a script, anything else
as a module (``python -m``).
"""
from __future__ import annotations

import runpy
import sys


def main() -> None:
    if len(sys.argv) < 3:
        print("usage: run_tree.py TREE SCRIPT.py|MODULE [args...]", file=sys.stderr)
        raise SystemExit(2)
    tree, target = sys.argv[1], sys.argv[2]
    sys.meta_path[:] = [f for f in sys.meta_path
                        if "editable" not in type(f).__name__.lower() and "editable" not in getattr(f, "__module__", "")]
    sys.path.insert(0, tree)
    sys.argv = [target] + sys.argv[3:]
    import clsplat
    print("clsplat from", clsplat.__file__, file=sys.stderr)
    if target.endswith(".py"):
        runpy.run_path(target, run_name="__main__")
    else:
        runpy.run_module(target, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
