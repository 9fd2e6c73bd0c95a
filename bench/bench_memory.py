"""Training memory against photo count and size (issue 18, item 3): peak RSS of the trainer's data path, this code
against a baseline commit of the repository (the loader before packed per-pixel storage), in the same run.

Each measurement is a fresh subprocess (so ``ru_maxrss`` is its own peak) that does what ``dars train`` does before
and during its first steps: ``load_scene``, ``resolve_config``, ``prepare_data`` (photos, priors, W maps),
``init_state`` (field, optimiser, DARS ray sampler) and ``--steps`` training steps. It prints the peak RSS after
each phase (the first training step, which loads the compiled hash-grid kernel, is not timed), the bytes the
photos take as uint8 (``H x W x 3`` per photo) and, per code version, the growth of the
peak with the uint8 bytes (least squares over the photo counts: 1.0 means the peak grows by exactly the uint8
bytes).

Captures:

* synthetic: ``N`` photos of ``S x S`` px (smooth random texture + grain, JPEG q90, cameras on a ring), written once
  per size under ``--work`` (``transforms_<N>.json`` lists N of them); W maps are written beforehand as ``priors/weights/<key>.npy`` (float16, as
  ``dars priors weights`` writes them), so both versions load the same priors and no time goes to computing them;
* ``--scene PATH`` (default: the real fox capture in ``$DARS_SHARED_DATA/real/fox`` when present): a real capture,
  W maps computed by the trainer as ``dars train`` does without priors.

The baseline code is ``git archive REF`` of this repository extracted to a temporary folder (the default REF is the
last commit before the packed storage, ``ff9638a``); ``--baseline none`` measures this code only. A baseline run is
skipped where its expected peak would exceed ``--baseline-max-gb`` (measured: 3.5 GB for 25 photos of 1 MP, 13.1 GB for
100: about 130 bytes a pixel).

Usage: ``flock /work/heavy.lock python bench/bench_memory.py [--counts 25,50,100,300] [--sizes 1000]
[--baseline ff9638a] [--steps 3] [--threads 2] [--downscale 1] [--scene PATH|none] [--out bench/out/memory]``;
writes ``<out>/bench_memory.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("DARS_SHARED_DATA", ROOT / ".." / "shared" / "data")).resolve()
GB = 1024.0 ** 3
_OLD_BYTES_PER_PIXEL = 130.0  # the baseline loader's peak per training pixel (measured, see the module docstring)

_CHILD = r"""
import json, resource, sys, time
code, scene_path, split, downscale, steps, threads = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5]), int(sys.argv[6])
sys.path.insert(0, code)
import torch
torch.set_num_threads(threads)
from toolkit.scene import load_scene
from toolkit.train import init_state, make_config, prepare_data, resolve_config, train_step

def peak():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0  # Linux: KiB

out = {"imports": peak()}
scene = load_scene(scene_path, split, downscale=downscale)
cfg = make_config("fast", steps=100000)
cfg, scene = resolve_config(cfg, scene)
t = time.perf_counter()
data = prepare_data(scene, cfg, log=lambda m: None)
out["load_s"] = time.perf_counter() - t
out["data"] = peak()
state = init_state(cfg, data)
out["init"] = peak()
train_step(state, data)  # the first step builds or loads the hash-grid kernel: not timed
state.step += 1
t = time.perf_counter()
for _ in range(steps - 1):
    train_step(state, data)
    state.step += 1
