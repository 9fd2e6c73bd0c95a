"""Where does a GLB's preview lose to its field? The moderngl preview's squared error against the test photos, split
two ways, beside the field's own render's error on the same pixels:

* by **what the mesh does there**: no mesh under the pixel (``hole``: the viewer draws the backdrop), a mesh whose
  depth is more than 5 % off the scene's true depth (``off``), or a mesh within 5 % (``on``);
* by the scene's **ground-truth class** (SPEC labels: painting, frame, display, base, wall, floor, other).

Per group: its share of the pixels, the preview's and the field's MSE there, its share of the preview's squared
error, and ``dB if field-like``: what the preview's PSNR (pooled over the views) would gain if that group's error
were the field's. The truth (depth, labels) is read for scoring only: nothing here feeds an export.

Usage (a trained run and its ``dars export-asset`` folder; one thread or two, about a minute for 20 views)::

    .venv/bin/python bench/bench_preview_gap.py RUN ASSET [--split test] [--every 1] [--json OUT.json]
    # e.g. a bench_train.py galleries run:
    G=bench/out/galleries/seed_1000001; .venv/bin/python bench/bench_preview_gap.py $G/run $G/asset
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CLASS_NAMES = ("painting", "frame", "display", "base", "wall", "floor", "other")
DEPTH_TOLERANCE = 0.05
"""Relative depth error above which a covered pixel counts as ``off``."""


def _groups(sse_p: np.ndarray, sse_f: np.ndarray, count: np.ndarray, names: list[str]) -> list[dict]:
    total_p, n = float(sse_p.sum()), float(count.sum())
    rows = []
    for k, name in enumerate(names):
        if count[k] == 0:
            continue
        alt = total_p - sse_p[k] + sse_f[k]
        rows.append({"group": name, "pixels": float(count[k] / n), "preview_mse": float(sse_p[k] / count[k] / 3),
                     "field_mse": float(sse_f[k] / count[k] / 3), "share_of_preview_error": float(sse_p[k] / total_p),
                     "db_if_field_like": float(10 * np.log10(total_p / max(alt, 1e-12)))})
    return rows


def preview_gap(run_dir: Path, asset_dir: Path, split: str = "test", every: int = 1, threads: int = 2) -> dict:
    """The two splits of one GLB (module docstring) over the views ``0, every, 2·every, ...`` of ``split``."""
    from export.gltf import load_glb
    from toolkit._checks import SceneError
    from toolkit.io import linear_to_srgb
    from toolkit.metrics import mesh_depth_map
    from toolkit.pinhole import PinholeCamera
    from toolkit.train import load_run
    from viewers.preview import OffscreenPreview

    torch.set_num_threads(threads)
    run = load_run(run_dir)
    sc = run.load_split(split)
    extras = sc.extras_available()
    if "depth" not in extras:
        raise SceneError(f"{run_dir}: the '{split}' split has no ground-truth depth; this benchmark scores rendered "
                         f"galleries (samples/galleries.py)")
    with_labels = "semantic" in extras
    glb = asset_dir / "scene.glb"
    asset = load_glb(glb)
    extent = float(np.linalg.norm((run.train_scene.aabb[1] - run.train_scene.aabb[0]).numpy()))
    geo_p, geo_f, geo_n = np.zeros(3), np.zeros(3), np.zeros(3)
    cls_p, cls_f, cls_n = np.zeros(256), np.zeros(256), np.zeros(256)
    p_view, p_field = [], []
    with OffscreenPreview(glb) as view:
        for i in range(0, len(sc), every):
            photo = sc.load_image(i).permute(1, 2, 0).numpy()
            gt = np.asarray(sc.load_extra(i, "depth"), np.float64).reshape(photo.shape[:2])
            with torch.no_grad():
                field = linear_to_srgb(run.render(sc.cameras, i).rgb.clamp(0, 1)).numpy()
            cam = PinholeCamera.from_cameras(sc.cameras, i, near=extent * 1e-3, far=extent * 10)
            shown = view.render(cam)
            preview = shown.to_float()
            depth = mesh_depth_map(asset.vertices, asset.faces, sc.cameras, i)
            hole = ~shown.mask
            off = ~hole & ~(np.abs(depth - gt) <= DEPTH_TOLERANCE * np.maximum(gt, 1e-3))
            geo = np.where(hole, 0, np.where(off, 1, 2))
            e_p = ((preview - photo) ** 2).sum(-1)
            e_f = ((field - photo) ** 2).sum(-1)
            geo_p += np.bincount(geo.ravel(), e_p.ravel(), 3)
            geo_f += np.bincount(geo.ravel(), e_f.ravel(), 3)
            geo_n += np.bincount(geo.ravel(), minlength=3)
            if with_labels:
                lab = np.asarray(sc.load_extra(i, "semantic")).astype(np.int64).reshape(gt.shape)
                cls_p += np.bincount(lab.ravel(), e_p.ravel(), 256)
                cls_f += np.bincount(lab.ravel(), e_f.ravel(), 256)
                cls_n += np.bincount(lab.ravel(), minlength=256)
            p_view.append(float(-10 * np.log10(max(e_p.mean() / 3, 1e-12))))
            p_field.append(float(-10 * np.log10(max(e_f.mean() / 3, 1e-12))))
    names = [*CLASS_NAMES, *(f"label {k}" for k in range(len(CLASS_NAMES), 255)), "unlabelled"]
    return {"run": str(run_dir), "asset": str(asset_dir), "split": split, "views": len(p_view),
            "preview_psnr": float(np.mean(p_view)), "field_psnr": float(np.mean(p_field)),
            "gap_db": float(np.mean(p_field) - np.mean(p_view)),
            "by_mesh": _groups(geo_p, geo_f, geo_n, ["hole", "off", "on"]),
            "by_class": _groups(cls_p, cls_f, cls_n, names) if with_labels else None}


def _print(res: dict) -> None:
    print(f"[preview gap] {res['asset']} ({res['split']}, {res['views']} views): preview {res['preview_psnr']:.2f} dB, "
          f"field {res['field_psnr']:.2f} dB, gap {res['gap_db']:.2f} dB (means over the views)")
    for key, title in (("by_mesh", "mesh under the pixel"), ("by_class", "ground-truth class (scoring only)")):
        if not res[key]:
            continue
        print(f"\n{title} | pixels | preview MSE | field MSE | share of preview error | dB if field-like")
        print("--- | --- | --- | --- | --- | ---")
        for r in res[key]:
            print(f"{r['group']} | {r['pixels']:.3f} | {r['preview_mse']:.5f} | {r['field_mse']:.5f} | "
                  f"{r['share_of_preview_error']:.3f} | {r['db_if_field_like']:.2f}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a `dars train` run directory (a rendered gallery's)")
    ap.add_argument("asset", type=Path, help="its `dars export-asset` folder (holding scene.glb)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--every", type=int, default=1, help="score every N-th view of the split")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = ap.parse_args(argv)
    if args.every < 1:
        ap.error(f"--every {args.every}: must be at least 1")
    res = preview_gap(args.run, args.asset, args.split, args.every, args.threads)
    _print(res)
    if args.json is not None:
        from toolkit.io import write_json

        write_json(args.json, res)
        print(f"\nfigures written to {args.json}")


if __name__ == "__main__":
    main()
