"""``dars export-onnx`` and ``dars infer``: the device bundle (SPEC stage 14) and ONNX Runtime inference.

* ``dars export-onnx RUN --out DIR [--precision fp32,fp16,int8] [--opset 17] [--json]`` — writes ``field.onnx``
  (+ ``segment.onnx`` / ``light.onnx`` when available), ``occupancy.npz``, ``background.npz``, ``metadata.json``
  and prints the parity report (:func:`export.field_onnx.export_onnx_models`).
* ``dars infer DIR --camera SCENE:SPLIT:INDEX --out PNG`` — renders the camera through ONNX Runtime
  (:func:`export.infer.render_view`); writes the colour to PNG and every decomposed output beside it
  (``<stem>_albedo.png``, ``_normal``, ``_depth``, ``_semantic`` ...).
* ``dars infer DIR --light PHOTO...`` — SH light per photo (``light.onnx``), JSON ``{"coeffs": ...}``.
* ``dars infer DIR --segment PHOTO... [--out DIR]`` — label PNGs (``segment.onnx``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .._checks import DarsError
from ._common import COUNT, log, number, print_json, set_threads

ONNX_FILES = ("metadata.json", "field.onnx", "field_fp16.onnx", "field_int8.onnx", "heads.onnx", "segment.onnx",
              "light.onnx", "occupancy.npz", "background.npz")
"""What ``dars export-onnx`` writes (:func:`export.field_onnx.export_onnx_models`)."""
PRECISIONS = ("fp32", "fp16", "int8")


def add_parser(sub: argparse._SubParsersAction) -> None:
    q = sub.add_parser("export-onnx", help="export a run for devices (field/segment/light ONNX + occupancy, "
                                           "background, metadata) with parity checks against torch")
    q.add_argument("run", help="RUN directory (output of `dars train`)")
    q.add_argument("--out", required=True, help="output directory")
    q.add_argument("--precision", default="fp32", help="comma-separated: fp32 (always), fp16, int8")
    q.add_argument("--opset", type=number(int, min=13, max=17), default=17,
                   help="ONNX opset, 13-17 (default 17; the graphs need nothing newer)")
    q.add_argument("--view", default="test:0", help="SPLIT:INDEX of the parity view (default test:0)")
    q.add_argument("--no-render-check", action="store_true", help="skip the rendered-view PSNR check")
    q.add_argument("--segmenter", default=None, help="segmenter.pt to export (default: the scene's priors/segment)")
    q.add_argument("--light-weights", default=None, help="light-network weights (default: the scene's light prior "
                                                          "or the shipped weights)")
    q.add_argument("--threads", type=COUNT, default=0, help="CPU threads for torch and ONNX Runtime (0: default)")
    q.add_argument("--force", action="store_true", help="write into a non-empty folder beside its files")
    q.add_argument("--json", action="store_true", help="print the report as JSON on stdout")
    q.set_defaults(func=cmd_export_onnx)

    q = sub.add_parser("infer", help="ONNX Runtime inference on an export: render a camera, or light/segmentation "
                                     "of photos (no torch in the inference path)")
    q.add_argument("dir", help="directory written by `dars export-onnx`")
    g = q.add_mutually_exclusive_group(required=True)
    g.add_argument("--camera", help="SCENE:SPLIT:INDEX to render, e.g. samples/gallery:test:0")
    g.add_argument("--light", nargs="+", metavar="PHOTO", help="estimate SH light from photos (light.onnx)")
    g.add_argument("--segment", nargs="+", metavar="PHOTO", help="segment photos (segment.onnx)")
    q.add_argument("--out", default=None, help="--camera: output PNG (required); --segment: output directory")
    q.add_argument("--precision", default="fp32", choices=["fp32", "fp16", "int8"], help="field graph to use")
    q.add_argument("--sh", default=None, help="JSON file with {'coeffs': [[r,g,b] x 9]} to relight with")
    q.add_argument("--poses", default=None, metavar="TRANSFORMS",
                   help="--light: transforms JSON holding the photos' camera poses (matched by file name; world +z "
                        "up); the shipped light network needs them")
    q.add_argument("--threads", type=COUNT, default=0, help="ONNX Runtime threads (0: its default)")
    q.add_argument("--force", action="store_true",
                   help="--camera: replace --out (and its sibling images); --segment: write into a non-empty folder")
    q.add_argument("--json", action="store_true", help="machine-readable output on stdout")
    q.set_defaults(func=cmd_infer)


def _parse_view(spec: str) -> tuple[str, int]:
    parts = spec.rsplit(":", 1)
    if len(parts) != 2 or not parts[1].isdigit():
        raise DarsError(f"--view {spec!r}: expected SPLIT:INDEX, e.g. test:0")
    return parts[0], int(parts[1])


def cmd_export_onnx(args: argparse.Namespace) -> int:
    from ..outputs import OutputDir
    from ..train.folder import find_run

    precision = tuple(p.strip() for p in args.precision.split(",") if p.strip())
    bad = [p for p in precision if p not in PRECISIONS]
    if bad:
        raise DarsError(f"--precision {args.precision}: unknown {', '.join(map(repr, bad))}; choose from "
                        f"{', '.join(PRECISIONS)} (comma-separated)")
    if "fp32" not in precision:
        precision = ("fp32",) + precision
    split, index = _parse_view(args.view)
    for option, path in (("--segmenter", args.segmenter), ("--light-weights", args.light_weights)):
        if path and not Path(path).is_file():
            raise DarsError(f"{option} {path}: file not found")
    find_run(args.run)
    folder = OutputDir(args.out, "export-onnx", force=args.force).check(ONNX_FILES)

    from export.field_onnx import FieldExportConfig, export_onnx_models

    set_threads(args.threads)
    cfg = FieldExportConfig(parity_split=split, parity_index=index, check_render=not args.no_render_check,
                            threads=args.threads, segmenter=args.segmenter, light_model=args.light_weights)
    with folder:
        rep = export_onnx_models(args.run, folder.path, opset=args.opset, precision=precision, cfg=cfg,
                                 log=log if not args.json else (lambda m: None))
    d = rep.to_dict()
    if args.json:
        print_json(d, default=str)
        return 0
    f = d["field"]
    print(f"wrote {rep.out_dir}: " + ", ".join(f"{k} ({v / 1e6:.2f} MB)" for k, v in d["files"].items()))
    print(f"opset {rep.opset}; field parity (max |onnxruntime - torch|): random {_fmt(f['random'])}")
    print(f"  real ({f['n_real']} samples along {f['real_view']} rays): {_fmt(f['real'])}")
    r = d["render"]
    if r:
        extra = f", torch with DARS {r['psnr_torch_dars']:.3f} dB" if "psnr_torch_dars" in r else ""
        print(f"render {r['view']}: PSNR onnx {r['psnr_onnx']:.4f} dB, torch {r['psnr_torch']:.4f} dB "
              f"(delta {r['delta_db']:.2e} dB; onnx vs torch {r['psnr_onnx_vs_torch']:.1f} dB){extra}")
    for p, v in d["variants"].items():
        if v.get("status") != "exported":
            print(f"{p}: {v.get('status')} ({v.get('reason')})")
            continue
        acc = f"PSNR vs fp32 {v['psnr_vs_fp32']:.2f} dB, vs GT {v['psnr_gt']:.3f} dB (fp32 {v['psnr_gt_fp32']:.3f})" \
            if "psnr_vs_fp32" in v else "no render check"
        print(f"{p}: {v['file']} {v['bytes'] / 1e6:.2f} MB, {acc}")
    for k in ("segment", "light"):
        s = d[k]
        print(f"{k}: {s['status']}" + (f" ({s.get('reason')})" if s["status"] != "exported" else
                                        f" -> {s['path']} (parity {s.get('max_abs_err')})"))
    return 0


def _fmt(errs: dict) -> str:
    worst = max(errs, key=errs.get)
    return f"max {errs[worst]:.2e} ({worst})"


def _parse_camera(spec: str) -> tuple[str, str, int]:
    """``SCENE:SPLIT:INDEX`` -> its parts (nothing is loaded)."""
    parts = spec.rsplit(":", 2)
    if len(parts) != 3 or not parts[2].isdigit():
        raise DarsError(f"--camera {spec!r}: expected SCENE:SPLIT:INDEX, e.g. samples/gallery:test:0")
    return parts[0], parts[1], int(parts[2])


def _camera(spec: str):
    from ..pinhole import PinholeCamera
    from ..scene import load_scene

    parts = _parse_camera(spec)
    scene = load_scene(parts[0], parts[1])
    i = int(parts[2])
    if not 0 <= i < len(scene):
        raise DarsError(f"--camera {spec!r}: index {i} is out of range ({parts[0]} split {parts[1]!r} has "
                        f"{len(scene)} frames)")
    return PinholeCamera.from_cameras(scene.cameras, i), scene, i


def _read_sh(path: str | None):
    if path is None:
        return None
    from ..sh import read_sh_json

    return read_sh_json(path).astype("float32")


def cmd_infer(args: argparse.Namespace) -> int:
    from export import infer

    threads = args.threads or None
    try:
        if args.camera:
            return _infer_camera(args, threads)
        if args.light:
            c2w = infer.poses_for_photos(args.poses, args.light) if args.poses else None
            sh = infer.infer_light(args.dir, args.light, threads, c2w=c2w)
            out = {"photos": list(args.light), "coeffs": sh.tolist(),
                   "convention": "real SH order 2, SPEC order, incident radiance, world frame +z up"}
            if len(args.light) > 1:
                out["mean"] = sh.mean(0).tolist()
            sys.stdout.write(json.dumps(out, indent=None if args.json else 2) + "\n")
            return 0
        return _infer_segment(args, threads)
    except infer.InferError as e:
        raise DarsError(str(e)) from e


def _infer_camera(args, threads) -> int:
    import time

    import numpy as np

    from export import infer

    from ..io import write_png
    from ..outputs import check_output_file
    from ..visualise import OUTPUT_NAMES, render_output_images

    if not args.out:
        raise DarsError("--camera needs --out PNG (the rendered colour; other outputs are written beside it)")
    out = Path(args.out)
    siblings = [out.with_name(f"{out.stem}_{name}.png") for name in OUTPUT_NAMES if name != "rgb"]
    check_output_file(out, args.force, suffixes=(".png",), siblings=siblings if out.suffix.lower() == ".png" else ())
    _parse_camera(args.camera)
    sh = _read_sh(args.sh)
    model = infer.load_model(args.dir, args.precision, threads)  # checks DIR before the scene is loaded
    cam, scene, i = _camera(args.camera)
    from tqdm import tqdm

    bar = tqdm(total=int(cam.width) * int(cam.height), desc="infer", unit="ray", unit_scale=True, file=sys.stderr,
               leave=False)

    def progress(done: int, total: int) -> None:
        bar.update(done - bar.n)

    t0 = time.perf_counter()
    try:
        outs = infer.render_view(model, cam, sh=sh, progress=progress)
    finally:
        bar.close()
    seconds = time.perf_counter() - t0
    imgs = render_output_images(outs, srgb=bool(model.metadata.get("srgb", True)))
    written = {}
    for name, img in imgs.items():
        p = out if name == "rgb" else out.with_name(f"{out.stem}_{name}.png")
        write_png(p, img)
        written[name] = str(p)
    res = {"camera": args.camera, "precision": args.precision, "seconds": round(seconds, 3),
           "size": [cam.width, cam.height], "files": written}
    try:
        gt = scene.load_image(i).numpy().transpose(1, 2, 0)
        mse = float(np.mean((imgs["rgb"].astype(np.float64) - gt.astype(np.float64)) ** 2))
        res["psnr"] = 10 * np.log10(1.0 / max(mse, 1e-20))
    except Exception:  # noqa: BLE001 - a camera without an image still renders
        pass
    if args.json:
        sys.stdout.write(json.dumps(res) + "\n")
    else:
        extra = f", PSNR vs the photo {res['psnr']:.2f} dB" if "psnr" in res else ""
        print(f"rendered {args.camera} in {seconds:.2f} s ({args.precision}){extra} -> {out} "
              f"(+ {len(written) - 1} decomposed outputs beside it)")
    return 0


def _infer_segment(args, threads) -> int:
    import numpy as np

    from export import infer

    from ..io import write_png
    from ..visualise import colourise_labels

    from ..outputs import OutputDir

    folder = None
    if args.out:
        stems = [Path(ph).stem for ph in args.segment]
        folder = OutputDir(args.out, "infer", force=args.force).check(
            [f"{s}_labels{k}.png" for s in stems for k in ("", "_preview")])
    labels = infer.infer_segment(args.dir, args.segment, threads)
    out_dir = folder.path if folder is not None else None
    files = []
    counts = []
    for ph, lab in zip(args.segment, labels):
        counts.append({infer.SEMANTIC_CLASSES[c]: int((lab == c).sum()) for c in range(len(infer.SEMANTIC_CLASSES))})
    if folder is not None:
        with folder:
            for ph, lab in zip(args.segment, labels):
                stem = Path(ph).stem
                write_png(out_dir / f"{stem}_labels.png", lab.astype(np.uint8))
                write_png(out_dir / f"{stem}_labels_preview.png", colourise_labels(lab))
                files.append(str(out_dir / f"{stem}_labels.png"))
    res = {"photos": list(args.segment), "pixels_per_class": counts, "files": files}
    if args.json:
        sys.stdout.write(json.dumps(res) + "\n")
    else:
        for ph, c in zip(args.segment, counts):
            top = sorted(c.items(), key=lambda kv: -kv[1])[:3]
            print(f"{ph}: " + ", ".join(f"{k} {v}" for k, v in top))
        if files:
            print(f"wrote {len(files)} label images to {out_dir}")
    return 0
