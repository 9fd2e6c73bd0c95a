"""Run a ``dars`` command inside a one-rank process group, so the data-parallel code path runs through the backend.

``torchrun --nproc_per_node 1`` starts no process group (a single rank trains as one process), and NCCL refuses two
ranks on one GPU: on a one-GPU machine this is the way to put every collective of ``dars train`` (broadcasts of the
config, layout and state, gradient all-reduces, occupancy sync, gathers of the RNG states and loss averages) through
NCCL. The group has one rank, so the collectives move nothing between devices: this checks the calls, the devices
and dtypes they see, not multi-GPU scaling.

Usage::

    python bench/one_rank_group.py --backend nccl train SCENE --out RUN --steps 100 --device cuda
    python bench/one_rank_group.py --backend gloo train SCENE --out RUN --steps 20 --device cpu

The training log says ``data-parallel: 1 processes (nccl)``; the last line printed is ``one-rank group: BACKEND rc N``.
Ran on an NVIDIA H200 (torch 2.11.0+cu130, NCCL 2.28.9) on 2026-11-29: 100 steps on the bundled sample, rc 0.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--backend", choices=("nccl", "gloo"), default="nccl")
    p.add_argument("--port", type=int, default=29517, help="MASTER_PORT of the one-rank group")
    args, rest = p.parse_known_args(argv)
    if not rest:
        p.error("give the dars command to run, e.g. train SCENE --out RUN --steps 100 --device cuda")
    import torch
    import torch.distributed as dist

    if args.backend == "nccl":
        if not torch.cuda.is_available():
            print("one-rank group: NCCL needs CUDA, and torch sees no GPU here (use --backend gloo)", file=sys.stderr)
            return 2
        torch.cuda.set_device(0)
    os.environ.setdefault("MASTER_ADDR", "127.0.0.1")
    os.environ.setdefault("MASTER_PORT", str(args.port))
    os.environ.pop("WORLD_SIZE", None)
    dist.init_process_group(args.backend, rank=0, world_size=1)
    import toolkit.distributed as td
    from toolkit.cli import main as dars

    td._CURRENT = td.Distributed(rank=0, world_size=1, local_rank=0, backend=args.backend)
    try:
        rc = dars(rest)
    finally:
        td.shutdown()
    print(f"one-rank group: {args.backend} rc {rc}")
    return rc


if __name__ == "__main__":
    raise SystemExit(main())
