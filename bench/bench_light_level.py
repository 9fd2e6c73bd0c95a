"""How well is the *level* of the room's light known from photos? Band 0 of the SH light (its brightness and colour)
sets the albedo's scale: photos fix albedo and light only up to a common factor per channel, so a light estimated
2x too dim gives an albedo 2x too bright. This benchmark scores three estimates of band 0 against the ground truth on
rendered galleries, per gallery and as mean / median / worst of ``|log(estimate / truth)|`` (mean over channels;
the network's signed ratio too, which tells a level that is low everywhere from one that scatters):

* ``net``: the shipped light network (``toolkit/weights/lightnet_small.pt``), mean over the training views, as
  ``dars priors light`` computes it;
* ``grey``: the trainer's grey-ambient start (an albedo-0.5 surface at the photos' mean linear brightness);
* ``max(x, bound_p)``: either, raised to a physical lower bound — a diffuse surface of albedo <= 1 under a light of
  level ``L00 * Y00`` reflects at most that radiance, so ``L00 >= q_p / Y00`` with ``q_p`` the p-quantile of the
  photos' linear pixel radiance (per channel). Speculars, lamps and sky break the bound for high p.

It also prints the whole light's Env-light L2 (eq. 36) per gallery against grey ambient, zero light and the training
mean, per image, where the network's squared error lies (band 0, the vertical and the horizontal components of bands
1-2) and, with ``--yaws``, the figure with each gallery's world turned about +z (a capture's yaw is arbitrary).

Usage (1 thread, a few seconds per gallery; pass galleries the light network was not trained on — see the card
``toolkit/weights/lightnet_small.json``)::

    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_light_level.py --yaws 0,37,90,180,270   # the validation galleries
    git show b1c55e2:toolkit/weights/lightnet_small.pt > /tmp/lightnet_world.pt             # the old world-frame net
    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_light_level.py --yaws 0,37,90,180,270 --weights /tmp/lightnet_world.pt

    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_light_level.py ~/.cache/dars/galleries/prior/seed_{21..35} \\
        ~/.cache/dars/galleries/prior/seed_{102..116} ~/.cache/dars/galleries/prior/seed_{11,83,85,88,89,92,95,101}
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from toolkit.io import linear_to_srgb, srgb_to_linear  # noqa: E402
from toolkit.lightnet import aggregate_sh, load_lightnet, predict_sh  # noqa: E402
from toolkit.metrics import env_light_l2  # noqa: E402
from toolkit.scene import load_scene  # noqa: E402
from toolkit.sh import SH_C0, rotate_sh, rotation_z  # noqa: E402
from toolkit.train.data import grey_ambient_sh  # noqa: E402

QUANTILES = (0.9, 0.95, 0.98, 0.99)
VERTICAL = [2, 6]  # SH indices that a turn about +z leaves alone: z (band 1) and 3z^2 - 1 (band 2)
HORIZONTAL = [1, 3, 4, 5, 7, 8]  # the rest of bands 1 and 2: they turn with the world's yaw


def gallery_levels(path: str, model, yaws: list[float] = ()) -> dict | None:
    """Band 0 (float [3] each) of the truth, the network, the grey start and the bounds of one gallery's training views;
    the whole light's Env-light L2 per scene and per image, where its squared error lies, and the scene figure with the
    world turned about +z by each of ``yaws`` (degrees; cameras and true SH together)."""
    sc = load_scene(path, "train")
    if sc.sh is None:
        print(f"[light-level] {path}: no ground-truth 'sh', skipped")
        return None
    imgs = torch.stack([sc.load_image(i) for i in range(len(sc))]).float()
    srgb = imgs if sc.srgb else linear_to_srgb(imgs.clamp(0, 1))  # the network reads 8-bit-style sRGB
    lin = srgb_to_linear(srgb)
    pix = lin.permute(1, 0, 2, 3).reshape(3, -1)
    pix = pix[:, :: max(1, pix.shape[1] // 2_000_000)]  # torch.quantile's input limit
    per_image = predict_sh(model, srgb, c2w=sc.cameras.c2w)
    net_sh = aggregate_sh(per_image, "mean")
    grey_sh = grey_ambient_sh(float(lin.mean()))
    truth = sc.sh.float()
    row = {"gallery": path, "truth": truth[0].numpy(), "net": net_sh[0].numpy(), "grey": grey_sh[0].numpy()}
    # the whole light (27 coefficients, eq. 36), per scene as `dars priors light` gives it, against the baselines
    whole = {"net": net_sh, "grey": grey_sh, "zero": torch.zeros_like(truth)}
    if model.meta.get("train_mean_sh") is not None:
        whole["train_mean"] = torch.tensor(model.meta["train_mean_sh"]).float()
    row["env_l2"] = {k: float(env_light_l2(v.float(), truth)) for k, v in whole.items()}
    row["env_l2_per_image"] = float(env_light_l2(per_image.float(), truth[None].expand_as(per_image)).mean())
    err2 = (net_sh.float() - truth) ** 2
    row["err2"] = {"band0": float(err2[0].sum()), "vertical": float(err2[VERTICAL].sum()),
                   "horizontal": float(err2[HORIZONTAL].sum())}
    oracle = {}
    for name, idx in (("band0", [0]), ("vertical", VERTICAL), ("horizontal", HORIZONTAL)):
        o = net_sh.float().clone()
        o[idx] = truth[idx]
        oracle[name] = float(env_light_l2(o, truth))
    row["oracle_env_l2"] = oracle  # the network's light with these components replaced by the truth
    row["yaw_env_l2"] = {}
    for yaw in yaws:
        rot = rotation_z(float(yaw)).float()
        c2w = sc.cameras.c2w.clone().float()
        c2w[:, :3, :4] = rot @ c2w[:, :3, :4]
        turned = aggregate_sh(predict_sh(model, srgb, c2w=c2w), "mean")
        row["yaw_env_l2"][str(yaw)] = float(env_light_l2(turned.float(), rotate_sh(truth, rot)))
    for p in QUANTILES:
        row[f"bound{p}"] = (torch.quantile(pix, p, dim=1) / SH_C0).numpy()
    return row


def _log_ratios(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per channel log(estimate / truth), both floored at 1e-3."""
    return np.log(np.maximum(est, 1e-3) / np.maximum(truth, 1e-3))


