"""The ``dars`` command line: one console script, one module per group of subcommands.

Each module in :data:`COMMANDS` registers its subcommands with ``add_parser(subparsers)``; its handlers only parse
arguments, call library functions and print. The modules import nothing heavy at the top (torch, numpy, Open3D ...
load inside the handlers), so ``dars --help`` and ``dars COMMAND --help`` stay fast. This package is the only part of
``toolkit`` that imports ``export/`` and ``viewers/`` (``tests/test_layering.py`` checks it).

Every command prints a clear error and exits non-zero on bad input; with ``--json`` it prints machine-readable output
on stdout and nothing else there (progress and logs go to stderr).
"""

from __future__ import annotations

import argparse
import sys

from .._checks import DarsError
from . import asset, evaluate, info, onnx, poses, priors, train, view

__all__ = ["COMMANDS", "build_parser", "main"]

COMMANDS = (info, poses, train, priors, asset, view, onnx, evaluate)
"""The subcommand modules, in ``dars --help`` order: info and contact-sheet; poses; train, render, relight; priors; mesh,
bake, export-asset; view, export-web; export-onnx, infer; eval, ablate."""


def build_parser() -> argparse.ArgumentParser:
    """The ``dars`` argument parser with every subcommand (imports no heavy module)."""
    p = argparse.ArgumentParser(
        prog="dars",
        description="DARS-NeRF toolkit: posed photos of galleries -> decomposed digital twins "
                    "(geometry, PBR materials, SH lighting, semantics), glTF, ONNX and previews.",
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for module in COMMANDS:
        module.add_parser(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    """Run ``dars`` with ``argv`` (default: ``sys.argv[1:]``); returns the exit status (2: bad input)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except DarsError as e:
        print(f"dars {args.command}: error: {e}", file=sys.stderr)
        return 2
    except FileNotFoundError as e:
        print(f"dars {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"dars {args.command}: interrupted", file=sys.stderr)
        return 130
