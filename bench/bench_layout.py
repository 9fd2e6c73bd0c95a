"""How good is the room box of :func:`toolkit.layout.fit_room_layout` as a depth target for textureless walls?

The box is fitted from the photos and poses only (sparse points for its axes, a photometric plane sweep for its
faces). For every pixel of the training photos' large textureless regions (:func:`toolkit.regions.textureless_regions`)
whose ray leaves the box through a face the sweep is confident of, the box's depth is compared with the
ground-truth depth map (scoring only: nothing here trains, and the ground truth feeds nothing). Printed per scene:
the fitted box, each face's contrast and share of pixels, the share of textureless pixels given a target, and
their depth error (median, within 5 / 10 cm, beyond 50 cm); then mean and worst over the scenes. With ``--labels
predicted`` (the default, as ``dars train`` does) only the textureless pixels the shipped segmenter labels wall or
floor count (:data:`toolkit.train.data.LAYOUT_CLASSES`); ``--labels none`` scores every textureless pixel.

    python bench/bench_layout.py samples/gallery ~/.cache/dars/galleries/validation/seed_1000001
    python bench/bench_layout.py      # the sample (without its aabb: the fit never reads it) and every cached
                                      # validation gallery
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from toolkit.bounds import triangulate_sparse_points  # noqa: E402
from toolkit.layout import LayoutConfig, fit_room_layout, layout_depth_targets  # noqa: E402
from toolkit.regions import textureless_regions  # noqa: E402
from toolkit.scene import load_scene  # noqa: E402
from toolkit.train.data import layout_pixels  # noqa: E402


def predicted_labels(scene):
    """The shipped segmenter's labels of every view (:class:`toolkit.pixels.PackedViews`), as ``dars train``
    computes them when it is given no priors."""
    import tempfile

    from toolkit.priors import priors_segment, read_priors

    with tempfile.TemporaryDirectory() as tmp:
        priors_segment(scene, Path(tmp) / "segment")
        return read_priors(scene, tmp, labels="segment", weights=False, colour=False, metal="none").labels


def score_scene(path: str, cfg: LayoutConfig, labels: str = "predicted") -> dict:
    scene = load_scene(path, "train", upright="off")
    if not scene.has_extra("depth"):
        raise SystemExit(f"{path}: no ground-truth depth maps in the train split; this benchmark scores against them")
    t0 = time.time()
    points = triangulate_sparse_points(scene).points
    lay = fit_room_layout(scene, points, cfg)
    fit_s = time.time() - t0
    lab = predicted_labels(scene) if labels == "predicted" else None
    regions = {v: layout_pixels(textureless_regions(scene.load_image(v)), lab, v) for v in range(len(scene))}
    tg = layout_depth_targets(scene, lay, regions=regions.__getitem__)
    n_regions = sum(int((r > 0).sum()) for r in regions.values())
    errors = []
    for v in tg["views"].unique().tolist():
        m = tg["views"] == v
        gt = scene.load_extra(v, "depth").numpy()[tg["rows"][m].numpy(), tg["cols"][m].numpy()]
        ok = (gt > 0) & np.isfinite(gt)
        errors.append(np.abs(tg["depth"][m].numpy() - gt)[ok])
    e = np.concatenate(errors) if errors else np.zeros(0)
    stat = (lambda f: float(f(e)) if len(e) else None)
    return {"scene": path, "labels": labels, "points": len(points), "fit_s": round(fit_s, 1), "layout": lay.to_json(),
            "size_m": np.round(lay.hi - lay.lo, 3).tolist(), "target_share": len(tg["depth"]) / max(n_regions, 1),
            "median_m": stat(np.median), "within_5cm": stat(lambda x: (x < 0.05).mean()),
            "within_10cm": stat(lambda x: (x < 0.10).mean()), "beyond_50cm": stat(lambda x: (x > 0.50).mean())}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="*", help="scene folders whose train split has ground-truth depth maps; default: "
                    "the bundled sample and the cached validation galleries (python samples/galleries.py)")
    ap.add_argument("--max-side", type=int, default=LayoutConfig.max_side, help="sweep image size")
    ap.add_argument("--stride", type=int, default=LayoutConfig.stride,
                    help="carry every STRIDE-th pixel of each sweep image (1: all; LayoutConfig.stride)")
    ap.add_argument("--highpass", type=float, default=LayoutConfig.highpass,
                    help="high-pass σ as a fraction of the sweep image's side (0: raw colours; LayoutConfig.highpass)")
    ap.add_argument("--labels", choices=("predicted", "none"), default="predicted",
                    help="predicted: only pixels the shipped segmenter labels wall or floor (as training); none: all")
    ap.add_argument("--json", default=str(ROOT / "bench" / "out" / "layout.json"))
    args = ap.parse_args()
    if not args.scenes:
        sys.path.insert(0, str(ROOT / "samples"))
        from galleries import cached_scenes  # where samples/galleries.py renders ($DARS_CACHE or ~/.cache/dars)

        args.scenes = [str(ROOT / "samples" / "gallery")] + cached_scenes()
        print("[layout] scenes: " + ", ".join(args.scenes))
    cfg = LayoutConfig(max_side=args.max_side, stride=args.stride, highpass=args.highpass)
    print(f"[layout] sweep: {cfg.max_side} px, pixel stride {cfg.stride}, high-pass σ {cfg.highpass:.4g} of the side, "
          f"{cfg.max_views} views; textureless pixels: "
          f"{'labelled wall or floor by the shipped segmenter' if args.labels == 'predicted' else 'all'}")
    rows = []
    for s in args.scenes:
        r = score_scene(s, cfg, args.labels)
        rows.append(r)
        faces = ", ".join(f"{n} {f['contrast']:.2f}/{f['coverage']:.0%}{'' if f['confident'] else ' (not used)'}"
                          for n, f in r["layout"]["faces"].items())
        print(f"[layout] {Path(s).name}: box {r['size_m']} m in {r['fit_s']} s; faces (contrast/pixels): {faces}")
    fmt = lambda x, p="{:.1%}": "-" if x is None else p.format(x)  # noqa: E731
    print("scene | points | textureless pixels with a target | median error | < 5 cm | < 10 cm | > 50 cm")
    for r in rows:
        print(f"{Path(r['scene']).name} | {r['points']} | {fmt(r['target_share'])} | {fmt(r['median_m'], '{:.3f} m')} | "
              f"{fmt(r['within_5cm'])} | {fmt(r['within_10cm'])} | {fmt(r['beyond_50cm'])}")
    scored = [r for r in rows if r["median_m"] is not None]
    if scored:
        med = [r["median_m"] for r in scored]
        w10 = [r["within_10cm"] for r in scored]
        print(f"mean / worst over {len(scored)} scenes: median error {np.mean(med):.3f} / {max(med):.3f} m, "
              f"within 10 cm {np.mean(w10):.1%} / {min(w10):.1%}, share with a target "
              f"{np.mean([r['target_share'] for r in rows]):.1%} / {min(r['target_share'] for r in rows):.1%}")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
