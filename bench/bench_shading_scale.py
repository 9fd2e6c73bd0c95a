"""Why is a run's albedo too bright? Irradiance at the rendered normals against the true normals, under the run's light.

A Lambertian pixel is ``albedo · E(n) / π``: the photo fixes the product, not the factors. If the normal head points
away from where the light comes from, ``E(n)`` at the rendered normal is small and the albedo grows to make up for
it — the render still matches the photo, the albedo MAE does not. This benchmark measures that on *test* views of
finished runs, with the split's ground-truth normals and albedo (ground truth used for scoring only):

* ``E_pred / E_true``: mean irradiance of the run's own light ``l_env`` (eq. 18's SH, Ramamoorthi-Hanrahan) at the
  rendered normals over the mean at the true normals, on the pixels with a true normal and opacity >= 0.5;
* ``albedo pred / true``: mean rendered albedo over the mean true albedo on the same pixels;
* ``E_truth / E_true``: the ground-truth light's irradiance at the true normals over the run's light's — how far the
  light *level* itself is off (the light prior's share of the albedo error);
* the normal MAE on those pixels, of the normal head and of the rendered depth's own normals (central differences
  over ±k pixels of the rendered surface points, k = 1 as the depth-normal loss takes them, and k = 4): how good the
  target the depth-normal term pulls the head toward is. The same construction on the ground-truth depth
  (``gt_depth_normal_mae_k1`` in the JSON; 2-3° on gallery 1000002) checks the method.

If the normals explain the albedo, ``albedo pred / true`` ≈ ``(E_true / E_pred) · (E_truth / E_true)``.

Usage (any finished runs with a ground-truth test split)::

    python bench/bench_shading_scale.py RUN [RUN ...] [--views 0,5,10,15] [--threads 1] [--out bench/out/shading_scale]

Writes ``bench_shading_scale.json`` under ``--out``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def shading_scale(l_env: torch.Tensor, normal_pred: torch.Tensor, normal_true: torch.Tensor,
                  albedo_pred: torch.Tensor, albedo_true: torch.Tensor, sh_truth: torch.Tensor | None = None) -> dict:
    """Irradiance and albedo levels of one view's masked pixels.

    Args:
        l_env: float [9, 3] the run's SH light.
        normal_pred, normal_true: float [M, 3] unit normals (rendered, ground truth).
        albedo_pred, albedo_true: float [M, 3].
        sh_truth: float [9, 3] the ground-truth light, or None.

    Returns:
        dict of means: ``E_pred``, ``E_true``, ``E_truth`` (None without ``sh_truth``), ``albedo_pred``,
        ``albedo_true``, ``normal_mae`` (degrees), ``pixels``.
    """
    from toolkit.sh import irradiance_sh

    if normal_pred.shape[0] == 0:
        raise ValueError("no pixels with a ground-truth normal and a rendered surface in this view")
    return {"E_pred": float(irradiance_sh(l_env, normal_pred).mean()),
            "E_true": float(irradiance_sh(l_env, normal_true).mean()),
            "E_truth": None if sh_truth is None else float(irradiance_sh(sh_truth, normal_true).mean()),
            "albedo_pred": float(albedo_pred.mean()), "albedo_true": float(albedo_true.mean()),
            "normal_mae": _mae_deg(normal_pred, normal_true), "pixels": int(normal_pred.shape[0])}


def _mae_deg(a: torch.Tensor, b: torch.Tensor) -> float:
    """:func:`toolkit.metrics.normal_mae_deg` (the evaluation's normal MAE) of normals given as [..., 3] rows."""
    from toolkit.metrics import normal_mae_deg

    return float(normal_mae_deg(a.reshape(-1, 3).T[..., None], b.expand_as(a).reshape(-1, 3).T[..., None]))


def pooled(rows: list[dict]) -> dict:
    """Pixel-weighted means over views, and the ratios the module docstring defines."""
    n = sum(r["pixels"] for r in rows)
    m = {k: sum(r[k] * r["pixels"] for r in rows) / n for k in ("E_pred", "E_true", "albedo_pred", "albedo_true",
                                                                  "normal_mae")}
    for k in ("depth_normal_mae_k1", "depth_normal_mae_k4", "gt_depth_normal_mae_k1"):  # per view, when measured
        vals = [r[k] for r in rows if r.get(k) is not None]
        m[k] = sum(vals) / len(vals) if vals else None
    truth = None if any(r["E_truth"] is None for r in rows) else sum(r["E_truth"] * r["pixels"] for r in rows) / n
    m.update(pixels=n, E_pred_over_true=m["E_pred"] / max(m["E_true"], 1e-12),
             albedo_pred_over_true=m["albedo_pred"] / max(m["albedo_true"], 1e-12),
             E_truth_over_true=None if truth is None else truth / max(m["E_true"], 1e-12))
    return m


def run_one(run_dir: str, views: list[int], split: str) -> dict:
    from toolkit._checks import DarsError
    from toolkit.cameras import generate_rays
    from toolkit.losses import depth_normals
    from toolkit.scene import load_scene
    from toolkit.train import load_run

    run = load_run(run_dir)
    if run.cfg.shading != "pbr":
        raise DarsError(f"{run_dir}: a radiance-only run (standard NeRF) has no albedo or light to measure")
    sc = load_scene(run.scene_path, split)
    missing = [k for k in ("normal", "albedo") if k not in sc.extras_available()]
    if missing:
        raise DarsError(f"{run.scene_path} split '{split}' has no ground-truth {', '.join(missing)} maps: this "
                        "benchmark needs a rendered gallery (samples/galleries.py) or the bundled sample")
    truth = None if sc.sh is None else sc.sh.float()
    rows = []
    with torch.no_grad():
        for i in [v for v in views if v < len(sc)]:
            out = run.render(sc.cameras, i)
            n_gt = sc.load_extra(i, "normal").permute(1, 2, 0)
            m = (n_gt.abs().sum(-1) > 0) & (out.opacity > 0.5)
            if not bool(m.any()):
                continue
            row = shading_scale(run.l_env, out.normal[m], n_gt[m], out.albedo[m],
                                sc.load_extra(i, "albedo").permute(1, 2, 0)[m], truth)
            h, w = out.depth.shape
            rays = generate_rays(sc.cameras, [i])
            d = rays.directions.reshape(h, w, 3)

            def surface(depth: torch.Tensor) -> torch.Tensor:  # camera-axis depth -> points along the rays
                return rays.origins.reshape(h, w, 3) + d * (depth / rays.z_scale.reshape(h, w))[..., None]

            pts = surface(out.depth)
            for k in (1, 4):
                mk = m[k:-k, k:-k]
                row[f"depth_normal_mae_k{k}"] = (_mae_deg(depth_normals(pts, d, k)[mk], n_gt[k:-k, k:-k][mk])
                                                  if bool(mk.any()) else None)
            row["gt_depth_normal_mae_k1"] = None  # the same construction on the true depth: checks the method
            if "depth" in sc.extras_available():
                gd = sc.load_extra(i, "depth")
                mk = (n_gt[1:-1, 1:-1].abs().sum(-1) > 0) & (gd[1:-1, 1:-1] > 0)
                if bool(mk.any()):
                    row["gt_depth_normal_mae_k1"] = _mae_deg(depth_normals(surface(gd), d, 1)[mk],
                                                             n_gt[1:-1, 1:-1][mk])
            rows.append(row)
    if not rows:
        raise DarsError(f"{run_dir}: none of views {views} has a rendered surface with a ground-truth normal")
    return {"run": run_dir, "views": len(rows), **pooled(rows)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="*", help="finished run folders (dars train --out)")
    ap.add_argument("--views", default="0,5,10,15", help="test views to render (comma-separated indices)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=str(REPO / "bench" / "out" / "shading_scale"))
    a = ap.parse_args(argv)
    if not a.runs:  # `make bench` runs every benchmark without arguments: nothing of the user's to measure
        print("[shading-scale] skipped: pass finished run folders of a scene with ground-truth normals and albedo "
              "(e.g. dars train GALLERY --out RUN --steps 600)")
        return 0
    torch.set_num_threads(max(1, a.threads))
    from toolkit._checks import DarsError
    from toolkit.io import write_json

    try:
        views = [int(v) for v in a.views.split(",") if v.strip()]
    except ValueError:
        ap.error(f"--views {a.views!r}: give comma-separated view indices, e.g. 0,5,10,15")
    results = []
    print("run                                        normal MAE  depth n. k=1/k=4  E_pred/E_true  albedo pred/true  "
          "E_truth/E_true")
    for r in a.runs:
        try:
            res = run_one(r, views, a.split)
        except DarsError as e:
            print(f"[shading-scale] {e}", file=sys.stderr)
            return 2
        results.append(res)
        t = "n/a" if res["E_truth_over_true"] is None else f"{res['E_truth_over_true']:.2f}"
        dn = "/".join("n/a" if res[k] is None else f"{res[k]:.1f}°" for k in ("depth_normal_mae_k1",
                                                                              "depth_normal_mae_k4"))
        print(f"{r[-42:]:<42} {res['normal_mae']:9.1f}° {dn:>17} {res['E_pred_over_true']:14.2f} "
              f"{res['albedo_pred_over_true']:17.2f} {t:>15}", flush=True)
    checks = [r["gt_depth_normal_mae_k1"] for r in results if r["gt_depth_normal_mae_k1"] is not None]
    if checks:
        print(f"method check: the ground-truth depth's own normals (±1 px) are {min(checks):.1f}-{max(checks):.1f}° "
              "from the true normals")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "bench_shading_scale.json", {"split": a.split, "views": views, "runs": results})
    print(f"wrote {out / 'bench_shading_scale.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
