"""``python -m clsplat.bench ...`` = ``clsplat bench ...``."""
from .cli import main

raise SystemExit(main())
