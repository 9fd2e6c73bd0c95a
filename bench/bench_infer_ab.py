"""The ONNX renderer against an older version of itself, in one process, runs interleaved (SPEC stage 14).

``dars infer`` is numpy + ONNX Runtime: its speed depends on the renderer (``export/infer.py``) and on the field
graph it is given (``field.onnx``, traced from ``toolkit.encoding.hash_grid_encode_torch`` and the field). This
bench renders one view with three arms, one after the other, ``--repeats`` rounds, and prints each arm's median
and its ratio to the first:

* ``baseline``: ``export/infer.py`` as of ``--baseline REV`` (read with ``git show``) on ``--baseline-export``
  (a bundle that REV's ``dars export-onnx`` wrote);
* ``renderer``: this tree's renderer on the same baseline bundle (what the renderer alone changed);
* ``both``: this tree's renderer on ``--export`` (a bundle this tree wrote; what both changed).

It also times each bundle's whole ``field.onnx`` on random points in its box (``--points``), interleaved, and prints
the largest difference of each arm's maps from the baseline's. The machine is shared: the arms alternate so that a
slow minute hits them all.

Usage::

    python bench/bench_infer_ab.py --baseline REV --baseline-export OLD --export NEW --camera SCENE:SPLIT:I
        [--width 270] [--repeats 3] [--threads 2] [--points 65536]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))


def load_baseline_renderer(rev: str, workdir: Path):
    """``export/infer.py`` at git revision ``rev`` (extracted by :func:`bench_memory.baseline_code`), imported as a
    module of its own (it needs numpy, onnxruntime and ``toolkit.pinhole`` only)."""
    from bench_memory import baseline_code

    code = baseline_code(rev, workdir)
    if code is None:
        raise SystemExit(f"--baseline {rev!r}: not a commit of this repository")
    spec = importlib.util.spec_from_file_location("infer_baseline", code / "export" / "infer.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["infer_baseline"] = mod  # its dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def field_throughput(bundles: dict[str, Path], threads: int, points: int, repeats: int) -> dict[str, float]:
    """Million points a second of each bundle's whole ``field.onnx`` (median of ``repeats``, interleaved)."""
    from export.infer import make_session

    meta = {k: json.loads((b / "metadata.json").read_text()) for k, b in bundles.items()}
    sessions = {k: make_session(b / "field.onnx", threads) for k, b in bundles.items()}
    first = next(iter(meta.values()))
    aabb = np.asarray(first["aabb"], np.float32)
    rng = np.random.default_rng(0)
    feed = {"points": aabb[0] + rng.random((points, 3)).astype(np.float32) * (aabb[1] - aabb[0]),
            "view_dirs": rng.standard_normal((points, 3)).astype(np.float32),
            "sh": np.asarray(first["l_env"], np.float32)}
    feed["view_dirs"] /= np.linalg.norm(feed["view_dirs"], axis=1, keepdims=True)
    times: dict[str, list[float]] = {k: [] for k in sessions}
    for s in sessions.values():  # warm-up
        s.run(None, {i.name: feed[i.name] for i in s.get_inputs()})
    for _ in range(repeats):
        for k, s in sessions.items():
            f = {i.name: feed[i.name] for i in s.get_inputs()}
            t0 = time.perf_counter()
            s.run(None, f)
            times[k].append(time.perf_counter() - t0)
    return {k: points / float(np.median(v)) / 1e6 for k, v in times.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", required=True, help="git revision of the baseline renderer")
    ap.add_argument("--baseline-export", required=True, help="bundle written by the baseline's dars export-onnx")
    ap.add_argument("--export", required=True, help="bundle written by this tree's dars export-onnx")
    ap.add_argument("--camera", required=True, help="SCENE:SPLIT:INDEX of the view")
    ap.add_argument("--width", type=int, default=None, help="render at this width (default: the photo's)")
    ap.add_argument("--repeats", type=int, default=3, help="rounds of the three renders (median)")
    ap.add_argument("--threads", type=int, default=2, help="ONNX Runtime threads")
    ap.add_argument("--points", type=int, default=65536, help="points of the field-throughput query")
    args = ap.parse_args(argv)

    from export import infer
    from toolkit.cli.onnx import _camera

    old_dir, new_dir = Path(args.baseline_export), Path(args.export)
    for d in (old_dir, new_dir):
        if not (d / "field.onnx").is_file():
            raise SystemExit(f"{d}: not an export bundle (no field.onnx); write one with dars export-onnx RUN --out {d}")
    cam = _camera(args.camera)[0]
    if args.width:
        cam = cam.resized(args.width)
    with tempfile.TemporaryDirectory() as td:
        base = load_baseline_renderer(args.baseline, Path(td))
        arms = {"baseline": (base, base.load_model(old_dir, threads=args.threads)),
                "renderer": (infer, infer.load_model(old_dir, threads=args.threads)),
                "both": (infer, infer.load_model(new_dir, threads=args.threads))}
        print(f"view {args.camera} at {cam.width}x{cam.height}, {args.threads} ONNX Runtime threads, baseline "
              f"{args.baseline} on {old_dir}, this tree on {new_dir}; {args.repeats} interleaved rounds")
        times: dict[str, list[float]] = {k: [] for k in arms}
        maps: dict[str, dict] = {}
        for _ in range(args.repeats):
            for k, (mod, model) in arms.items():
                t0 = time.perf_counter()
                maps[k] = mod.render_view(model, cam)
                times[k].append(time.perf_counter() - t0)
    ref = float(np.median(times["baseline"]))
    for k, ts in times.items():
        diff = max(float(np.abs(maps[k][n].astype(np.float64) - maps["baseline"][n]).max())
                   for n in ("rgb", "depth", "normal", "albedo") if n in maps[k])
        print(f"  {k:9s} view {float(np.median(ts)):7.2f} s (runs {', '.join(f'{t:.2f}' for t in ts)})  "
              f"x{float(np.median(ts)) / ref:.3f} of the baseline  max |map - baseline| {diff:.2g}")
    tp = field_throughput({"baseline": old_dir, "this tree": new_dir}, args.threads, args.points, 7)
    print(f"  field.onnx, {args.points} random points, median of 7: baseline {tp['baseline']:.3f} Mpt/s, this tree "
          f"{tp['this tree']:.3f} Mpt/s (x{tp['this tree'] / tp['baseline']:.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
