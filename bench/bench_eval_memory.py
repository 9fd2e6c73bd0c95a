"""Peak memory of ``dars eval`` on a full-size real capture: this code against a baseline commit, in the same run.

``dars eval`` renders every test view in chunks, then draws Fig. 7's maps: the samples per ray the *training*
sampler gives a few training views. Up to ``c0dc812`` those maps rendered a whole training image as one chunk (so
the DARS budgets were shared over the image), which on the real fox at its full 540 x 960 px peaked at 15 GB. They
now find the occupied rays first, draw the budgets over the whole image, and render in chunks (same maps).

The bench trains one short run on the capture with this code (``--steps``, the figures do not depend on how well
it is trained), then, per code version, evaluates it in a fresh subprocess (so ``ru_maxrss`` is its own peak):
first ``training_sample_counts`` of one training view alone, then ``evaluate_run`` on ``--limit`` test views with
the usual figures. It prints the peak RSS after each phase, the wall time, and the ratio this / baseline, and
checks that both versions give the same sample-count map.

Usage: ``flock /work/heavy.lock python bench/bench_eval_memory.py [--scene PATH] [--steps 60] [--limit 2]
[--baseline c0dc812|none] [--threads 2] [--work DIR] [--out bench/out/eval_memory]``; writes
``<out>/bench_eval_memory.json``. The baseline peaks near 15 GB on the fox: run it alone on a machine with 24 GB.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_memory import GB, ROOT, SHARED, baseline_code, run_child  # noqa: E402

_CHILD = r"""
import json, resource, sys, time
code, run_dir, limit, threads, maps = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
sys.path.insert(0, code)
import torch
torch.set_num_threads(threads)
from toolkit.evaluate import EvalConfig, evaluate_run, training_sample_counts
from toolkit.train import load_run

def peak():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0  # Linux: KiB

run = load_run(run_dir)
out = {"load": peak()}
t = time.perf_counter()
c = training_sample_counts(run, 0)
out["counts_s"] = time.perf_counter() - t
out["counts"] = peak()
torch.save(c, maps)
t = time.perf_counter()
res = evaluate_run(run, "test", EvalConfig(limit=limit), log=lambda m: None)
out["eval_s"] = time.perf_counter() - t
out["eval"] = peak()
out["psnr"] = res.metrics["psnr"]
out["views"] = res.info["views"]
out["image_size"] = res.info["image_size"]
print("RESULT " + json.dumps(out))
"""


def measure(code: Path, run_dir: Path, limit: int, threads: int, maps: Path) -> dict:
    return run_child(_CHILD, code, [str(code), str(run_dir), str(limit), str(threads), str(maps)], threads)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=str(SHARED / "real" / "fox"), help="a capture (default: the real fox)")
    ap.add_argument("--steps", type=int, default=60, help="training steps of the evaluated run")
    ap.add_argument("--limit", type=int, default=2, help="test views evaluated")
    ap.add_argument("--baseline", default="c0dc812", help="git commit to compare with, or 'none'")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--work", default=None, help="where the run and the baseline code go (default: temp)")
    ap.add_argument("--out", default=str(ROOT / "bench" / "out" / "eval_memory"))
    args = ap.parse_args()
    scene = Path(args.scene)
    if not (scene / "transforms.json").is_file():
        print(f"bench_eval_memory: no capture at {scene} (set --scene or DARS_SHARED_DATA)")
        return 1
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="dars_bench_eval_memory_"))
    work.mkdir(parents=True, exist_ok=True)
    run_dir = work / f"run_{scene.name}_{args.steps}"
    if not (run_dir / "checkpoint.pt").is_file():
        print(f"training {run_dir} ({args.steps} steps) ...", flush=True)
        subprocess.run([sys.executable, "-m", "toolkit.cli", "train", str(scene), "--out", str(run_dir), "--steps",
                        str(args.steps), "--seed", "0", "--threads", str(args.threads), "--force"], check=True,
                       cwd=str(ROOT), capture_output=True)
    versions = {"this": ROOT}
    if args.baseline != "none":
        base = baseline_code(args.baseline, work)
        if base is not None:
            versions[args.baseline] = base

    print(f"{'code':<9} {'loadGB':>7} {'countsGB':>9} {'counts_s':>9} {'evalGB':>7} {'eval_s':>7} {'views':>5} "
          f"{'PSNR':>6}")
    results, maps = {}, {}
    import torch

    for version, code in versions.items():
        maps[version] = work / f"counts_{version}.pt"
        r = measure(code, run_dir, args.limit, args.threads, maps[version])
        results[version] = r
        if "error" in r:
            print(f"{version:<9} {r['error']}", flush=True)
            continue
        print(f"{version:<9} {r['load'] / GB:7.2f} {r['counts'] / GB:9.2f} {r['counts_s']:9.1f} {r['eval'] / GB:7.2f} "
              f"{r['eval_s']:7.1f} {r['views']:>5} {r['psnr']:6.2f}", flush=True)
    summary: dict = {}
    ok = [v for v in versions if "error" not in results[v]]
    if "this" in ok and len(ok) == 2:
        other = next(v for v in ok if v != "this")
        a, b = torch.load(maps["this"]), torch.load(maps[other])
        summary = {"peak_ratio_this_over_baseline": results["this"]["eval"] / results[other]["eval"],
                   "eval_time_ratio": results["this"]["eval_s"] / results[other]["eval_s"],
                   "same_sample_counts": bool(torch.equal(a["samples"], b["samples"])
                                              and torch.equal(a["fine"], b["fine"]))}
        print(f"\npeak RSS this / {other}: {summary['peak_ratio_this_over_baseline']:.2f}; eval time "
              f"{summary['eval_time_ratio']:.2f}; same sample-count map: {summary['same_sample_counts']}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_eval_memory.json").write_text(json.dumps({"args": vars(args), "results": results,
                                                           "summary": summary}, indent=2))
    print(f"-> {out / 'bench_eval_memory.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
