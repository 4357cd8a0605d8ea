"""The argument parser of every ``clsplat`` command: a user's mistake is one line on stderr.

argparse prints the usage and then the error; a command-line mistake here is instead one line,
``PROG: MESSAGE (see PROG --help)``, with exit status 2 (argparse's own messages name the
argument: ``argument --steps: expected a positive integer, got 0``).
"""
from __future__ import annotations

import argparse
import sys
from typing import NoReturn

__all__ = ["ArgumentParser"]


class ArgumentParser(argparse.ArgumentParser):
    """:class:`argparse.ArgumentParser` whose errors are one line (module docstring)."""

    def error(self, message: str) -> NoReturn:
        print(f"{self.prog}: {' '.join(message.split())} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)
