"""Could the photos' own sparse points pin a textureless wall? A plane through them, scored as a depth target.

A textureless wall's depth is not fixed by the photos (README, "Where the room's geometry goes wrong"). One candidate
prior is a plane through the sparse points (:func:`toolkit.bounds.triangulate_sparse_points`) that fall in each large
textureless region (:func:`toolkit.regions.textureless_regions`) of a training photo, used as that region's depth
target. This benchmark measures how good such targets would be before anyone trains on them: for every region, the
points projected into it (its edges dilated by ``--dilate`` pixels, where a painting's frame or the floor line has
features) get a RANSAC plane (inliers within ``--tau`` of their depth), and the plane's depth at the region's pixels
is compared with the ground-truth depth map (scoring only: nothing here trains).

Two point sets are compared:

* ``own``: only the points triangulated from this very photo (visible in it by construction);
* ``all``: every point that projects into the region (more points, but some are hidden behind other surfaces).

A region is *anchored* when its plane has ``--min-inliers`` inliers that spread over at least ``--min-spread`` of the
region's extent (a line of points along the floor fits any plane through it). Printed per scene: the share of region
pixels anchored, and the depth error of the anchored pixels (median, within 5 / 10 cm, beyond 50 cm).

    python bench/bench_sparse_planes.py samples/gallery ~/.cache/dars/galleries/validation/seed_1000001
    python bench/bench_sparse_planes.py     # the sample and every cached validation gallery
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

from toolkit.bounds import SparsePointsConfig, _pixel_rays, _project, triangulate_sparse_points  # noqa: E402
from toolkit.regions import textureless_regions  # noqa: E402
from toolkit.scene import load_scene  # noqa: E402


def ransac_plane(X: np.ndarray, z: np.ndarray, tau: float, rng: np.random.Generator, iters: int = 300):
    """(centroid, unit normal, inlier mask) of the plane with the most points within ``tau · z`` of it, refitted
    to its inliers; None when no three points span a plane."""
    best = None
    for _ in range(iters):
        i = rng.choice(len(X), 3, replace=False)
        n = np.cross(X[i[1]] - X[i[0]], X[i[2]] - X[i[0]])
        if np.linalg.norm(n) < 1e-9:
            continue
        n /= np.linalg.norm(n)
        inl = np.abs((X - X[i[0]]) @ n) < tau * z
        if best is None or inl.sum() > best.sum():
            best = inl
    if best is None:
        return None
    c = X[best].mean(0)
    n = np.linalg.svd(X[best] - c)[2][2]
    return c, n, np.abs((X - c) @ n) < tau * z


def score_scene(path: str, args) -> dict:
    from scipy import ndimage

    scene = load_scene(path, "train", upright="off")
    if not scene.has_extra("depth"):
        raise SystemExit(f"{path}: no ground-truth depth maps in the train split; this benchmark scores against them")
    t0 = time.time()
    pts = triangulate_sparse_points(scene, SparsePointsConfig(max_views=len(scene)))
    P = pts.points
    c2w = scene.cameras.c2w.double().numpy()
    Ks = scene.cameras.intrinsics().double().numpy()
    rng = np.random.default_rng(0)
    res = {m: {"pixels": 0, "anchored": 0, "errors": []} for m in ("own", "all")}
    for v in range(len(scene)):
        reg = textureless_regions(scene.load_image(v))
        if reg.max() == 0:
            continue
        gt = scene.load_extra(v, "depth").numpy()
        H, W = reg.shape
        uv, z = _project(c2w[v], Ks[v], P)
        col, row = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        inview = (z > 0) & (col >= 0) & (row >= 0) & (col < W) & (row < H)
        own = (pts.views == v).any(1)
        ys, xs = np.mgrid[0:H, 0:W]
        for k in range(1, int(reg.max()) + 1):
            m = reg == k
            near = ndimage.binary_dilation(m, iterations=args.dilate)
            hit = inview.copy()
            hit[inview] = near[row[inview], col[inview]]
            spread_region = np.sqrt(np.linalg.eigvalsh(np.cov(np.stack([xs[m], ys[m]]).astype(float))))[0]
            for mode, sel in (("own", hit & own), ("all", hit)):
                res[mode]["pixels"] += int(m.sum())
                if sel.sum() < 3:
                    continue
                fit = ransac_plane(P[sel], z[sel], args.tau, rng)
                if fit is None:
                    continue
                c, n, inl = fit
                if inl.sum() < args.min_inliers:
                    continue
                spread = np.sqrt(np.linalg.eigvalsh(np.cov(uv[sel][inl].T)))[0]
                if spread < args.min_spread * max(spread_region, 1e-6):
                    continue
                rays = _pixel_rays(c2w[v], Ks[v], np.stack([xs[m] + 0.5, ys[m] + 0.5], -1))
                o = c2w[v, :3, 3]
                with np.errstate(divide="ignore", invalid="ignore"):
                    t = ((c - o) @ n) / (rays @ n)
                _, zp = _project(c2w[v], Ks[v], o + t[:, None] * rays)
                g = gt[m]
                ok = (g > 0) & np.isfinite(g) & np.isfinite(zp)
                res[mode]["anchored"] += int(m.sum())
                res[mode]["errors"].append(np.abs(zp - g)[ok])
    out = {"scene": path, "points": len(P), "seconds": round(time.time() - t0, 1)}
    for mode, r in res.items():
        e = np.concatenate(r["errors"]) if r["errors"] else np.zeros(0)
        out[mode] = {"region_pixels": r["pixels"], "anchored_share": r["anchored"] / max(r["pixels"], 1),
                     "median_m": float(np.median(e)) if len(e) else None,
                     "within_5cm": float((e < 0.05).mean()) if len(e) else None,
                     "within_10cm": float((e < 0.10).mean()) if len(e) else None,
                     "beyond_50cm": float((e > 0.50).mean()) if len(e) else None}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="*", help="scene folders whose train split has ground-truth depth maps; default: "
                    "the bundled sample and the cached validation galleries (python samples/galleries.py)")
    ap.add_argument("--dilate", type=int, default=3, help="pixels added round each region to catch its edge points")
    ap.add_argument("--tau", type=float, default=0.015, help="RANSAC inlier distance, a fraction of the depth")
    ap.add_argument("--min-inliers", type=int, default=8)
    ap.add_argument("--min-spread", type=float, default=0.15,
                    help="inliers' smaller image-space spread over the region's, below which the plane is not anchored")
    ap.add_argument("--json", default=str(ROOT / "bench" / "out" / "sparse_planes.json"))
    args = ap.parse_args()
    if not args.scenes:
        sys.path.insert(0, str(ROOT / "samples"))
        from galleries import cached_scenes  # where samples/galleries.py renders ($DARS_CACHE or ~/.cache/dars)

        args.scenes = [str(ROOT / "samples" / "gallery")] + cached_scenes()
        print("[sparse-planes] scenes: " + ", ".join(args.scenes))
    rows = [score_scene(s, args) for s in args.scenes]
    fmt = lambda x, p="{:.1%}": "-" if x is None else p.format(x)  # noqa: E731
    print("scene | points | set | region pixels anchored | median error | < 5 cm | < 10 cm | > 50 cm")
    for r in rows:
        for mode in ("own", "all"):
            m = r[mode]
            print(f"{Path(r['scene']).name} | {r['points']} | {mode} | {fmt(m['anchored_share'])} | "
                  f"{fmt(m['median_m'], '{:.2f} m')} | {fmt(m['within_5cm'])} | {fmt(m['within_10cm'])} | "
                  f"{fmt(m['beyond_50cm'])}")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
