"""``python -m clsplat.bench ...`` = ``clsplat bench ...``."""
from clsplat.bench_cli import main

raise SystemExit(main())