out["step_s"] = (time.perf_counter() - t) / max(steps - 1, 1)
out["train"] = peak()
hw = [(int(h), int(w)) for h, w in zip(scene.cameras.height, scene.cameras.width)]
out["photos"] = len(hw)
out["uint8_bytes"] = sum(3 * h * w for h, w in hw)
print("RESULT " + json.dumps(out))
"""


def make_capture(root: Path, counts: list[int], size: int, seed: int = 0) -> dict[int, Path]:
    """``max(counts)`` synthetic JPEG photos of ``size`` x ``size`` px on a ring of cameras, float16 W maps, and a
    ``transforms_<n>.json`` listing the first ``n`` photos for each count; returns {n: that file}."""
    import cv2
    import numpy as np

    from toolkit.pinhole import look_at

    scene = root / f"synthetic_{size}px"
    (scene / "images").mkdir(parents=True, exist_ok=True)
    wdir = scene / "priors" / "weights"
    wdir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    n_max = max(counts)
    frames = []
    for k in range(n_max):
        name = f"images/p_{k:04d}.jpg"
        a = 2 * math.pi * k / n_max
        c2w = look_at([3.0 * math.cos(a), 3.0 * math.sin(a), 0.5 + 0.3 * math.sin(5 * a)], [0.0, 0.0, 0.0])
        frames.append({"file_path": name, "transform_matrix": np.asarray(c2w).tolist()})
        if (scene / name).is_file() and (wdir / f"images__p_{k:04d}.npy").is_file():
            continue
        low = rng.random((12, 12, 3)).astype(np.float32)
        img = cv2.resize(low, (size, size), interpolation=cv2.INTER_CUBIC)
        img = np.clip(img + rng.normal(0, 0.03, img.shape).astype(np.float32), 0, 1)
        cv2.imwrite(str(scene / name), (img * 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 90])
        w = cv2.resize(rng.random((8, 8)).astype(np.float32), (size, size), interpolation=cv2.INTER_LINEAR)
        np.save(wdir / f"images__p_{k:04d}.npy", w.astype(np.float16))
    files = {}
    for n in counts:
        # the frames spread evenly over the ring, so every subset surrounds the scene
        pick = [frames[round(i * n_max / n)] for i in range(n)]
        meta = {"camera_angle_x": 0.9, "aabb": [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], "frames": pick}
        files[n] = scene / f"transforms_{n}.json"
        files[n].write_text(json.dumps(meta))
    return files


def baseline_code(ref: str, work: Path) -> Path | None:
    """``git archive REF`` of this repository extracted under ``work`` (None when the commit is not there)."""
    dst = work / f"code_{ref}"
    if (dst / "toolkit" / "__init__.py").is_file():
        return dst
    dst.mkdir(parents=True, exist_ok=True)
    try:
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", ref], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(dst)], input=archive, check=True)
    except (subprocess.CalledProcessError, FileNotFoundError) as e:
        print(f"bench_memory: baseline {ref} unavailable ({e}); measuring this code only")
        return None
    return dst


def run_child(child: str, code: Path, argv: list[str], threads: int) -> dict:
    """Run the script ``child`` in a fresh Python process on the code at ``code`` (``argv`` after it), parse its last
    ``RESULT {json}`` line and add the wall time as ``wall_s``; ``{"error": ...}`` with the output's tail when it
    fails. A fresh process makes ``ru_maxrss`` its own peak."""
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), PYTHONPATH=str(code))
    if code != ROOT:  # the hash-grid kernel is built per source path: the baseline gets its own build folder
        env["DARS_EXT_DIR"] = str(code / "_ext")
    t = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", child, *argv], capture_output=True, text=True, env=env, cwd=str(code))
    lines = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
    if p.returncode != 0 or not lines:
        tail = (p.stderr or p.stdout).strip().splitlines()[-5:]
        return {"error": f"exit {p.returncode}: " + " | ".join(tail)}
    r = json.loads(lines[-1][7:])
    r["wall_s"] = time.perf_counter() - t
    return r


def measure(code: Path, scene: Path, split: str, downscale: int, steps: int, threads: int) -> dict:
    return run_child(_CHILD, code, [str(code), str(scene), split, str(downscale), str(steps), str(threads)], threads)


def _slope(rows: list[dict]) -> float | None:
    """Least-squares growth of the training peak per uint8 photo byte."""
    pts = [(r["uint8_bytes"], r["train"]) for r in rows if "train" in r]
    if len(pts) < 2:
        return None
    mx = sum(x for x, _ in pts) / len(pts)
    my = sum(y for _, y in pts) / len(pts)
    sxx = sum((x - mx) ** 2 for x, _ in pts)
    return sum((x - mx) * (y - my) for x, y in pts) / sxx if sxx else None


def _row(label: str, version: str, r: dict) -> str:
    if "error" in r:
        return f"{label:<28} {version:<9} {r['error']}"
    return (f"{label:<28} {version:<9} {r['photos']:>6} {r['uint8_bytes'] / GB:8.2f} {r['imports'] / GB:8.2f} "
            f"{r['data'] / GB:8.2f} {r['init'] / GB:8.2f} {r['train'] / GB:8.2f} {r['load_s']:7.1f} {r['step_s']:7.2f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--counts", default="25,50,100,300", help="photo counts of the synthetic captures")
    ap.add_argument("--sizes", default="1000", help="photo sizes (px, square) of the synthetic captures")
    ap.add_argument("--baseline", default="ff9638a", help="git commit of the old loader, or 'none'")
    ap.add_argument("--baseline-max-gb", type=float, default=14.0,
                    help="skip baseline runs expected to peak above this (about 130 bytes a pixel)")
    ap.add_argument("--scene", default="auto", help="a real capture to measure too ('auto': the fox; 'none')")
    ap.add_argument("--split", default="train", help="split of --scene")
    ap.add_argument("--downscale", type=int, default=1, help="--downscale of every measured load")
    ap.add_argument("--steps", type=int, default=3, help="training steps (at least 1; the first is not timed)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--work", default=None, help="where synthetic captures and the baseline code go (default: temp)")
    ap.add_argument("--out", default=str(ROOT / "bench" / "out" / "memory"))
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT))

    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="dars_bench_memory_"))
    work.mkdir(parents=True, exist_ok=True)
    versions = {"this": ROOT}
    if args.baseline != "none":
        base = baseline_code(args.baseline, work)
        if base is not None:
            versions[f"{args.baseline}"] = base
    cases: list[tuple[str, Path, str, int]] = []  # (label, scene, split, pixels)
    counts = [int(c) for c in args.counts.split(",") if c.strip()]
    for size in [int(s) for s in args.sizes.split(",") if s.strip()]:
        for n, file in make_capture(work, counts, size).items():
            cases.append((f"synthetic {n} x {size}px", file, "all", n * (size // args.downscale) ** 2))
    real = SHARED / "real" / "fox" if args.scene == "auto" else (None if args.scene == "none" else Path(args.scene))
    if real is not None and real.exists():
        cases.append((f"{real.name} ({args.split})", real, args.split, 0))

    print(f"{'capture':<28} {'code':<9} {'photos':>6} {'uint8GB':>8} {'importGB':>8} {'dataGB':>8} {'initGB':>8} "
          f"{'trainGB':>8} {'load_s':>7} {'step_s':>7}")
    results: list[dict] = []
    for label, scene, split, pixels in cases:
        for version, code in versions.items():
            if version != "this" and pixels and _OLD_BYTES_PER_PIXEL * pixels / GB > args.baseline_max_gb:
                r = {"error": f"skipped (expected peak {_OLD_BYTES_PER_PIXEL * pixels / GB:.1f} GB > --baseline-max-gb)"}
            else:
                r = measure(code, scene, split, args.downscale, args.steps, args.threads)
            r.update(capture=label, code=version, synthetic=split == "all")
            results.append(r)
            print(_row(label, version, r), flush=True)
    summary = {}
    for version in versions:
        syn = [r for r in results if r["code"] == version and r["synthetic"] and "train" in r]
        summary[version] = {"growth_per_uint8_byte": _slope(syn)}
    for label in dict.fromkeys(r["capture"] for r in results):
        pair = {r["code"]: r for r in results if r["capture"] == label and "train" in r}
        if "this" in pair and len(pair) == 2:
            other = next(v for k, v in pair.items() if k != "this")
            summary.setdefault("ratio_this_over_baseline", {})[label] = pair["this"]["train"] / other["train"]
    print()
    for version in versions:
        g = summary[version]["growth_per_uint8_byte"]
        print(f"peak growth per uint8 photo byte ({version}): " + ("-" if g is None else f"{g:.2f}"))
    for label, ratio in summary.get("ratio_this_over_baseline", {}).items():
        print(f"peak RSS this / baseline, {label}: {ratio:.2f}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_memory.json").write_text(json.dumps({"args": vars(args), "results": results, "summary": summary},
                                                      indent=2))
    print(f"-> {out / 'bench_memory.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
