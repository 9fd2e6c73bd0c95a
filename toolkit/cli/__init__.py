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
import errno
import sys
from pathlib import Path

from .._checks import DarsError
from ..outputs import release_all
from . import asset, evaluate, info, onnx, poses, priors, train, view

__all__ = ["COMMANDS", "build_parser", "main", "describe_os_error"]

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
    """Run ``dars`` with ``argv`` (default: ``sys.argv[1:]``); returns the exit status.

    0: done; 2: bad input (a wrong option, a missing or damaged file, an output folder dars may not write: one line
    on stderr naming the file or value and what to do); 1: the system failed a read or write (disk full, permission
    denied ...: one line naming the path); 130: interrupted. A traceback means a bug in dars.
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help, or an argument error argparse has already printed
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
    name = f"dars {args.command}" + (f" {args.priors_command}" if getattr(args, "priors_command", None) else "")
    try:
        return int(args.func(args) or 0)
    except DarsError as e:
        print(f"{name}: error: {e}", file=sys.stderr)
        return 2
    except FileNotFoundError as e:
        print(f"{name}: error: {describe_os_error(e, args)}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"{name}: error: {describe_os_error(e, args)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{name}: interrupted", file=sys.stderr)
        return 130
    finally:
        release_all()


_OS_ERRORS = {
    errno.ENOSPC: ("no space left on device", "free some space or choose another --out, then run the command again"),
    errno.EDQUOT: ("disk quota exceeded", "free some space or choose another --out, then run the command again"),
    errno.EACCES: ("permission denied", "check the permissions, or choose another path (--out)"),
    errno.EPERM: ("operation not permitted", "check the permissions, or choose another path (--out)"),
    errno.EROFS: ("read-only file system", "choose a path on a writable disk (--out)"),
    errno.EISDIR: ("is a folder, not a file", "give a file path"),
    errno.ENOTDIR: ("a part of the path is a file, not a folder", "check the path"),
    errno.ENOENT: ("no such file or folder", "check the path"),
    errno.ENAMETOOLONG: ("file name too long", "choose a shorter path"),
    errno.EMFILE: ("too many open files", "raise the limit (ulimit -n) and run the command again"),
}


def describe_os_error(e: OSError, args: argparse.Namespace | None = None) -> str:
    """One line for an OS error: what failed, on which path (the real file, not a temporary one), what to do."""
    from ..outputs import is_temp_file

    what, fix = _OS_ERRORS.get(e.errno, (e.strerror or type(e).__name__, "check the path and run the command again"))
    path = e.filename
    if e.filename2 is not None and path is not None and is_temp_file(Path(str(path)).name):
        path = e.filename2  # os.replace(temporary, real): name the real file
    if path is not None and is_temp_file(Path(str(path)).name):
        p = Path(str(path))
        path = p.with_name(p.name[1:].rsplit(".", 2)[0])  # .NAME.XXXXXXXX.tmp -> NAME
    where = f": {path}" if path is not None else ""
    if args is not None and getattr(args, "command", None) == "train" and e.errno in (errno.ENOSPC, errno.EDQUOT):
        fix += f"; the last complete checkpoint is intact: continue with `dars train --resume --out {args.out}`"
    return f"{what}{where} ({fix})"
