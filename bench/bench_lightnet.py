"""Train the light estimation network on rendered lightings and report the held-out Env-light L2 (eq. 36).

Prints the network's error on **held-out lightings** (never seen in training: a whole probe map and unseen random
skies) next to two baselines — (a) the training-set mean SH, (b) the SH of each image's own mean colour — plus the
trainer's grey-ambient default, the ratios, a per-source breakdown, and the same figures on the bundled sample
(``samples/gallery``, whose lighting — the ``pisa`` probe — is held out by default). ``--save FILE`` writes the
weights and ``FILE`` with ``.json``: the commands and every figure.

Usage (1 thread; the data set is cached outside the repo)::

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 OMP_NUM_THREADS=1 \\
    .venv/bin/python samples/render_lightings.py --seed 0                # ~2 min -> ~/.cache/dars/lightnet/...
    .venv/bin/python samples/render_lightings.py --seed 1 --rotations-per-probe 0 --train-skies 0 --mixtures 0 \
        --suns 0 --out ~/.cache/dars/lightnet/gallery_heldout_s1.npz      # a second, untouched held-out set
    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_lightnet.py --arch small --save /tmp/lightnet_room.pt \
        --eval-data ~/.cache/dars/lightnet/gallery_heldout_s1.npz
    # the shipped weights (heading frame): 300 procedural galleries (prior and light profiles), the pisa probe and
    # four validation galleries held out; --mix-data reads the render_lightings.py --seed 0 set above
    .venv/bin/python samples/galleries.py --profile prior --seeds 0-35,81-108,200-231
    .venv/bin/python samples/galleries.py --profile light --seeds 500-699
    V=~/.cache/dars/galleries/validation
    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_lightnet.py --galleries ~/.cache/dars/galleries/prior \
        ~/.cache/dars/galleries/light --seeds 0-35,81-108,200-231,500-699 --heldout-galleries $V/seed_1000000 \
        $V/seed_1000001 $V/seed_1000002 $V/seed_1000003 --holdout-probes pisa --steps 3000 --weight-decay 1e-3 \
        --mix-data --frame heading --hflip --seed 0 --save toolkit/weights/lightnet_small.pt
    # the paper's network (hours on one CPU core; minutes on a GPU):
    .venv/bin/python bench/bench_lightnet.py --arch resnet34 --steps 8000 --save /tmp/lightnet_resnet34.pt
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import asdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
DEFAULT_DATA = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "dars" / "lightnet" / "gallery_lightings_s0.npz"


def evaluate_on_scene(model, scene_path: Path, train_mean_sh) -> dict | None:
    """Env-light L2 of the mean prediction over each split of a scene with GT SH (None without the scene)."""
    import torch

    from toolkit.io import srgb_to_linear
    from toolkit.lightnet import aggregate_sh, mean_colour_sh, predict_sh
    from toolkit.train import grey_ambient_sh
    from toolkit.metrics import env_light_l2
    from toolkit.scene import list_splits, load_scene

    if not (scene_path / "transforms_train.json").is_file():
        return None
    out = {}
    for split in [s for s in ("train", "test") if s in list_splits(scene_path)]:
        sc = load_scene(scene_path, split)
        if sc.sh is None:
            return None
        imgs = torch.stack([sc.load_image(i) for i in range(len(sc))])
        per = predict_sh(model, imgs, c2w=sc.cameras.c2w)
        gt = sc.sh.float()
        out[split] = {
            "views": len(sc),
            "network_mean": float(env_light_l2(aggregate_sh(per, "mean"), gt)),
            "network_median": float(env_light_l2(aggregate_sh(per, "median"), gt)),
            "network_per_image": float(env_light_l2(per, gt[None].expand_as(per)).mean()),
            "train_mean_sh": float(env_light_l2(train_mean_sh.float(), gt)),
            "mean_colour": float(env_light_l2(aggregate_sh(mean_colour_sh(imgs)), gt)),
            "grey_ambient": float(env_light_l2(grey_ambient_sh(float(srgb_to_linear(imgs).mean())), gt)),
            "zero_light": float(gt.norm()),
        }
    return out


def gallery_source_summary(per_source: dict) -> dict | None:
    """Equal-weight mean over the held-out gallery sources (``room/...`` views of --mix-data left out) of the
    network's and the baselines' Env-light L2, the network / grey-ambient ratio and whether the network beats zero
    light on every source (the issue's targets: all true, and ratio <= 0.7)."""
    src = {k: v for k, v in per_source.items() if not k.startswith("room/")}
    if not src:
        return None
    keys = ("network", "network_per_lighting", "zero_light", "grey_ambient", "mean_colour", "train_mean_sh")
    out = {k: sum(v[k] for v in src.values()) / len(src) for k in keys}
    out["sources"] = sorted(src)
    out["network_over_grey"] = out["network"] / out["grey_ambient"]
    out["beats_zero_on_every_source"] = all(v["network"] < v["zero_light"] for v in src.values())
    return out


def _with_seeds(dirs: list[Path], spec: str | None) -> list[Path]:
    """The gallery folders (``seed_N``) whose seed is in ``spec`` (``"0-35,81"``; None: all of them)."""
    if not spec:
        return dirs
    want = set()
    for part in spec.split(","):
        a, _, b = part.partition("-")
        want |= set(range(int(a), int(b or a) + 1))
    return [d for d in dirs if d.name[5:].isdigit() and int(d.name[5:]) in want]


def _trained_seeds(weights: Path) -> set[int] | None:
    """The gallery seeds a network's card (``FILE.json`` beside ``FILE.pt``) lists as trained on, or None (no card)."""
    card = weights.with_suffix(".json")
    if not card.is_file():
        return None
    gal = (json.loads(card.read_text()).get("galleries") or {})
    return {int(s) for seeds in (gal.get("train_seeds_by_probe") or {}).values() for s in seeds}


def _score_only(args) -> int:
    """``--score-only``: Env-light L2 of a trained network on galleries it was not trained on, per source and per
    gallery, with the baselines, the network / grey-ambient ratio and the galleries where it is worse than zero light."""
    import torch

    torch.set_num_threads(args.threads)
    from toolkit._checks import DarsError
    from toolkit.lightnet import (DEFAULT_WEIGHTS, LightDataset, evaluate_lightnet, gallery_dirs,
                                  light_dataset_from_galleries, load_lightnet)

    weights = Path(args.weights).expanduser() if args.weights else DEFAULT_WEIGHTS
    try:
        model = load_lightnet(weights)
        dirs = _with_seeds(gallery_dirs(*args.galleries), args.seeds)
        ds = light_dataset_from_galleries(dirs, model.cfg.input_size, progress=not args.json)
    except DarsError as e:
        print(f"bench_lightnet: error: {e}", file=sys.stderr)
        return 2
    trained = _trained_seeds(weights)
    info = ds.meta["galleries"]
    seen = [i for i, g in enumerate(info) if trained is not None and g["seed"] is not None and int(g["seed"]) in trained]
    keep = torch.tensor([int(l) not in seen for l in ds.lighting.tolist()])
    if not bool(keep.any()):
        print("bench_lightnet: error: every gallery given was in the weights' training set (its card's "
              "train_seeds_by_probe); render unseen ones with samples/galleries.py --seeds S", file=sys.stderr)
        return 2
    idx = torch.nonzero(keep).flatten()
    ds = LightDataset(ds.radiance[idx], ds.sh[idx], ds.lighting[idx], torch.ones(len(idx), dtype=torch.bool),
                      ds.sources, ds.meta, ds.heading[idx])
    train_mean = model.meta.get("train_mean_sh")
    train_mean = torch.zeros(9, 3) if train_mean is None else torch.as_tensor(train_mean, dtype=torch.float32)
    ev = evaluate_lightnet(model, ds, train_mean)
    per_gallery = [{"gallery": info[r["lighting"]]["path"], "seed": info[r["lighting"]]["seed"],
                    "profile": info[r["lighting"]]["profile"], "probe": info[r["lighting"]]["probe"], "views": r["images"],
                    **{k: r[k] for k in ("network", "grey_ambient", "zero_light", "true_over_network_level",
                                         "network_true_level")}} for r in ev.per_lighting]
    summary = gallery_source_summary(ev.per_source)
    worse = [r for r in per_gallery if r["network"] > r["zero_light"]]
    figures = {"command": "bench/bench_lightnet.py " + " ".join(sys.argv[1:]), "weights": str(weights),
               "galleries": len(per_gallery), "skipped_trained_on": [info[i]["path"] for i in seen],
               "card": None if trained is None else str(weights.with_suffix(".json")),
               "heldout": ev.to_json(), "sources": summary, "per_gallery": per_gallery,
               "worse_than_zero_light": [r["gallery"] for r in worse],
               "network_over_grey_per_gallery_mean": sum(r["network"] for r in per_gallery) / sum(r["grey_ambient"] for r in per_gallery),
               "level": _level_summary(per_gallery),
               "env_light_l2": "eq. 36: ||pred - gt||_2 over the 27 coefficients; per source: mean over images "
                               "(network: per image); per gallery: the mean prediction over its views, as dars priors light"}
    if args.json:
        sys.stdout.write(json.dumps(figures, indent=2) + "\n")
        return 0
    print(f"weights {weights}: {len(per_gallery)} galleries ({ev.images} views) scored"
          + (f", {len(seen)} skipped (in the card's training seeds)" if seen else "")
          + ("" if trained is not None else " (no card beside the weights: cannot check what they were trained on)"))
    print(f"  {'source':<16}{'img':>5}{'rooms':>6}{'net':>8}{'net/rm':>8}{'zero':>8}{'grey':>8}{'mean col':>9}{'net/grey':>9}")
    for s, d in ev.per_source.items():
        print(f"  {s:<16}{d['images']:>5}{d['lightings']:>6}{d['network']:8.3f}{d['network_per_lighting']:8.3f}"
              f"{d['zero_light']:8.3f}{d['grey_ambient']:8.3f}{d['mean_colour']:9.3f}{d['network'] / d['grey_ambient']:9.2f}")
    print(f"  equal weight over the {len(summary['sources'])} sources: net {summary['network']:.3f} (per room "
          f"{summary['network_per_lighting']:.3f}), grey {summary['grey_ambient']:.3f}, zero {summary['zero_light']:.3f}; "
          f"net/grey {summary['network_over_grey']:.2f}; better than zero light on every source: "
          f"{summary['beats_zero_on_every_source']}")
    print(f"  per room (the mean over its views, as dars priors light): net/grey {figures['network_over_grey_per_gallery_mean']:.2f}"
          f" on the means; worse than zero light on {len(worse)} of {len(per_gallery)} rooms"
          + (": " + ", ".join(f"{Path(r['gallery']).name} ({r['network']:.2f} > {r['zero_light']:.2f})" for r in worse) if worse else ""))
    lv = figures["level"]
    print(f"  the light's level (diagnosis; the truth is used here, never by the network): true / predicted level per room "
          f"10th-50th-90th percentile {lv['ratio_p10']:.2f} / {lv['ratio_p50']:.2f} / {lv['ratio_p90']:.2f}; told its true "
          f"level, the network would score net/grey {lv['network_true_level_over_grey']:.2f} on the means (the rest is "
          f"the light's direction and colour) instead of {figures['network_over_grey_per_gallery_mean']:.2f}")
    return 0


def _level_summary(per_gallery: list[dict]) -> dict:
    """How much of the per-room error is the light's level: percentiles of true / predicted level, and the ratio to
    grey ambient of the network's estimate scaled to the true level (an oracle for diagnosis, not an estimate)."""
    import numpy as np

    r = np.array([g["true_over_network_level"] for g in per_gallery])
    grey = sum(g["grey_ambient"] for g in per_gallery)
    return {"ratio_p10": float(np.percentile(r, 10)), "ratio_p50": float(np.median(r)), "ratio_p90": float(np.percentile(r, 90)),
            "network_true_level_over_grey": sum(g["network_true_level"] for g in per_gallery) / grey,
            "definition": "true_over_network_level: the truth's mean DC over the room estimate's; network_true_level: "
                          "the L2 of the room estimate times that ratio (uses the truth: a diagnosis, not a method)"}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(DEFAULT_DATA), help=f"data set from samples/render_lightings.py (default {DEFAULT_DATA})")
    ap.add_argument("--galleries", nargs="+", default=None, metavar="DIR",
                    help="train on rendered galleries instead of --data: profile folders (their seed_<N>/ with a "
                         "stamp.json) or gallery folders (samples/galleries.py)")
    ap.add_argument("--holdout-probes", nargs="*", default=["pisa"], metavar="PROBE",
                    help="with --galleries: galleries lit by these HDR probes are held out (default: pisa)")
    ap.add_argument("--heldout-galleries", nargs="*", default=[], metavar="DIR",
                    help="with --galleries: galleries held out as a whole (e.g. the validation profile's)")
    ap.add_argument("--max-galleries", type=int, default=None, metavar="N",
                    help="with --galleries: use only the first N training galleries (by seed) of the profile folders")
    ap.add_argument("--seeds", default=None, metavar="A-B,C",
                    help="with --galleries: only the profile galleries of these seeds (ranges and commas, e.g. 0-30,81-110)")
    ap.add_argument("--mix-data", action="store_true",
                    help="with --galleries: also train on --data (the sample room under many lightings)")
    ap.add_argument("--arch", default="small", choices=["small", "resnet18", "resnet34"])
    ap.add_argument("--steps", type=int, default=4000)
    ap.add_argument("--batch-size", type=int, default=32)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--weight-decay", type=float, default=0.0)
    ap.add_argument("--exposure-jitter", type=float, default=0.5)
    ap.add_argument("--shift-px", type=int, default=3)
    ap.add_argument("--loss", default="huber", choices=["l2", "huber"])
    ap.add_argument("--huber-delta", type=float, default=1.0)
    ap.add_argument("--output-range", default=None, choices=["absolute", "image"], help="default: the preset's (image)")
    ap.add_argument("--dc-max", type=float, default=None, help="upper end of L00 (default: the preset's)")
    ap.add_argument("--frame", default="world", choices=["world", "heading"],
                    help="answer in the world frame from the photo alone, or relative to each photo's heading, turned "
                         "into the world by its pose (toolkit.lightnet.LightNetConfig.frame)")
    ap.add_argument("--hflip", action="store_true", help="flip half the photos left-right, targets mirrored (--frame heading)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--eval-data", default=None, metavar="NPZ",
                    help="also evaluate on the held-out views of this data set (e.g. one generated with another --seed "
                         "and no training lightings: a clean test set that no design decision looked at)")
    ap.add_argument("--sample", default=str(REPO / "samples" / "gallery"), help="scene with GT SH to evaluate on too")
    ap.add_argument("--save", default=None, metavar="FILE.pt", help="write the weights here and the figures to FILE.json")
    ap.add_argument("--half", action="store_true", help="store the weights as float16")
    ap.add_argument("--json", action="store_true", help="print only the figures as JSON on stdout")
    ap.add_argument("--score-only", action="store_true",
                    help="train nothing: score --weights (default: the shipped network) on every gallery of --galleries, "
                         "per lighting source and per gallery, against zero light, grey ambient and the image mean colour; "
                         "galleries whose seed the weights' card lists as trained on are reported apart")
    ap.add_argument("--weights", default=None, metavar="FILE.pt", help="--score-only: the weights (default: shipped)")
    args = ap.parse_args(argv)

    import torch

    torch.set_num_threads(args.threads)
    from toolkit._checks import DarsError
    from toolkit.lightnet import (LightDataset, TrainLightNetConfig, concat_light_datasets, evaluate_lightnet,
                                  gallery_dirs, light_dataset_from_galleries, lightnet_config, load_light_dataset,
                                  save_lightnet, train_lightnet)

    if args.score_only:
        if not args.galleries:
            ap.error("--score-only needs --galleries DIR [DIR ...]")
        return _score_only(args)
    try:
        if args.galleries:
            dirs = gallery_dirs(*args.galleries)
            held = {Path(d).resolve() for d in args.heldout_galleries}
            dirs = _with_seeds([d for d in dirs if d.resolve() not in held], args.seeds)
            dirs = dirs[:args.max_galleries]
            ds = light_dataset_from_galleries(dirs, 64, tuple(args.holdout_probes), tuple(args.heldout_galleries),
                                              progress=not args.json)
            if args.mix_data:
                room = load_light_dataset(args.data)
                room = LightDataset(room.radiance, room.sh, room.lighting, room.test,
                                    tuple(f"room/{x}" for x in room.sources), room.meta, room.heading)
                ds = concat_light_datasets(ds, room)
        else:
            ds = load_light_dataset(args.data)
    except DarsError as e:
        print(f"bench_lightnet: error: {e}", file=sys.stderr)
        return 2
    train, test = ds.split("train"), ds.split("test")
    over = ({"output_range": args.output_range} if args.output_range else {}) | ({"dc_max": args.dc_max} if args.dc_max is not None else {})
    over["frame"] = args.frame
    cfg = TrainLightNetConfig(arch=lightnet_config(args.arch, **over), loss=args.loss, huber_delta=args.huber_delta, steps=args.steps, batch_size=args.batch_size, lr=args.lr, weight_decay=args.weight_decay,
                              exposure_jitter=args.exposure_jitter, shift_px=args.shift_px, hflip=args.hflip, seed=args.seed)
    t0 = time.time()
    model, hist = train_lightnet(ds, cfg)
    ev = evaluate_lightnet(model, test, hist.train_mean_sh)
    ev_train = evaluate_lightnet(model, train, hist.train_mean_sh)
    sample = evaluate_on_scene(model, Path(args.sample), hist.train_mean_sh)
    ev_extra = None
    if args.eval_data:
        extra = load_light_dataset(args.eval_data)
        ev_extra = evaluate_lightnet(model, extra.split("test"), hist.train_mean_sh)
    cmd = "bench/bench_lightnet.py " + " ".join(sys.argv[1:] if argv is None else argv)
    gal = ds.meta.get("galleries") or next((m.get("galleries") for m in ds.meta.get("parts", []) if m.get("galleries")), None)
    gal_fig = None if gal is None else {
        "roots": args.galleries, "galleries": len(gal),
        "render_command": "samples/galleries.py --profile P --seeds S per profile " + str(sorted({g["profile"] for g in gal})), "holdout_probes": args.holdout_probes,
        "heldout_galleries": args.heldout_galleries, "mix_data": args.data if args.mix_data else None,
        "train_seeds_by_probe": {p: sorted(g["seed"] for g in gal if g["probe"] == p and not g["heldout"])
                                 for p in sorted({g["probe"] for g in gal})},
        "train_galleries": sum(1 for g in gal if not g["heldout"]),
        "heldout_seeds_by_source": {s: sorted(g["seed"] for g in gal if g["source"] == s and g["heldout"])
                                    for s in sorted({g["source"] for g in gal if g["heldout"]})},
        "units": "radiance = the frames' linear .hdr (exposure baked into the light powers), area-averaged to 64 px; "
                 "sh = transforms 'sh' (same units: SH of light.hdr agrees within 2 %; PNG = sRGB(clip(hdr)) within 8-bit noise)"}
    figures = {
        "command": cmd,
        "galleries": gal_fig,
        "data": {"path": str(args.data) if not args.galleries or args.mix_data else None, "command": ds.meta.get("command"), "views": len(ds), "train_views": len(train),
                 "test_views": len(test), "train_lightings": int(train.lighting.unique().numel()),
                 "test_lightings": int(test.lighting.unique().numel()), "render_seconds": ds.meta.get("seconds"),
                 "size": ds.meta.get("size"), "spp": ds.meta.get("spp"), "holdout": ds.meta.get("plan", {}).get("holdout_probe") if not args.galleries else args.holdout_probes},
        "arch": asdict(model.cfg), "parameters": model.num_parameters(), "train_seconds": round(hist.seconds, 1),
        "train_config": {k: v for k, v in asdict(cfg).items() if k != "arch"},
        "final_loss": float(sum(hist.losses[-100:]) / max(len(hist.losses[-100:]), 1)),
        "heldout": ev.to_json(), "heldout_gallery_sources": gallery_source_summary(ev.per_source), "train": {k: getattr(ev_train, k) for k in ("network", "train_mean_sh", "mean_colour", "grey_ambient", "zero_light")},
        "sample": sample,
        "eval_data": None if ev_extra is None else {"path": str(args.eval_data), "command": extra.meta.get("command"),
                                                    **ev_extra.to_json()},
        "env_light_l2": "eq. 36: ||pred - gt||_2 over the 27 coefficients, mean over held-out images",
    }
    if args.save:
        path = Path(args.save)
        save_lightnet(path, model, {"training_command": cmd, "data_command": ds.meta.get("command"),
                                    "heldout_env_light_l2": ev.network, "half": args.half})
        figures["weights"] = {"path": str(path), "bytes": path.stat().st_size}
        from toolkit.io import write_json

        write_json(path.with_suffix(".json"), figures)
    if args.json:
        sys.stdout.write(json.dumps(figures, indent=2) + "\n")
        return 0
    print(f"data: {len(train)} train views ({figures['data']['train_lightings']} lightings), {len(test)} held-out views "
          f"({figures['data']['test_lightings']} lightings, held-out probe: {figures['data']['holdout']}), "
          f"{figures['data']['size']} px {figures['data']['spp']} spp, rendered in {figures['data']['render_seconds']} s")
    print(f"net: {args.arch}, {model.num_parameters() / 1e6:.3f} M parameters; trained {args.steps} steps in "
          f"{hist.seconds:.0f} s (final loss {figures['final_loss']:.4f})")
    print(f"\nEnv-light L2 on held-out lightings ({ev.images} images, {ev.lightings} lightings), lower is better:")
    rows = [("network (per image)", ev.network), ("network (mean over a lighting's views)", ev.network_per_lighting),
            ("baseline (a) training-set mean SH", ev.train_mean_sh), ("baseline (b) image mean colour", ev.mean_colour),
            ("trainer's grey ambient (2x (b))", ev.grey_ambient), ("zero light", ev.zero_light)]
    for name, v in rows:
        print(f"  {name:<42} {v:8.4f}   x{v / ev.network:5.2f} of the network's")
    print(f"  {'source':<16}{'img':>5}{'light':>6}{'net':>8}{'net/lt':>8}{'zero':>8}{'grey':>8}{'(b)':>8}{'(a)':>8}"
          f"{'net/grey':>9}")
    for s, d in ev.per_source.items():
        print(f"  {s:<16}{d['images']:>5}{d['lightings']:>6}{d['network']:8.3f}{d['network_per_lighting']:8.3f}"
              f"{d['zero_light']:8.3f}{d['grey_ambient']:8.3f}{d['mean_colour']:8.3f}{d['train_mean_sh']:8.3f}"
              f"{d['network'] / d['grey_ambient']:9.2f}")
    gs = figures["heldout_gallery_sources"]
    if gs and args.galleries:
        print(f"  mean over held-out gallery sources {gs['sources']}: net {gs['network']:.3f} (per lighting "
              f"{gs['network_per_lighting']:.3f}), zero {gs['zero_light']:.3f}, grey {gs['grey_ambient']:.3f}, "
              f"(b) {gs['mean_colour']:.3f}, (a) {gs['train_mean_sh']:.3f}; net/grey {gs['network_over_grey']:.2f}; "
              f"beats zero light on every source: {gs['beats_zero_on_every_source']}")
    print(f"  training views: net {ev_train.network:.4f}, (a) {ev_train.train_mean_sh:.4f}, (b) {ev_train.mean_colour:.4f}, "
          f"grey {ev_train.grey_ambient:.4f}, zero {ev_train.zero_light:.4f}")
    if ev_extra is not None:
        print(f"\nEnv-light L2 on the held-out lightings of {args.eval_data} ({ev_extra.images} images, "
              f"{ev_extra.lightings} lightings): network {ev_extra.network:.4f} (per lighting "
              f"{ev_extra.network_per_lighting:.4f}); (a) {ev_extra.train_mean_sh:.4f} "
              f"(x{ev_extra.train_mean_sh / ev_extra.network:.2f}); (b) {ev_extra.mean_colour:.4f} "
              f"(x{ev_extra.mean_colour / ev_extra.network:.2f}); grey ambient {ev_extra.grey_ambient:.4f}")
        print("  per source: " + "; ".join(f"{s} ({d['images']} img): net {d['network']:.3f}, (a) {d['train_mean_sh']:.3f}, "
                                           f"(b) {d['mean_colour']:.3f}" for s, d in ev_extra.per_source.items()))
    if sample:
        for split, d in sample.items():
            print(f"sample {args.sample} [{split}, {d['views']} views]: net mean {d['network_mean']:.4f}, median "
                  f"{d['network_median']:.4f}, per image {d['network_per_image']:.4f}; (a) {d['train_mean_sh']:.4f}, "
                  f"(b) {d['mean_colour']:.4f}, grey {d['grey_ambient']:.4f}, zero {d['zero_light']:.4f}")
    if args.save:
        print(f"wrote {figures['weights']['path']} ({figures['weights']['bytes'] / 1e6:.2f} MB) and "
              f"{Path(args.save).with_suffix('.json')}")
    print(f"total {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
