"""Helpers the command modules share (printing, threads)."""

from __future__ import annotations

import argparse
import json
import sys

SCENE_HELP = "scene directory, transforms JSON, COLMAP model or tiny-NeRF .npz"


def print_json(obj, indent: int | None = 2, default=None) -> None:
    """``obj`` as JSON on stdout (the only thing a ``--json`` command prints there)."""
    sys.stdout.write(json.dumps(obj, indent=indent, default=default) + "\n")


def log(msg: str) -> None:
    """A progress or log line on stderr."""
    print(msg, file=sys.stderr)


def set_threads(n: int) -> None:
    """``--threads N``: torch's CPU threads (0: leave the default)."""
    if n > 0:
        import torch

        torch.set_num_threads(n)


def eval_device(name: str) -> str:
    """``--device auto|cpu|cuda[:N]`` of a command that loads a run: ``auto`` is CUDA when present, else the CPU.

    Raises:
        DarsError: CUDA asked for on a machine without it, or a device name torch does not know.
    """
    import torch

    from .._checks import DarsError

    from ..train.step import resolve_device

    if name == "auto":
        return str(resolve_device(name))
    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError):
        raise DarsError(f"--device {name!r}: give auto, cpu or cuda[:N]") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise DarsError(f"--device {name}: CUDA is not available on this machine (give --device cpu or auto)")
    if dev.type not in ("cpu", "cuda"):
        raise DarsError(f"--device {name!r}: give auto, cpu or cuda[:N]")
    return str(dev)


def number(kind: type = float, min: float | None = None, max: float | None = None, above: float | None = None):
    """An argparse ``type=`` that accepts a finite number of ``kind`` (int or float) in range, else names the rule:
    ``dars train: error: argument --minutes: must be a finite number, got 'nan'``. Checked while parsing, before any
    work."""
    import math

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'a whole number' if kind is int else 'a number'}, "
                                             f"got {text!r}") from None
        if kind is float and not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
        if min is not None and value < min:
            raise argparse.ArgumentTypeError(f"must be ≥ {min:g}, got {text}")
        if above is not None and value <= above:
            raise argparse.ArgumentTypeError(f"must be > {above:g}, got {text}")
        if max is not None and value > max:
            raise argparse.ArgumentTypeError(f"must be ≤ {max:g}, got {text}")
        return value

    parse.__name__ = kind.__name__
    return parse


COUNT = number(int, min=0)
"""A whole number ≥ 0 (0 usually means "all" or "off")."""
POSITIVE = number(int, min=1)
"""A whole number ≥ 1."""
FINITE = number(float)
"""Any finite number."""
NONNEGATIVE = number(float, min=0)
"""A finite number ≥ 0."""
