"""Data-parallel training (issue 20): 1 process vs 2 processes (gloo, 1 thread each) at equal global batch and steps.

Trains the same scene three times — 1 process (seed 0), 1 process (seed 1: the seed noise), 2 processes through
``torchrun`` (seed 0) — each with ``--threads 1``, the same ``--steps`` and ``--batch-rays`` (the global batch: each
of the 2 ranks draws half), then ``dars eval`` on the same test views. Prints, in one table and as ratios against
the 1-process run: training steps/s (from the checkpoint's training time), test PSNR at equal steps (beside the seed
noise), peak RSS per rank (each rank loads only its half of the photos).

On a 2-core machine the two ranks share the cores with everything else: run it on a quiet machine. Usage:
``python bench/bench_ddp.py [--scene PATH] [--steps 300] [--batch-rays 1024] [--limit 6] [--out bench/out/ddp]``
(default scene: the shared tiny Lego, 100 px; else a synthetic scene built in code).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SHARED = Path(os.environ.get("DARS_SHARED_DATA", ROOT / ".." / "shared" / "data")).resolve()
PY = sys.executable

_MEASURE = ("import resource, subprocess, sys; rc = subprocess.run(sys.argv[1:]).returncode; "
            "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr); sys.exit(rc)")
"""Run a command in a fresh wrapper and print the peak RSS (KB) of its largest process on the last line of stderr."""


def _env(threads: int) -> dict:
    return {**os.environ, "OMP_NUM_THREADS": str(threads), "PYTHONPATH": str(ROOT)}


def _train(scene: str, out: Path, nproc: int, steps: int, batch: int, seed: int) -> dict:
    if out.exists():
        shutil.rmtree(out)
    args = ["train", scene, "--out", str(out), "--steps", str(steps), "--batch-rays", str(batch), "--seed", str(seed),
            "--threads", "1", "--quiet"]
    cmd = ([PY, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(nproc), "-m", "toolkit.cli"]
           if nproc > 1 else [PY, "-m", "toolkit.cli"]) + args
    t0 = time.time()
    p = subprocess.run([PY, "-c", _MEASURE, *cmd], cwd=ROOT, env=_env(1), capture_output=True, text=True)
    if p.returncode:
        raise SystemExit(f"training failed ({' '.join(cmd)}):\n{p.stderr[-3000:]}")
    wall = time.time() - t0
    import torch

    ck = torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=False)
    rows = [json.loads(x) for x in (out / "log.jsonl").read_text().splitlines() if x.strip()]
    dist = [r for r in rows if r.get("kind") == "distributed"]
    rss_ranks = dist[-1]["peak_rss_mb"] if dist else [int(p.stderr.strip().splitlines()[-1]) / 1024.0]
    return {"processes": nproc, "seed": seed, "steps": int(ck["step"]), "train_s": float(ck["elapsed"]),
            "wall_s": wall, "steps_per_s": int(ck["step"]) / float(ck["elapsed"]),
            "peak_rss_mb_per_rank": [round(float(r), 1) for r in rss_ranks],
            "in_sync": dist[-1]["in_sync"] if dist else None}


def _psnr(run: Path, limit: int) -> float:
    p = subprocess.run([PY, "-m", "toolkit.cli", "eval", str(run), "--json", "--limit", str(limit), "--quiet",
                        "--threads", "2", "--force"], cwd=ROOT, env=_env(2), capture_output=True, text=True)
    if p.returncode:
        raise SystemExit(f"eval of {run} failed:\n{p.stderr[-3000:]}")
    return float(json.loads(p.stdout)["psnr"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--batch-rays", type=int, default=1024)
    ap.add_argument("--limit", type=int, default=6, help="test views evaluated")
    ap.add_argument("--out", default=str(ROOT / "bench" / "out" / "ddp"))
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = args.scene
    if not scene:
        lego = SHARED / "tiny_lego" / "tiny_lego_100.npz"
        if lego.is_file():
            scene = str(lego)
        else:
            sys.path.insert(0, str(ROOT / "tests"))
            from synthetic import make_scene

            scene = str(make_scene(out / "synthetic", n_train=40, n_test=8, size=64))
    print(f"scene {scene}: {args.steps} steps, {args.batch_rays} rays per step (global), 1 thread per process")
    # build (or check) the compiled hash-grid kernel first, so no run's first step pays for it
    subprocess.run([PY, "-c", "from toolkit.encoding import hashgrid_kernel; hashgrid_kernel()"], cwd=ROOT,
                   env=_env(1), check=True)
    runs = {}
    for key, nproc, seed in (("1p", 1, 0), ("1p-seed1", 1, 1), ("2p", 2, 0)):
        r = _train(scene, out / key, nproc, args.steps, args.batch_rays, seed)
        r["psnr"] = _psnr(out / key, args.limit)
        runs[key] = r
        print(f"  {key:9s} {r['steps_per_s']:6.2f} steps/s  PSNR {r['psnr']:6.2f} dB  peak RSS/rank "
              f"{', '.join(f'{v:.0f}' for v in r['peak_rss_mb_per_rank'])} MB  (wall {r['wall_s']:.0f} s)")
    a, b, n = runs["1p"], runs["2p"], runs["1p-seed1"]
    ratios = {"steps_per_s_2p_over_1p": b["steps_per_s"] / a["steps_per_s"],
              "psnr_2p_minus_1p_db": b["psnr"] - a["psnr"],
              "seed_noise_db": abs(n["psnr"] - a["psnr"]),
              "peak_rss_per_rank_2p_over_1p": max(b["peak_rss_mb_per_rank"]) / max(a["peak_rss_mb_per_rank"]),
              "ranks_in_sync": b["in_sync"]}
    print(f"2 vs 1 process: steps/s x{ratios['steps_per_s_2p_over_1p']:.2f}, PSNR {ratios['psnr_2p_minus_1p_db']:+.2f} dB "
          f"(seed noise {ratios['seed_noise_db']:.2f} dB), peak RSS per rank x{ratios['peak_rss_per_rank_2p_over_1p']:.2f}, "
          f"ranks in sync: {ratios['ranks_in_sync']}")
    (out / "bench_ddp.json").write_text(json.dumps({"scene": scene, "steps": args.steps, "batch_rays": args.batch_rays,
                                                    "runs": runs, "ratios": ratios}, indent=2) + "\n")
    print(f"-> {out / 'bench_ddp.json'}")


if __name__ == "__main__":
    main()
