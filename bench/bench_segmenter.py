"""Train the shipped segmenter (7 SPEC classes + metal mask) on procedural galleries and score it on scenes it never saw.

Training data: the ``prior`` profile galleries (``python samples/galleries.py --profile prior --seeds 0-159``: rooms,
materials, objects, lighting and camera paths all drawn at random; 12 views of 160 px each). Photometric
augmentation stands in for real cameras: exposure (+-1.5 stops), white balance and contrast jitter, blur, sensor
noise, JPEG. The last ``--holdout`` prior seeds are kept out of training and scored; so are the validation galleries
(``--profile validation``, a different seed range that the prior profile refuses) and the bundled sample
(``samples/gallery``): **no evaluation scene is in the training set.** Scores: mIoU over the 7 classes (per class
too) and the IoU of the metal mask, on every frame of the scene's test split.

``--save FILE`` writes the weights and ``FILE`` with ``.json`` (the card: data, seeds, command, held-out scores).

Usage (2 threads; ~25 min on 2 CPU cores)::

    .venv/bin/python samples/galleries.py --profile prior --seeds 0-159
    .venv/bin/python samples/galleries.py --profile validation --seeds 1000000,1000001
    .venv/bin/python bench/bench_segmenter.py --save toolkit/weights/segmenter_small.pt
    # the shipped weights (2026-12-05): 203 prior galleries, the 16 the earlier network never saw held out to
    # compare on; 8000 steps (alone: not better than the earlier network), then 8000 more from those weights
    .venv/bin/python samples/galleries.py --profile prior --seeds 117-199,232-263
    .venv/bin/python bench/bench_segmenter.py --steps 8000 --holdout-seeds 109-116,224-231 --save /tmp/seg_203.pt
    .venv/bin/python bench/bench_segmenter.py --steps 8000 --holdout-seeds 109-116,224-231 --seed 1 \
        --init /tmp/seg_203.pt --save toolkit/weights/segmenter_small.pt
    # more rooms for training only (the light profile's 64 px galleries, resized; tried 2026-12-05, not better):
    .venv/bin/python bench/bench_segmenter.py --steps 8000 --extra-dir ~/.cache/dars/galleries/light --save /tmp/seg.pt
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "samples"))
from galleries import cache_root  # noqa: E402  (where samples/galleries.py renders: $DARS_CACHE or ~/.cache/dars)

CACHE = cache_root()


def _seed_of(d: Path) -> int:
    """The seed of a gallery folder ``seed_<N>``."""
    return int(d.name.split("_")[1])


def _gallery_dirs(root: Path) -> list[Path]:
    dirs = [d for d in root.glob("seed_*") if (d / "stamp.json").is_file()]
    return sorted(dirs, key=_seed_of)


def split_holdout(dirs: list[Path], holdout: int, holdout_seeds: str = "") -> tuple[list[Path], list[Path]]:
    """(training, held-out) galleries: the seeds of ``holdout_seeds`` (``A-B,C``) held out where given, else the
    last ``holdout``. A held-out seed that is not rendered is an error (the comparison it was asked for would
    silently shrink)."""
    from galleries import parse_seeds

    if not holdout_seeds:
        return dirs[:len(dirs) - holdout], dirs[len(dirs) - holdout:]
    want = set(parse_seeds(holdout_seeds, "prior"))
    missing = sorted(want - {_seed_of(d) for d in dirs})
    if missing:
        raise SystemExit(f"--holdout-seeds: prior galleries {seed_ranges(missing)} are not rendered in "
                         f"{dirs[0].parent if dirs else 'the prior directory'}; render them with "
                         f"`python samples/galleries.py --profile prior --seeds {seed_ranges(missing)}`")
    return [d for d in dirs if _seed_of(d) not in want], [d for d in dirs if _seed_of(d) in want]


def seed_ranges(seeds: list[int]) -> str:
    """Sorted seeds as ``A-B,C`` ranges (what ``--seeds`` reads back)."""
    out, seeds = [], sorted(set(seeds))
    i = 0
    while i < len(seeds):
        j = i
        while j + 1 < len(seeds) and seeds[j + 1] == seeds[j] + 1:
            j += 1
        out.append(str(seeds[i]) if i == j else f"{seeds[i]}-{seeds[j]}")
        i = j + 1
    return ",".join(out)


def load_labelled(dirs: list[Path], splits=("train", "test"), progress: bool = True):
    """(images float [N, 3, H, W], labels int64 [N, H, W], metal bool [N, H, W], source per view) of galleries
    whose frames share one size."""
    import torch
    from tqdm import tqdm

    from toolkit.scene import list_splits, load_scene

    imgs, labs, mets, src = [], [], [], []
    for d in tqdm(dirs, desc="load galleries", disable=not progress, file=sys.stderr):
        for split in [s for s in splits if s in list_splits(d)]:
            sc = load_scene(d, split, upright="off")
            for i in range(len(sc)):
                imgs.append(sc.load_image(i))
                labs.append(sc.load_extra(i, "semantic"))
                mets.append(sc.load_extra(i, "metal").bool() if "metal" in sc.frames[i].extras
                            else torch.zeros_like(labs[-1], dtype=torch.bool))
                src.append(f"{d.name}:{split}:{i}")
    return torch.stack(imgs), torch.stack(labs), torch.stack(mets), src


def _resize_to(x, size, nearest: bool):
    """Images float [N, 3, h, w] (bilinear) or labels / masks [N, h, w] (nearest) to ``size`` (H, W)."""
    import torch.nn.functional as F

    if tuple(x.shape[-2:]) == tuple(size):
        return x
    if nearest:
        return F.interpolate(x[:, None].float(), size=tuple(size), mode="nearest")[:, 0].to(x.dtype)
    return F.interpolate(x, size=tuple(size), mode="bilinear", align_corners=False).clamp(0.0, 1.0)


def scene_prior_of(net, scene_path: Path, split: str = "train"):
    """(scene prior, training prior) as ``dars priors segment`` estimates them on the photos of ``split``, or None
    when the network records no training prior."""
    import torch

    from toolkit.scene import load_scene
    from toolkit.segment import (SCENE_PRIOR_FLOOR, SegmentConfig, estimate_scene_prior, segment_images,
                                 segmenter_train_prior)

    pt = segmenter_train_prior(net)
    if pt is None:
        return None
    sc = load_scene(scene_path, split, upright="off")
    samples = []
    for i in range(len(sc)):
        pr = segment_images(sc.load_image(i)[None], SegmentConfig(backend="builtin"), model=net).probabilities[0]
        step = max(1, int((pr.shape[1] * pr.shape[2] / 4096) ** 0.5))
        samples.append(pr[:, ::step, ::step].reshape(pr.shape[0], -1).T)
    return estimate_scene_prior(torch.cat(samples), pt, SCENE_PRIOR_FLOOR), pt


def score(net, scene_path: Path, split: str = "test", scene_prior: bool = True) -> dict:
    """mIoU (per class) and metal-mask IoU of ``net`` on every frame of one split; with ``scene_prior`` the labels
    are relabelled by the scene's class prior estimated on its training photos, as ``dars priors segment`` does
    (``miou_raw`` is the network's own argmax)."""
    import torch

    from toolkit.scene import load_scene
    from toolkit.segment import METAL_THRESHOLD, SegmentConfig, apply_scene_prior, mean_iou, metal_iou, segment_images

    sc = load_scene(scene_path, split, upright="off")
    prior = scene_prior_of(net, scene_path) if scene_prior else None
    preds, raw, gts, mp, mg = [], [], [], [], []
    for i in range(len(sc)):
        seg = segment_images(sc.load_image(i)[None], SegmentConfig(backend="builtin"), model=net)
        raw.append(seg.labels[0].flatten())
        if prior is not None:
            seg = replace(seg, labels=apply_scene_prior(seg.probabilities, *prior).argmax(1))
        preds.append(seg.labels[0].flatten())
        gts.append(sc.load_extra(i, "semantic").flatten())
        if seg.metal is not None and "metal" in sc.frames[i].extras:
            mp.append((seg.metal[0] > METAL_THRESHOLD).flatten())
            mg.append(sc.load_extra(i, "metal").bool().flatten())
    miou, per = mean_iou(torch.cat(preds), torch.cat(gts))
    miou_raw, per_raw = mean_iou(torch.cat(raw), torch.cat(gts))
    out = {"scene": str(scene_path), "split": split, "views": len(sc), "miou": miou, "miou_raw": miou_raw,
           "scene_prior": None if prior is None else [round(float(v), 5) for v in prior[0]],
           "per_class": _per_class(per), "per_class_raw": _per_class(per_raw)}
    if mg:
        out["metal_iou"] = metal_iou(torch.cat(mp), torch.cat(mg), torch.cat(gts))
        out["metal_pixels_gt"] = int(torch.cat(mg).sum())
        out["metal_pixels_pred"] = int(torch.cat(mp).sum())
    return out


def _per_class(ious) -> dict:
    """Per-class IoUs as a {class: IoU rounded to 4 places} dict, None for a class absent from both (NaN)."""
    from toolkit.scene import SEMANTIC_CLASSES

    return {c: (None if v != v else round(v, 4)) for c, v in zip(SEMANTIC_CLASSES, ious)}


def _class_cells(per_class: dict) -> str:
    """One 7-wide cell per class for the score table ('-' where the class is absent)."""
    from toolkit.scene import SEMANTIC_CLASSES

    return " ".join("      -" if per_class.get(c) is None else f"{per_class[c]:7.3f}" for c in SEMANTIC_CLASSES)


def _mean_worst(rs: list[dict]) -> dict | None:
    """mean and worst mIoU (and metal IoU where scored) of score rows."""
    v = [r["miou"] for r in rs]
    if not v:
        return None
    out = {"mean": sum(v) / len(v), "worst": min(v), "scenes": len(v)}
    raw = [r["miou_raw"] for r in rs if r.get("miou_raw") is not None]
    if len(raw) == len(v):
        out.update(raw_mean=sum(raw) / len(raw), raw_worst=min(raw))
    m = [r["metal_iou"] for r in rs if r.get("metal_iou") is not None]
    if m:
        out.update(metal_iou_mean=sum(m) / len(m), metal_iou_worst=min(m))
    return out


def _print_scores(rows: list[tuple[str, dict]]) -> None:
    from toolkit.scene import SEMANTIC_CLASSES

    print(f"\n{'scene (test split, never trained on)':<40} {'mIoU':>6} {'raw':>6} {'metal IoU':>10}  "
          + " ".join(f"{c[:7]:>7}" for c in SEMANTIC_CLASSES))
    for name, r in rows:
        m = r.get("metal_iou")
        print(f"{name:<40} {r['miou']:6.3f} {r.get('miou_raw', float('nan')):6.3f} "
              f"{('-' if m is None else f'{m:.3f}'):>10}  {_class_cells(r['per_class'])}")
        if r.get("per_class_raw") and r["per_class_raw"] != r["per_class"]:
            print(f"{'':<40} {'':6} {'(raw per class)':>17}  {_class_cells(r['per_class_raw'])}")
        if r.get("metal_pixels_gt") == 0 and r.get("metal_pixels_pred"):
            # IoU 0 here is only false positives: say so rather than let it read as metal that was missed
            print(f"{'':<40} (no true metal pixel in these views: metal IoU 0 counts the {r['metal_pixels_pred']} "
                  "pixels predicted metal)")
    print("mIoU: labels relabelled by the scene's class prior estimated on its training photos, as `dars priors "
          "segment` does (toolkit.segment.estimate_scene_prior); raw: the network's own argmax")


def _score_only(net, validation: list[Path], sample: Path) -> int:
    """``--score-only``: per-scene scores, mean and worst over the validation galleries, the sample."""
    scores = {"validation": [score(net, d) for d in validation if (d / "transforms_test.json").is_file()]}
    if (sample / "transforms_test.json").is_file():
        scores["sample"] = score(net, sample)
    if not scores["validation"] and "sample" not in scores:
        print("no scene to score: render the validation galleries (python samples/galleries.py --profile validation)",
              file=sys.stderr)
        return 2
    rows = [(f"validation {Path(r['scene']).name}", r) for r in scores["validation"]]
    if "sample" in scores:
        rows.append(("sample (samples/gallery)", scores["sample"]))
    _print_scores(rows)
    summary = {"validation": _mean_worst(scores["validation"]), "sample": scores.get("sample", {}).get("miou")}
    print(json.dumps(summary, indent=1))
    out = REPO / "bench" / "out" / "segmenter_scores.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"scores": scores, "summary": summary}, indent=1) + "\n")
    print(f"wrote {out}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--prior-dir", type=Path, default=CACHE / "prior", help="prior-profile galleries (training data)")
    ap.add_argument("--max-galleries", type=int, default=0, help="use at most this many (0: all rendered)")
    ap.add_argument("--holdout", type=int, default=8, help="last N prior galleries kept out of training and scored")
    ap.add_argument("--holdout-seeds", default="", metavar="A-B,C",
                    help="these prior seeds are kept out of training and scored instead of the last --holdout "
                         "(e.g. the galleries an earlier segmenter was scored on, to compare the two on them)")
    ap.add_argument("--extra-dir", type=Path, nargs="*", default=[],
                    help="more labelled galleries for training only (e.g. the light profile's 64 px rooms: "
                         "CACHE/light), resized to the prior views' size; never scored")
    ap.add_argument("--validation", type=Path, nargs="*",
                    default=sorted((CACHE / "validation").glob("seed_*")), help="validation galleries to score")
    ap.add_argument("--sample", type=Path, default=REPO / "samples" / "gallery")
    ap.add_argument("--widths", default="8,16,32,64,128,256")
    ap.add_argument("--work-size", type=int, default=160, help="short side photos are resized to (training scale)")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--batch", type=int, default=12)
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--lr", type=float, default=4e-3)
    ap.add_argument("--scale-range", default="0.75,1.3", metavar="LO,HI",
                    help="random rescale of the training views around the work size (above 1: zoomed in, as close-up "
                         "photos of a wall are)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--init", type=Path, default=None, help="continue from this segmenter.pt")
    ap.add_argument("--save", type=Path, default=None, help="write the weights here and the card beside (.json)")
    ap.add_argument("--score-only", action="store_true",
                    help="train nothing: score the shipped segmenter (or --init) on the validation galleries and the "
                         "sample (none of them in its training set)")
    args = ap.parse_args(argv)

    import torch

    from toolkit.segment import (Segmenter, SegmenterConfig, TrainSegmenterConfig, load_segmenter, save_segmenter,
                                 train_segmenter)

    torch.set_num_threads(args.threads)
    if args.score_only:
        return _score_only(load_segmenter(args.init), args.validation, args.sample)
    dirs = _gallery_dirs(args.prior_dir)
    if args.max_galleries:
        dirs = dirs[:args.max_galleries]
    if len(dirs) <= args.holdout:
        print(f"need more than {args.holdout} rendered galleries in {args.prior_dir}, found {len(dirs)}; render them "
              "with `python samples/galleries.py --profile prior --seeds 0-159`", file=sys.stderr)
        return 2
    train_dirs, held_dirs = split_holdout(dirs, args.holdout, args.holdout_seeds)
    t0 = time.time()
    imgs, labs, mets, _ = load_labelled(train_dirs)
    extra_dirs = [d for root in args.extra_dir for d in _gallery_dirs(root)]
    if extra_dirs:  # smaller renders (the light profile's 64 px): brought to the prior views' size
        e_imgs, e_labs, e_mets, _ = load_labelled(extra_dirs)
        imgs, labs, mets = (torch.cat([a, _resize_to(b, a.shape[-2:], nearest)]) for a, b, nearest in
                            ((imgs, e_imgs, False), (labs, e_labs, True), (mets, e_mets, True)))
    print(f"training data: {len(train_dirs)} + {len(extra_dirs)} galleries, {imgs.shape[0]} views of "
          f"{imgs.shape[-1]}x{imgs.shape[-2]} ({time.time() - t0:.0f} s to load); metal pixels "
          f"{mets.float().mean() * 100:.2f} %", flush=True)
    widths = tuple(int(w) for w in args.widths.split(","))
    arch = SegmenterConfig(widths=widths, groups=4, metal=True, work_size=args.work_size)
    net = load_segmenter(args.init) if args.init else Segmenter(arch)
    # photos are segmented at work_size on their short side: train_segmenter trains at that scale (x 0.75-1.3)
    cfg = TrainSegmenterConfig(arch=arch, steps=args.steps, batch_size=args.batch, crop=args.crop,
                               scale_range=tuple(float(x) for x in args.scale_range.split(",")), lr=args.lr, colour_jitter=0.25,
                               exposure_stops=1.5, noise=0.03, blur=1.5, jpeg=30, seed=args.seed, progress=True)
    res = train_segmenter(imgs, labs, cfg, model=net, metal=mets)
    print(f"trained {args.steps} steps in {res.seconds:.0f} s; train mIoU {res.train_miou:.3f}; "
          f"final loss {sum(res.losses[-50:]) / max(len(res.losses[-50:]), 1):.3f}", flush=True)
    n_views = int(imgs.shape[0])
    del imgs, labs, mets
    net = res.model
    scores = {"prior_heldout": [score(net, d) for d in held_dirs],
              "validation": [score(net, d) for d in args.validation if (d / "transforms_test.json").is_file()]}
    if (args.sample / "transforms_test.json").is_file():
        scores["sample"] = score(net, args.sample)
    rows = [(f"prior {Path(r['scene']).name}", r) for r in scores["prior_heldout"]]
    rows += [(f"validation {Path(r['scene']).name}", r) for r in scores["validation"]]
    if "sample" in scores:
        rows.append(("sample (samples/gallery)", scores["sample"]))
    _print_scores(rows)
    summary = {"prior_heldout": _mean_worst(scores["prior_heldout"]), "validation": _mean_worst(scores["validation"]),
               "sample": scores.get("sample", {}).get("miou")}
    print(json.dumps(summary, indent=1))
    if args.save:
        card = {
            "command": "bench/bench_segmenter.py " + " ".join(argv if argv is not None else sys.argv[1:]),
            "data": {"train_galleries": [d.name for d in train_dirs], "profile": args.prior_dir.name,
                     "extra_galleries": [f"{d.parent.name}/{d.name}" for d in extra_dirs],
                     "render_command": f"samples/galleries.py --profile {args.prior_dir.name} --seeds "
                                       + seed_ranges([_seed_of(d) for d in train_dirs + held_dirs]),
                     "views": n_views,
                     "heldout_prior_galleries": [d.name for d in held_dirs],
                     "validation_galleries": [Path(r["scene"]).name for r in scores["validation"]],
                     "augmentation": "rescale, crop, h-flip, brightness/white balance/contrast/saturation jitter, "
                                     "exposure +-1.5 stops, blur (sigma <= 1.5 px), noise (sd <= 0.03), JPEG q 30-95"},
            "arch": asdict(arch), "parameters": net.num_parameters(),
            "train_config": {k: v for k, v in asdict(cfg).items() if k != "arch"},
            "train_seconds": round(res.seconds, 1), "train_miou": res.train_miou,
            "final_loss": sum(res.losses[-50:]) / max(len(res.losses[-50:]), 1),
            "class_pixels": res.class_pixels, "scores": scores, "summary": summary,
            "ground_truth_use": "labels and metal masks of the prior galleries train it; evaluation scenes are "
                                "other seeds and the bundled sample",
        }
        init_card = args.init.with_suffix(".json") if args.init else None
        if init_card is not None:  # fine-tuned: what the starting weights were trained on is part of its data
            prev = json.loads(init_card.read_text()) if init_card.is_file() else {}
            card["init"] = {"weights": str(args.init), "command": prev.get("command"), "data": prev.get("data"),
                            "init": prev.get("init")}
        save_segmenter(args.save, net, {"card": args.save.with_suffix(".json").name, "summary": summary,
                                        "class_pixels": res.class_pixels, "class_balance": cfg.class_balance})
        tmp = args.save.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(card, indent=1) + "\n")
        tmp.replace(args.save.with_suffix(".json"))
        print(f"wrote {args.save} ({args.save.stat().st_size / 1e6:.1f} MB) and its card")
    return 0


if __name__ == "__main__":
    sys.exit(main())
