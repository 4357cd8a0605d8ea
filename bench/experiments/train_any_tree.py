"""Run ``clsplat train ARGS`` with the train command of whichever tree is imported: today's
(``clsplat.models.registry``) or one from before the registry (``clsplat.models.common.cli``), so
that an older commit's training steps can be timed beside today's (``steps_tree_ab.sh``).

    python bench/experiments/run_tree.py OLD_TREE bench/experiments/train_any_tree.py pgt --preset small ...
    python bench/experiments/train_any_tree.py pgt --preset small ...          # today's tree
"""
import sys

import clsplat  # noqa: F401  first: the thread defaults go in before torch loads

try:
    from clsplat.models.registry import train_command
except ImportError:   # trees before the registry
    from clsplat.models.common.cli import train_command

raise SystemExit(train_command(sys.argv[1:]))
