"""How good can the albedo be under one global SH light? A bound from the ground truth, before any training.

The field shades a Lambertian pixel as ``albedo · E(n) / π`` with ``E`` the irradiance of one SH light for the whole
room (eq. 18), plus a bounded per-point correction. So the albedo it can reach is at best the photo's own radiance
divided by ``E(n)/π``. This benchmark computes that albedo on a gallery's *test* views from the ground truth alone
(radiance, normals, albedo, labels; ground truth used for scoring only, nothing here trains anything) and scores it
with the evaluation's albedo MAE (eq. 34, on :func:`toolkit.metrics.material_mask`, the albedo clamped to [0, 1] as
the field's is):

* ``true_sh``: under the gallery's own SH light (the JSON's ``"sh"``: the incident light at the room's centre, the
  Env-light L2 target), with its per-channel scale-aligned MAE (``true_sh_aligned``) as ``dars eval`` reports it;
* ``best_sh``: under the global SH light that fits the photos best given the true albedo (per channel, least squares
  of ``π · radiance ≈ albedo · E(n; L)`` over the material pixels, then a descent on this MAE itself from the better
  of that fit and the true light, :func:`best_global_sh`): what a perfect light estimate of this model could give.
  A search, not a proof, so the best MAE may lie a little lower;
* ``true_sh_damped``: under the true light with its bands 1 and 2 scaled by 0.75, 0.5 and 0.25 (its level kept): the
  same light made less directional, as a room's interreflections make the light that reaches its walls and floor;
* the same two on the diffuse pixels alone (``diffuse_*``: metallic < 0.1 and roughness ≥ 0.5, where a Lambertian
  term is the whole story), and ``best_sh``'s MAE per ground-truth class.

Where ``best_sh`` is above a target, no light estimate meets it with a global SH light: the rest is light that
varies across the room (spots on the art, the floor far from the laylights, shadows), which only the per-point light
residual (or the albedo) can take.

Usage (galleries rendered by ``samples/galleries.py`` or the bundled sample; by default the cached validation set,
else the sample)::

    python bench/bench_albedo_bound.py [GALLERY ...] [--split test] [--out bench/out/albedo_bound]

Writes ``bench_albedo_bound.json`` under ``--out``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

CLASSES = ("painting", "frame", "display", "base", "wall", "floor", "other")
DAMPING = (0.75, 0.5, 0.25)
"""Factors on the true light's bands 1 and 2 for ``true_sh_damped`` (a less directional light, band 0 kept)."""


def damp_sh(sh: torch.Tensor, d: float) -> torch.Tensor:
    """float [9, 3]: ``sh`` with its bands 1 and 2 (the light's direction) scaled by ``d``, band 0 (its level) kept."""
    out = sh.clone()
    out[1:] = out[1:] * d
    return out


def _irradiance_design(normals: torch.Tensor) -> torch.Tensor:
    """float64 [M, 9]: ``E(n; L)_c = design @ L[:, c]`` (:func:`toolkit.sh.irradiance_sh` as a linear map of L)."""
    from toolkit.sh import SH_BAND_OF_K, SH_IRRADIANCE_BANDS, sh_basis

    bands = torch.tensor([SH_IRRADIANCE_BANDS[b] for b in SH_BAND_OF_K], dtype=torch.float64)
    return sh_basis(normals.double()) * bands


def implied_albedo(radiance: torch.Tensor, normals: torch.Tensor, sh: torch.Tensor) -> torch.Tensor:
    """float [M, 3]: ``π · radiance / E(n; sh)`` clamped to [0, 1] (E floored at 1e-4)."""
    from toolkit.sh import irradiance_sh

    e = irradiance_sh(sh.to(radiance), normals.to(radiance)).clamp_min(1e-4)
    return (math.pi * radiance / e).clamp(0.0, 1.0)


def best_global_sh(radiance: torch.Tensor, albedo: torch.Tensor, normals: torch.Tensor, steps: int = 300,
                   starts: tuple[torch.Tensor, ...] = ()) -> torch.Tensor:
    """float [9, 3]: the global SH light whose implied albedo has the lowest MAE that we find.

    Per channel the least-squares L of ``π · radiance ≈ albedo · E(n; L)``, then ``steps`` of Adam on the MAE of
    :func:`implied_albedo` itself from the best of that fit and ``starts`` (e.g. the scene's own light). A search,
    not a proof: the true optimum may lie a little lower."""
    if radiance.shape[0] < 9:
        raise ValueError(f"{radiance.shape[0]} pixels cannot fix the 9 SH coefficients of a channel")
    y = _irradiance_design(normals)
    cols = []
    for c in range(3):
        m = y * albedo[:, c:c + 1].double()
        cols.append(torch.linalg.lstsq(m, math.pi * radiance[:, c:c + 1].double()).solution[:, 0])
    mae = lambda L: (implied_albedo(radiance, normals, L) - albedo).abs().mean()  # noqa: E731
    cands = [torch.stack(cols, 1).float(), *[s.float() for s in starts]]
    best = min(cands, key=lambda L: float(mae(L)))
    if steps <= 0:
        return best
    L = best.clone().requires_grad_(True)
    opt = torch.optim.Adam([L], lr=0.01 * float(best[0].abs().mean()) + 1e-4)
    found, found_v = best, float(mae(best))
    for _ in range(steps):
        opt.zero_grad()
        v = mae(L)
        v.backward()
        if v.item() < found_v:
            found, found_v = L.detach().clone(), v.item()
        opt.step()
    return found