def log_error(est: np.ndarray, truth: np.ndarray) -> float:
    return float(np.abs(_log_ratios(est, truth)).mean())


def signed_log_ratio(est: np.ndarray, truth: np.ndarray) -> float:
    """mean over channels of log(estimate / truth): < 0 where the estimate is dimmer than the truth."""
    return float(_log_ratios(est, truth).mean())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("galleries", nargs="*", help="rendered gallery folders (transforms_train.json with 'sh'); "
                    "default: the cached validation galleries (python samples/galleries.py --profile validation)")
    ap.add_argument("--weights", default=None, help="light network weights (default: the shipped ones)")
    ap.add_argument("--yaws", default="", metavar="DEG,DEG",
                    help="also score each gallery with its world turned about +z by these angles (cameras and true SH "
                         "together, as a capture's arbitrary frame): e.g. 0,37,90,180,270")
    ap.add_argument("--json", default=str(ROOT / "bench" / "out" / "light_level.json"))
    args = ap.parse_args()
    yaws = [float(v) for v in args.yaws.split(",") if v.strip()]
    if not args.galleries:
        sys.path.insert(0, str(ROOT / "samples"))
        from galleries import cache_root  # where samples/galleries.py renders ($DARS_CACHE or ~/.cache/dars)

        cache = cache_root() / "validation"
        args.galleries = sorted(str(p) for p in cache.glob("seed_*") if p.is_dir())
        if not args.galleries:
            print(f"[light-level] skipped: no gallery given and none rendered in {cache} "
                  "(python samples/galleries.py --profile validation --seeds 1000000)")
            return 0
    torch.set_num_threads(1)
    model = load_lightnet(args.weights)
    rows = [r for r in (gallery_levels(g, model, yaws) for g in args.galleries) if r is not None]
    if not rows:
        print("[light-level] no gallery with ground-truth SH")
        return 1
    cands = {"net": lambda r: r["net"], "grey": lambda r: r["grey"]}
    for p in QUANTILES:
        cands[f"max(net, bound{p})"] = (lambda q: lambda r: np.maximum(r["net"], r[f"bound{q}"]))(p)
        cands[f"max(grey, bound{p})"] = (lambda q: lambda r: np.maximum(r["grey"], r[f"bound{q}"]))(p)
    print(f"{'gallery':40s} {'truth':>6s} {'net':>6s} {'grey':>6s}  (band 0, mean over channels)")
    for r in rows:
        print(f"{Path(r['gallery']).name:40s} {r['truth'].mean():6.2f} {r['net'].mean():6.2f} {r['grey'].mean():6.2f}")
    summary = {}
    print(f"\n{'estimate of band 0':24s} |log(estimate/truth)|: mean  median  worst   (n = {len(rows)} galleries)")
    for k, f in cands.items():
        e = np.array([log_error(f(r), r["truth"]) for r in rows])
        summary[k] = {"mean": float(e.mean()), "median": float(np.median(e)), "worst": float(e.max())}
        print(f"{k:24s} {e.mean():27.3f} {np.median(e):7.3f} {e.max():6.3f}")
    ref = summary["grey"]["mean"]
    print(f"ratio net / grey (mean): {summary['net']['mean'] / ref:.3f}")
    # the signed error: a level that is low everywhere (a bias) reads the same in |log| as one that scatters
    bias = np.array([signed_log_ratio(r["net"], r["truth"]) for r in rows])
    summary["net_log_ratio"] = {"mean": float(bias.mean()), "median": float(np.median(bias)),
                                "below_truth": int((bias < 0).sum())}
    print(f"net band 0 / truth: exp(mean log) {np.exp(bias.mean()):.2f}x, exp(median log) "
          f"{np.exp(np.median(bias)):.2f}x; below the truth on {int((bias < 0).sum())} of {len(rows)} galleries")
    keys = list(rows[0]["env_l2"])
    print(f"\n{'whole light, Env-light L2 (eq. 36)':40s} " + " ".join(f"{k:>10s}" for k in keys))
    for r in rows:
        print(f"{Path(r['gallery']).name:40s} " + " ".join(f"{r['env_l2'][k]:10.2f}" for k in keys))
    env = {k: np.array([r["env_l2"][k] for r in rows]) for k in keys}
    print(f"{'mean':40s} " + " ".join(f"{env[k].mean():10.2f}" for k in keys))
    print(f"{'worst':40s} " + " ".join(f"{env[k].max():10.2f}" for k in keys))
    print(f"net / grey (mean of per-gallery ratios): {(env['net'] / env['grey']).mean():.3f}; galleries where the net "
          f"is worse than no light: {int((env['net'] > env['zero']).sum())} of {len(rows)}")
    per_img = np.array([r["env_l2_per_image"] for r in rows])
    print(f"net per image (mean over a gallery's photos of each photo's own estimate): mean {per_img.mean():.2f}, "
          f"worst {per_img.max():.2f}")
    summary["env_l2"] = {k: {"mean": float(v.mean()), "worst": float(v.max())} for k, v in env.items()}
    summary["env_l2"]["net_per_image"] = {"mean": float(per_img.mean()), "worst": float(per_img.max())}
    parts = {k: sum(r["err2"][k] for r in rows) for k in rows[0]["err2"]}
    total = sum(parts.values())
    oracle = {k: float(np.mean([r["oracle_env_l2"][k] for r in rows])) for k in rows[0]["oracle_env_l2"]}
    print("where the net's error lies (squared error over the galleries): "
          + ", ".join(f"{k} {v / total:.0%}" for k, v in parts.items())
          + "; with those components taken from the truth, mean Env-light L2 / grey's: "
          + ", ".join(f"{k} {v / env['grey'].mean():.3f}" for k, v in oracle.items()))
    summary["error_share"] = {k: v / total for k, v in parts.items()}
    summary["oracle_over_grey"] = {k: v / float(env["grey"].mean()) for k, v in oracle.items()}
    if yaws:
        y = np.array([[r["yaw_env_l2"][str(a)] for a in yaws] for r in rows])  # [galleries, yaws]
        print(f"\n{'net, world turned about +z by':40s} " + " ".join(f"{a:9.0f}°" for a in yaws) + "      range")
        for r, v in zip(rows, y):
            print(f"{Path(r['gallery']).name:40s} " + " ".join(f"{x:10.2f}" for x in v) + f" {v.max() - v.min():10.2f}")
        print(f"{'mean':40s} " + " ".join(f"{x:10.2f}" for x in y.mean(0)))
        print(f"mean over yaws {y.mean():.3f}, the worst yaw's mean {y.mean(0).max():.3f}, widest range in one gallery "
              f"{(y.max(1) - y.min(1)).max():.2f}")
        summary["yaws"] = {"yaws": yaws, "mean_per_yaw": y.mean(0).tolist(), "mean": float(y.mean()),
                           "worst_yaw_mean": float(y.mean(0).max()), "widest_range": float((y.max(1) - y.min(1)).max())}
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = {"galleries": [r["gallery"] for r in rows], "summary": summary,
           "per_gallery": [{k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in r.items()} for r in rows]}
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(doc, indent=1))
    tmp.replace(out)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
