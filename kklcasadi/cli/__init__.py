"""The ``kklcasadi`` command line (also ``python -m kklcasadi``): one module per command, the shared
flags and the one error path in :mod:`.flags`.

``demo``, ``train``, ``evaluate``, ``estimate`` (an observer over a recorded log), ``export``,
``bench``, ``compare`` (the observer beside the EKF and MHE), ``certificate`` (Proposition 1 of the
paper for a model), ``tune`` (a design search on Optuna), ``generalise`` (inputs and noise levels the
observer was not fit on, with the domain monitor), ``robustness`` (plants and noise the EKF's model
does not describe, beside the tuned and the augmented EKF), ``resign`` (accept a checked edit of a model card).
Every error is one line ``error: ...`` on stderr with exit status 2 (``KKLCASADI_DEBUG=1`` shows the
traceback instead); every warning a command raises (a note such as the C compiler's absence) is one line
``warning: ...`` on stderr (:func:`show_warning`: the command line's own display; the library's warnings are
Python's as ever).
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import warnings
from typing import Any, Optional, Sequence, TextIO

from .. import provenance
from . import bench, certificate, compare, demo, estimate, evaluate, export, generalise, resign, robustness, train, tune
from .flags import USER_ERRORS, Parser

__all__ = ["main", "build_parser", "show_warning"]

COMMANDS = (demo, train, evaluate, estimate, export, bench, compare, certificate, tune, generalise, robustness,
            resign)


class _Version(argparse.Action):
    """``--version``: the package version, the commit of its checkout, casadi's and torch's versions; exit."""

    def __init__(self, option_strings: Sequence[str], dest: str = argparse.SUPPRESS, **kwargs: object) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS,
                         help="print the version (and the commit of a git checkout) and exit")

    def __call__(self, parser: argparse.ArgumentParser, *args: object) -> None:
        stamp = provenance.stamp(command="kklcasadi --version")
        where = "not a git checkout" if stamp.commit == provenance.UNKNOWN else f"commit {stamp.commit}"
        print(f"kklcasadi {stamp.version} ({where}; casadi {stamp.casadi}, torch {stamp.torch}, python {stamp.python})")
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="kklcasadi", description="Learned KKL observers (HyperKKL) in CasADi and C.")
    parser.add_argument("--version", action=_Version)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    for command in COMMANDS:
        command.add_parser(sub)
    return parser


def show_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                 file: Optional[TextIO] = None, line: Optional[str] = None) -> None:
    """A warning as the command line shows it: one line ``warning: TEXT`` on stderr (or ``file``), without
    Python's ``file:line: Category:`` prefix and source line (a :func:`warnings.showwarning`)."""
    stream: Any = sys.stderr if file is None else file
    if stream is not None:
        stream.write(f"warning: {' '.join(str(message).split())}\n")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; a user error prints one line ``error: ...`` and returns 2, a warning one line
    ``warning: ...`` (:func:`show_warning`, for the command's run only)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    args.command_line = shlex.join(["kklcasadi", *argv])         # what the result files' stamps record
    try:
        with warnings.catch_warnings():                           # restores Python's display afterwards
            warnings.showwarning = show_warning
            return args.func(args)
    except USER_ERRORS as exc:
        if os.environ.get("KKLCASADI_DEBUG"):
            raise
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