def _aligned_mae(pred: torch.Tensor, target: torch.Tensor) -> float:
    from toolkit.metrics import albedo_mae_aligned

    return float(albedo_mae_aligned(pred.T[..., None], target.T[..., None], torch.ones(pred.shape[0], 1, dtype=torch.bool))[0])


def albedo_bound(radiance: torch.Tensor, albedo: torch.Tensor, normals: torch.Tensor, labels: torch.Tensor,
                 sh: torch.Tensor | None, diffuse: torch.Tensor | None = None) -> dict:
    """The bound's figures on the masked pixels of a split (see the module docstring).

    Args:
        radiance, albedo: float [M, 3] linear radiance and true albedo.
        normals: float [M, 3] unit true normals.
        labels: int [M] true class ids (0-6).
        sh: float [9, 3] the scene's own SH light, or None (then ``true_sh*`` are None).
        diffuse: bool [M] the diffuse pixels, or None (all).

    Returns:
        dict: ``pixels``, ``true_sh``, ``true_sh_aligned``, ``true_sh_damped`` ({d: MAE} under :func:`damp_sh`),
        ``best_sh``, ``diffuse_pixels``, ``diffuse_true_sh``,
        ``diffuse_best_sh``, ``best_sh_by_class`` ({class: MAE}), ``best_sh_share_by_class`` ({class: share of the
        pooled error}), ``best_sh_level_by_class`` ({class: mean implied over mean true albedo}), ``best_sh_coeffs``.

    Raises:
        ValueError: fewer than 9 pixels.
    """
    diffuse = torch.ones(radiance.shape[0], dtype=torch.bool) if diffuse is None else diffuse
    best = best_global_sh(radiance, albedo, normals, starts=() if sh is None else (sh,))
    a_best = implied_albedo(radiance, normals, best)
    err_best = (a_best - albedo).abs().mean(-1)
    out = {"pixels": int(radiance.shape[0]), "true_sh": None, "true_sh_aligned": None, "true_sh_damped": None,
           "best_sh": float(err_best.mean()), "diffuse_pixels": int(diffuse.sum()), "diffuse_true_sh": None,
           "diffuse_best_sh": None, "best_sh_coeffs": best.tolist()}
    if sh is not None:
        a_true = implied_albedo(radiance, normals, sh)
        err_true = (a_true - albedo).abs().mean(-1)
        out.update(true_sh=float(err_true.mean()), true_sh_aligned=_aligned_mae(a_true, albedo))
        out["true_sh_damped"] = {str(d): float((implied_albedo(radiance, normals, damp_sh(sh, d)) - albedo).abs().mean())
                                 for d in DAMPING}
        if diffuse.sum() >= 9:
            out["diffuse_true_sh"] = float(err_true[diffuse].mean())
    if diffuse.sum() >= 9:
        d_best = best_global_sh(radiance[diffuse], albedo[diffuse], normals[diffuse], starts=(best,))
        out["diffuse_best_sh"] = float((implied_albedo(radiance[diffuse], normals[diffuse], d_best)
                                        - albedo[diffuse]).abs().mean())
    total = float(err_best.sum()) or 1.0
    out["best_sh_by_class"], out["best_sh_share_by_class"], out["best_sh_level_by_class"] = {}, {}, {}
    for c, name in enumerate(CLASSES):
        m = labels == c
        if int(m.sum()) == 0:
            continue
        out["best_sh_by_class"][name] = float(err_best[m].mean())
        out["best_sh_share_by_class"][name] = float(err_best[m].sum()) / total
        out["best_sh_level_by_class"][name] = float(a_best[m].mean() / albedo[m].mean().clamp_min(1e-6))
    return out


