"""``clsplat bench``: the engine's benchmark reports (``bench/``, installed as ``clsplat.bench``;
registered as the ``bench`` command through the ``clsplat.commands`` entry point).

    clsplat bench {stages,precision,stability,all,composite} [--out DIR] [--device DEV] [--quick] [--repeats N]
    clsplat bench percall [--scenes ...] [--repeats N] [--layout ...] [--profile] [--json FILE]
    clsplat bench peers [--opensplat DIR] [--scenes ...] [--repeats N] [--out DIR]

Each report writes ``<name>.json`` and ``<name>.md`` into ``--out`` (precision also a PNG);
``all`` runs the three and writes ``report.md`` with the device description and the command;
``composite`` (not part of ``all``) times the tuned compositing kernels against the baseline ones.
"""
from __future__ import annotations

import shlex
import sys
import time
from pathlib import Path

from clsplat.argparser import ArgumentParser

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    """benchmark reports: clsplat bench {stages,precision,stability,all,composite} --out DIR, or
    clsplat bench percall [...]"""
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["percall"]:   # the per-call cost of rasterization(): its own options
        from . import percall
        return percall.main(argv[1:])
    if argv[:1] == ["peers"]:     # other CPU renderers on identical inputs: its own options
        from . import peers
        return peers.main(argv[1:])
    p = ArgumentParser(prog="clsplat bench", description=__doc__.split("\n")[0],
                       epilog="also: clsplat bench percall [...], the per-call cost of rasterization(), and "
                              "clsplat bench peers [...], other CPU renderers on identical inputs "
                              "(their own options: -h)")
    p.add_argument("report", choices=("stages", "precision", "stability", "all", "composite"))
    p.add_argument("--out", default="bench_out", help="output folder (created)")
    p.add_argument("--device", default=None, help="OpenCL device, e.g. 'pocl' or '0:0' (default CLSPLAT_DEVICE)")
    p.add_argument("--quick", action="store_true", help="tiny configuration (for tests)")
    p.add_argument("--repeats", type=int, default=None, help="timed repeats after the first call")
    a = p.parse_args(argv)
    if a.repeats is not None and a.repeats < 1:
        p.error("--repeats must be >= 1")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    names = ("stages", "precision", "stability") if a.report == "all" else (a.report,)
    defaults = {"stages": 5, "precision": 3, "stability": 3, "composite": 7}
    parts, secs = [], {}
    import torch

    import clsplat

    from . import composite, precision, stability, stages
    reports = {"stages": stages, "precision": precision, "stability": stability, "composite": composite}
    torch.set_num_threads(1)  # torch's CPU threads would fight PoCL's workers for the cores
    for name in names:
        mod = reports[name]
        t0 = time.perf_counter()
        mod.run(out, device=a.device, quick=a.quick, repeats=a.repeats or defaults[name])
        secs[name] = time.perf_counter() - t0
        print(f"clsplat bench {name}: {secs[name]:.1f} s -> {out / (name + '.md')}", flush=True)
        parts.append((out / f"{name}.md").read_text())
    if a.report == "all":
        cmd = "clsplat bench " + " ".join(shlex.quote(x) for x in (argv if argv is not None else sys.argv[1:]))
        head = ["# clsplat benchmark report", "", f"Command: `{cmd}`", "",
                "Devices:", "", "```", clsplat.describe_devices(), "```", "",
                "Run time: " + ", ".join(f"{k} {v:.0f} s" for k, v in secs.items()), ""]
        (out / "report.md").write_text("\n".join(head) + "\n" + "\n".join(parts))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
