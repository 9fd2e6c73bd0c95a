"""Benchmark of the device path (SPEC stage 14): ONNX Runtime vs torch eager on the same CPU.

Measures, for each thread count (``--threads 1,2``):

* **field throughput** — points per second of the whole field query (density, normal, materials, semantics, local
  light and the PBR-shaded colour: :class:`export.field_onnx.FieldOnnxModule`) on ``--points`` random points in
  the scene box: torch eager with the compiled C++ hash-grid kernel (what training and ``dars render`` use),
  torch eager with the plain-torch encoding (the code the graph is traced from), and ONNX Runtime fp32 / fp16 /
  int8 (``field.onnx``, ``field_fp16.onnx``, ``field_int8.onnx``);
* **view render** — one full test view (the sample's are 128 x 128) with the run's render sampler, DARS off:
  :meth:`toolkit.train.run.Run.render` vs :func:`export.infer.render_view` (numpy + ONNX Runtime), both with the
  run's shading (once per ray or at every sample, as it trained), plus each variant's PSNR against the ground truth
  and against the fp32 render.

Ratios are against torch eager (kernel) at the same thread count. Wall times are medians of ``--repeats``
runs after one warm-up. The machine is shared: run with ``--threads 1`` there.

Usage::

    python bench/bench_onnx.py --run RUN [--export DIR] [--threads 1,2] [--points 65536] [--repeats 3] [--json F]

``--export`` defaults to ``RUN/onnx`` and is created (fp32 + fp16 + int8) when missing.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _median_time(fn, repeats: int) -> float:
    fn()  # warm-up
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def _psnr(a, b) -> float:
    import numpy as np

    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * math.log10(1.0 / mse)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", required=True, help="RUN directory of `dars train`")
    ap.add_argument("--export", default=None, help="export directory (default RUN/onnx; created when missing)")
    ap.add_argument("--threads", default="1,2", help="comma-separated thread counts")
    ap.add_argument("--points", type=int, default=65536, help="points per field query")
    ap.add_argument("--repeats", type=int, default=3, help="timed repeats of each field query (median)")
    ap.add_argument("--view", default="test:0", help="SPLIT:INDEX of the rendered view")
    ap.add_argument("--no-view", action="store_true", help="skip the view renders")
    ap.add_argument("--json", default=None, help="also write the results as JSON here")
    args = ap.parse_args(argv)

    import numpy as np
    import torch

    from export import infer
    from export.field_onnx import FieldExportConfig, FieldOnnxModule, _TorchHashGrid, export_onnx_models
    from toolkit.io import linear_to_srgb
    from toolkit.train import load_run

    threads = [int(t) for t in args.threads.split(",") if t.strip()]
    torch.set_num_threads(threads[0])
    exp = Path(args.export) if args.export else Path(args.run) / "onnx"
    if not (exp / "metadata.json").is_file():
        print(f"exporting {args.run} -> {exp} (fp32, fp16, int8) ...", file=sys.stderr)
        export_onnx_models(args.run, exp, precision=("fp32", "fp16", "int8"), cfg=FieldExportConfig(threads=threads[0]))
    precisions = [p for p in ("fp32", "fp16", "int8") if (exp / infer.FIELD_FILES[p]).is_file()]
    run = load_run(args.run, with_weights=False)
    module = FieldOnnxModule(run.field, run.cfg.shading).eval()
    g = torch.Generator().manual_seed(0)
    lo, hi = run.train_scene.aabb
    pts = lo + torch.rand(args.points, 3, generator=g) * (hi - lo)
    dirs = torch.nn.functional.normalize(torch.randn(args.points, 3, generator=g), dim=-1)
    sh = run.l_env.reshape(9, 3)
    split, index = args.view.rsplit(":", 1)
    sc = run.load_split(split)
    index = int(index)
    cam = infer.PinholeCamera.from_cameras(sc.cameras, index)
    gt = sc.load_image(index).numpy().transpose(1, 2, 0)
    srgb = lambda x: np.clip(linear_to_srgb(np.clip(x, 0, 1)), 0, 1)  # noqa: E731
    sampler = replace(run.cfg.render_sampler, dars=False)

    rows = []
    for nt in threads:
        torch.set_num_threads(nt)
        args_t = (pts, dirs, sh) if run.cfg.shading == "pbr" else (pts, dirs)

        def torch_field():
            with torch.no_grad():
                module(*args_t)

        def torch_field_pure():
            with torch.no_grad(), _TorchHashGrid(run.field):
                module(*args_t)

        t_kernel = _median_time(torch_field, args.repeats)
        t_pure = _median_time(torch_field_pure, args.repeats)
        view_torch = None
        rgb32 = None
        if not args.no_view:
            t0 = time.perf_counter()
            with torch.no_grad():
                o = run.render(sc.cameras, index, sampler=sampler)  # the run's own shading: per ray or per sample
            view_torch = time.perf_counter() - t0
            torch_rgb = o.rgb.numpy()
        base = {"threads": nt, "points": args.points}
        rows.append({**base, "backend": "torch eager (C++ kernel)", "precision": "fp32", "field_s": t_kernel,
                     "view_s": view_torch, "psnr_gt": _psnr(srgb(torch_rgb), gt) if view_torch else None})
        rows.append({**base, "backend": "torch eager (pure torch)", "precision": "fp32", "field_s": t_pure,
                     "view_s": None, "psnr_gt": None})
        for p in precisions:
            model = infer.load_model(exp, p, threads=nt)
            feed_sh = None if run.cfg.shading != "pbr" else sh.numpy()
            pn, dn = pts.numpy(), dirs.numpy()
            t_field = _median_time(lambda: model.query(pn, dn, feed_sh, chunk=args.points), args.repeats)
            row = {**base, "backend": "onnxruntime", "precision": p, "field_s": t_field, "view_s": None,
                   "psnr_gt": None}
            if not args.no_view:
                t0 = time.perf_counter()
                rgb = infer.render_view(model, cam)["rgb"]
                row["view_s"] = time.perf_counter() - t0
                row["psnr_gt"] = _psnr(srgb(rgb), gt)
                if p == "fp32":
                    rgb32 = rgb
                    row["psnr_vs_torch"] = _psnr(srgb(rgb), srgb(torch_rgb))
                elif rgb32 is not None:
                    row["psnr_vs_fp32"] = _psnr(srgb(rgb), srgb(rgb32))
            row["bytes"] = (exp / infer.FIELD_FILES[p]).stat().st_size
            rows.append(row)
        ref = next(r for r in rows if r["threads"] == nt and r["backend"].startswith("torch eager (C++"))
        for r in rows:
            if r["threads"] == nt:
                r["field_pts_per_s"] = r["points"] / r["field_s"]
                r["field_ratio"] = ref["field_s"] / r["field_s"]
                r["view_ratio"] = (ref["view_s"] / r["view_s"]) if r["view_s"] and ref["view_s"] else None

    space = (f"contracted to far radius {run.field.cfg.far_radius:g}" if run.field.cfg.contraction else "bounded")
    print(f"\nrun {args.run} (step {run.step}, {run.cfg.shading}, encoding {run.field.cfg.encoding}, {space}); "
          f"export {exp}; "
          f"view {args.view} {cam.width}x{cam.height}, sampler {sampler.n_coarse}+{sampler.n_fine}, DARS off; "
          f"{args.points} points per field query; torch {torch.__version__}")
    hdr = (f"{'thr':>3} {'backend':<26} {'prec':<5} {'MB':>6} {'field Mpt/s':>11} {'x torch':>8} "
           f"{'view s':>7} {'x torch':>8} {'PSNR GT':>8} {'PSNR vs fp32/torch':>18}")
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        mb = f"{r['bytes'] / 1e6:6.2f}" if "bytes" in r else f"{'':>6}"
        view = f"{r['view_s']:7.2f}" if r["view_s"] else f"{'-':>7}"
        vr = f"{r['view_ratio']:8.2f}" if r.get("view_ratio") else f"{'-':>8}"
        pg = f"{r['psnr_gt']:8.3f}" if r.get("psnr_gt") else f"{'-':>8}"
        pv = r.get("psnr_vs_fp32", r.get("psnr_vs_torch"))
        pv = f"{pv:18.2f}" if pv is not None else f"{'-':>18}"
        print(f"{r['threads']:>3} {r['backend']:<26} {r['precision']:<5} {mb} {r['field_pts_per_s'] / 1e6:11.3f} "
              f"{r['field_ratio']:8.2f} {view} {vr} {pg} {pv}")
    print("x torch: speed relative to torch eager with the C++ kernel at the same thread count (>1 = faster).")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "run": args.run, "export": str(exp)}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