def gather(scene_dir: Path, split: str = "test") -> dict:
    """The material-mask pixels of every view of ``split``: radiance, albedo, normals, labels and the diffuse mask."""
    from toolkit.metrics import material_mask
    from toolkit.scene import load_scene

    sc = load_scene(scene_dir, split)
    need = ("radiance", "albedo", "normal", "semantic")
    missing = [k for k in need if any(k not in f.extras for f in sc.frames)]
    if missing:
        raise SystemExit(f"{scene_dir} split '{split}': frames lack ground-truth {missing} maps; this benchmark needs "
                         f"a rendered gallery (samples/galleries.py) or the bundled sample")
    rows = {k: [] for k in ("radiance", "albedo", "normal", "labels", "diffuse")}
    for i in range(len(sc)):
        lab = sc.load_extra(i, "semantic")
        n = sc.load_extra(i, "normal").permute(1, 2, 0)
        mask = material_mask(lab) & (n.norm(dim=-1) > 0.5)
        rough = sc.load_extra(i, "roughness") if "roughness" in sc.frames[i].extras else torch.ones_like(lab, dtype=torch.float32)
        metal = sc.load_extra(i, "metallic") if "metallic" in sc.frames[i].extras else torch.zeros_like(lab, dtype=torch.float32)
        rows["radiance"].append(sc.load_extra(i, "radiance").permute(1, 2, 0)[mask])
        rows["albedo"].append(sc.load_extra(i, "albedo").permute(1, 2, 0)[mask])
        rows["normal"].append(torch.nn.functional.normalize(n[mask], dim=-1))
        rows["labels"].append(lab[mask])
        rows["diffuse"].append(((metal < 0.1) & (rough >= 0.5))[mask])
    out = {k: torch.cat(v) for k, v in rows.items()}
    out["sh"] = None if sc.sh is None else sc.sh.float()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("galleries", nargs="*", type=Path,
                    help="gallery folders (default: every cached validation gallery, ~/.cache/dars/galleries/validation, "
                         "else the bundled sample)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "out" / "albedo_bound")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    dirs = args.galleries
    if not dirs:
        from samples.galleries import cache_root

        dirs = sorted((cache_root() / "validation").glob("seed_*"))
        if not dirs:
            print("no validation gallery cached (python samples/galleries.py --profile validation --seeds all renders "
                  "them): the bundled sample alone")
            dirs = [REPO / "samples" / "gallery"]
    t0 = time.time()
    res = {}
    print(f"{'gallery':<16} {'pixels':>7} | {'true SH':>7} {'aligned':>7} | {'best SH':>7} | diffuse: true  best | "
          "best SH per class (MAE, share of the error)")
    for d in dirs:
        px = gather(d, args.split)
        r = albedo_bound(px["radiance"], px["albedo"], px["normal"], px["labels"], px["sh"], px["diffuse"])
        res[str(d)] = r
        f = lambda v: "   -   " if v is None else f"{v:7.3f}"  # noqa: E731
        cls = ", ".join(f"{k} {v:.2f} ({100 * r['best_sh_share_by_class'][k]:.0f} %)" for k, v in r["best_sh_by_class"].items())
        print(f"{d.name:<16} {r['pixels']:>7} | {f(r['true_sh'])} {f(r['true_sh_aligned'])} | {f(r['best_sh'])} | "
              f"{f(r['diffuse_true_sh'])} {f(r['diffuse_best_sh'])} | {cls}", flush=True)
        if r["true_sh_damped"]:
            print(f"{'':<16} true light, bands 1-2 x d: " + ", ".join(f"d={d} {v:.3f}" for d, v in r["true_sh_damped"].items()))
    keys = ("true_sh", "true_sh_aligned", *[f"true_sh_damped_{d}" for d in DAMPING], "best_sh", "diffuse_true_sh",
            "diffuse_best_sh")
    flat = [dict(r, **{f"true_sh_damped_{d}": (r["true_sh_damped"] or {}).get(str(d)) for d in DAMPING}) for r in res.values()]
    summary = {}
    for k in keys:
        vals = [r[k] for r in flat if r[k] is not None]
        if vals:
            summary[k] = {"mean": sum(vals) / len(vals), "worst": max(vals), "n": len(vals)}
    print("mean / worst over the galleries: " + "; ".join(f"{k} {v['mean']:.3f} / {v['worst']:.3f}" for k, v in summary.items()))
    args.out.mkdir(parents=True, exist_ok=True)
    from toolkit.io import write_json

    path = args.out / "bench_albedo_bound.json"
    write_json(path, {"command": "bench/bench_albedo_bound.py " + " ".join(sys.argv[1:] if argv is None else argv),
                      "split": args.split, "galleries": res, "summary": summary, "seconds": round(time.time() - t0, 1),
                      "ground_truth": "scoring only: radiance, normals, albedo and labels of the split"})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
