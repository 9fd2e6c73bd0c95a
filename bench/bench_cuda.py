"""CUDA checks and figures, for a machine with a GPU (none of this runs in CI).

What it measures, in one run, on whatever GPU ``torch.cuda`` sees:

1. **Step time, CPU vs CUDA, at equal settings**: ``dars train`` (fast preset, seed 0, default priors) on the scene
   ``--scene`` (default: the bundled sample) for ``--cpu-steps`` steps on the CPU (all cores of the machine) and
   ``--gpu-steps`` on CUDA; seconds per step from the run's own ``log.jsonl`` (first logged step excluded: warm-up).
2. **NCCL**: ``torchrun --nproc_per_node N -m toolkit.cli train ... --device cuda`` with N = min(GPUs, 2): with two
   GPUs the NCCL process group, the all-reduces and the ranks' parameter digests (``in_sync``); with one GPU only the
   torchrun launch on CUDA (a single rank has no process group; NCCL refuses two ranks on one GPU).
3. **Quality, CUDA**: the first of ``--galleries`` trained for ``--check-steps`` (600: equal steps with the CPU
   figures in the README), then each gallery for ``--steps`` (comma-separated; ``auto`` is the most steps, in
   multiples of 500, that fit what is left of ``--budget-s`` at the measured step time), each with ``dars train``'s
   defaults (photos and poses only), then ``evaluate_run`` on its test split: PSNR, albedo MAE (raw and
   scale-aligned), normal MAE, mIoU, metallic MAE.

Everything is appended to ``OUT/results.txt`` as it is measured, so a run stopped at a time limit keeps what it
finished. Usage::

    python bench/bench_cuda.py --galleries G0 G1 --steps auto --budget-s 420 --out OUT
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
PY = sys.executable
T0 = time.time()


def _say(out: Path, line: str) -> None:
    print(line, flush=True)
    with open(out / "results.txt", "a") as f:
        f.write(line + "\n")


def _train(cmd_prefix: list[str], scene: str, run: Path, steps: int, device: str, seed: int = 0) -> float:
    args = cmd_prefix + ["train", scene, "--out", str(run), "--steps", str(steps), "--seed", str(seed),
                         "--device", device, "--quiet", "--force"]
    t = time.time()
    subprocess.run(args, check=True, cwd=ROOT)
    return time.time() - t


def _sec_per_step(run: Path) -> tuple[float, tuple[int, int]]:
    rows = [r for r in map(json.loads, open(run / "log.jsonl")) if r.get("kind") == "train" and "elapsed" in r]
    if len(rows) < 2:
        raise RuntimeError(f"{run}/log.jsonl: fewer than two logged steps; train longer")
    a, b = rows[0], rows[-1]
    return (b["elapsed"] - a["elapsed"]) / max(b["step"] - a["step"], 1), (a["step"], b["step"])


def _evaluate(run: Path, device: str) -> dict:
    from toolkit.evaluate import EvalConfig, evaluate_run
    from toolkit.train.run import load_run
    te = evaluate_run(load_run(run, device=device), "test", EvalConfig(figure_views=4, weight_views=0))
    m = dict(te.metrics)
    m.update({k: v for k, v in (te.details.get("materials") or {}).items()})
    try:
        from toolkit.report import plot_test_grid
        plot_test_grid(te.figures.grid, run / "test_grid.png")
    except Exception as e:  # noqa: BLE001 - a figure is a nicety here
        print(f"(no test grid: {e})")
    return m


def _fmt(m: dict) -> str:
    def f(k, fmt):
        v = m.get(k)
        return "-" if v is None else fmt % v
    s = (f"PSNR {f('psnr', '%.2f')} SSIM {f('ssim', '%.3f')} albedo {f('albedo_mae', '%.3f')} "
         f"aligned {f('albedo_mae_aligned', '%.3f')} metallic {f('metallic_mae', '%.3f')} "
         f"normal {f('normal_mae', '%.1f')} mIoU {f('miou', '%.3f')} env_l2 {f('env_light_l2', '%.2f')}")
    return s


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=str(ROOT / "samples" / "gallery"))
    ap.add_argument("--galleries", nargs="*", default=[])
    ap.add_argument("--steps", default="auto")
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--check-steps", type=int, default=600,
                    help="first gallery only: train this many steps too (equal steps with the CPU figures); 0: none")
    ap.add_argument("--max-steps", type=int, default=10000, help="cap on an auto step count")
    ap.add_argument("--cpu-steps", type=int, default=60)
    ap.add_argument("--gpu-steps", type=int, default=150)
    ap.add_argument("--budget-s", type=float, default=420.0, help="seconds for the whole run (auto steps fit it)")
    ap.add_argument("--skip", default="", help="comma-separated parts to skip: time,nccl,quality")
    ap.add_argument("--out", default=str(ROOT / "bench" / "out" / "cuda"))
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    skip = set(filter(None, a.skip.split(",")))

    import torch
    cuda = torch.cuda.is_available()
    dev = "cuda" if cuda else "cpu"
    name = torch.cuda.get_device_name() if cuda else "no CUDA device (CPU only)"
    _say(out, f"# bench_cuda: torch {torch.__version__}, {name}, {os.cpu_count()} CPU cores")
    cli = [PY, "-m", "toolkit.cli"]

    sps_gpu = None
    if "time" not in skip:
        runs = out / "runs"
        _train(cli, a.scene, runs / "time_cpu", a.cpu_steps, "cpu")
        sps_cpu, n1 = _sec_per_step(runs / "time_cpu")
        _say(out, f"step time, {Path(a.scene).name}, fast preset: CPU ({os.cpu_count()} cores) "
                  f"{sps_cpu * 1000:.0f} ms/step "
                  f"(steps {n1[0]}..{n1[1]})")
        if cuda:
            _train(cli, a.scene, runs / "time_gpu", a.gpu_steps, "cuda")
            sps_gpu, n2 = _sec_per_step(runs / "time_gpu")
            _say(out, f"step time, {Path(a.scene).name}, fast preset: CUDA {sps_gpu * 1000:.0f} ms/step "
                      f"(steps {n2[0]}..{n2[1]}); CPU/CUDA = {sps_cpu / sps_gpu:.1f}x")
    if "nccl" not in skip and cuda:
        run = out / "runs" / "nccl"
        n = min(torch.cuda.device_count(), 2)
        t = time.time()
        r = subprocess.run([PY, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(n), "-m",
                            "toolkit.cli", "train", a.scene, "--out", str(run), "--steps", "50", "--device", "cuda",
                            "--quiet", "--force", "--no-auto-priors"], cwd=ROOT, capture_output=True, text=True)
        tail = (r.stdout + r.stderr).strip().splitlines()[-2:]
        ok = r.returncode == 0 and (run / "checkpoint.pt").exists()
        dist_row = {}
        if (run / "log.jsonl").exists():
            for line in open(run / "log.jsonl"):
                if '"distributed"' in line:
                    dist_row = json.loads(line)
        what = (f"backend={dist_row.get('backend')} in_sync={dist_row.get('in_sync')}" if dist_row else
                "one GPU: torchrun with 1 rank trains without a process group, so NCCL itself is NOT exercised")
        _say(out, f"torchrun {n} rank(s), --device cuda: {'ok' if ok else 'FAILED rc=%d' % r.returncode}, {what}, "
                  f"{time.time() - t:.0f}s; {' | '.join(tail)}")
    if "quality" not in skip:
        jobs = []
        if a.check_steps and a.galleries:
            jobs.append((a.galleries[0], str(a.check_steps)))
        jobs += [(g, st) for st in a.steps.split(",") for g in a.galleries]
        for seed in [int(s) for s in a.seeds.split(",")]:
            for i, (g, st) in enumerate(jobs):
                left = a.budget_s - (time.time() - T0)
                if st == "auto":
                    per = sps_gpu or 0.1
                    n_left = sum(1 for _, s2 in jobs[i:] if s2 == "auto")
                    steps = min(a.max_steps, int(max(0.0, (left - 45 * n_left) / n_left) / per) // 500 * 500)
                    if steps < 1000:
                        _say(out, f"{Path(g).name}: too little time left ({left:.0f} s) for an auto run")
                        continue
                else:
                    steps = int(st)
                run = out / "runs" / f"{Path(g).name}_{steps}_s{seed}"
                tt = _train(cli, g, run, steps, dev, seed=seed)
                m = _evaluate(run, dev)
                _say(out, f"{Path(g).name} {dev} steps={steps} seed={seed}: {_fmt(m)} train {tt:.0f}s "
                          f"(t={time.time() - T0:.0f}s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
