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


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (``--downscale``)."""
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return n
