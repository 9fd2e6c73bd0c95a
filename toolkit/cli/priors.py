"""``dars priors weights|segment|colour|light|layout|sh-probe`` — the prior stages on a scene (:mod:`toolkit.priors`).

Outputs go to ``--out DIR`` or ``<scene>/priors/<stage>`` under the one output-folder policy (:mod:`toolkit.outputs`:
``dars_manifest.json`` lists what dars wrote; files it did not write are never overwritten; ``--force`` writes beside
them). ``sh-probe`` fits SH to an HDR probe file and prints it; ``--out FILE`` also writes the JSON (an existing file
only with ``--force``). Nothing is ever written beside the input unless asked.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .._checks import DarsError
from ..defaults import YAW_FROM_DEFAULT
from ._common import COUNT, FINITE, NONNEGATIVE, POSITIVE, SCENE_HELP, print_json

_LM = ["(0,0)", "(1,-1)", "(1,0)", "(1,1)", "(2,-2)", "(2,-1)", "(2,0)", "(2,1)", "(2,2)"]
"""(l, m) of the 9 SH coefficients, SPEC order (table rows)."""


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("priors", help="prior stages: weights, segment, colour, light, layout, sh-probe",
                       description="Prior stages on a scene; outputs go next to the scene unless --out.")
    stages = p.add_subparsers(dest="priors_command", metavar="STAGE")
    stages.required = True

    q = stages.add_parser("weights", help="distortion weight maps W (eqs. 2-4, 8) + heat-map overlays")
    _common(q, "weights")
    q.add_argument("--alpha", type=NONNEGATIVE, default=0.5, help="gradient weight (default 0.5)")
    q.add_argument("--beta", type=NONNEGATIVE, default=0.3, help="semantic edge weight (default 0.3)")
    q.add_argument("--gamma", type=NONNEGATIVE, default=0.2, help="metal mask weight (default 0.2)")
    q.add_argument("--lambda-reg", type=NONNEGATIVE, default=0.3, help="smoothness weight of eq. 8 (default 0.3)")
    q.add_argument("--labels", choices=["auto", "scene", "segment", "none"], default="auto",
                   help="labels for the semantic edges: auto (default) = the predictions of `dars priors segment` "
                        "when present, else none; scene = the scene's ground truth (experiments only)")
    q.add_argument("--metal", choices=["auto", "scene", "segment", "none"], default="auto",
                   help="metal mask of eq. 4: auto (default) = the predicted masks when present, else none; "
                        "scene = the scene's ground truth (experiments only)")
    q.add_argument("--segment", default=None, metavar="DIR",
                   help="folder of `dars priors segment` outputs (default: the 'segment' folder beside --out, "
                        "else <scene>/priors/segment)")
    q.add_argument("--no-metal", action="store_true", help="no metal term (as --metal none)")
    q.set_defaults(func=cmd_weights)

    q = stages.add_parser("segment", help="7-class semantic labels + metal mask (shipped network by default)")
    _common(q, "segment")
    q.add_argument("--backend", choices=["shipped", "builtin", "provided", "onnx"], default="shipped",
                   help="shipped (default): the shipped network on any photos; builtin: fine-tune it on the scene's "
                        "labelled views; provided: the scene's own labels (ground truth); onnx: --model FILE.onnx")
    q.add_argument("--model", default=None, help="shipped/builtin: a segmenter.pt instead of the shipped one; "
                                                 "onnx: the .onnx file")
    q.add_argument("--train-every", type=POSITIVE, default=4,
                   help="builtin: fine-tune on every n-th labelled view (default 4)")
    q.add_argument("--eval-split", default="test", help="also report mIoU on this split if labelled ('none' to skip)")
    q.add_argument("--steps", type=POSITIVE, default=300, help="builtin: fine-tuning steps (default 300)")
    q.add_argument("--seed", type=COUNT, default=0)
    q.add_argument("--no-onnx", action="store_true", help="builtin: do not write segmenter.onnx")
    q.add_argument("--scene-prior", choices=["on", "off"], default="on",
                   help="on (default): relabel with the scene's own class prior, estimated by EM over all its photos "
                        "(drops classes the room lacks, e.g. a display case); off: each photo's own argmax")
    q.set_defaults(func=cmd_segment)

    q = stages.add_parser("colour", help="per-image exposure / white-balance gains against the scene's consensus")
    _common(q, "colour")
    q.add_argument("--detector", choices=["orb", "sift"], default="orb")
    q.add_argument("--gauge", choices=["median", "mean"], default="median",
                   help="median: the typical photo has gain 1 (default; robust to a few odd exposures); "
                        "mean: the geometric-mean gain is 1")
    q.add_argument("--reference", type=COUNT, default=None,
                   help="fix this image's gain to 1 instead (overrides --gauge)")
    q.set_defaults(func=cmd_colour)
    _add_light(stages)

    q = stages.add_parser("layout",
                          help="the room's box (walls, floor, ceiling) from the posed photos, by a plane sweep",
                          description="Fit the room's box (toolkit.layout) and write priors/layout/layout.json and "
                                      "layout.png (each face's sweep; photos tinted by face). `dars train "
                                      "--layout-depth W --priors DIR` reads it instead of fitting the box again.")
    _common(q, "layout")
    q.add_argument("--no-upright", action="store_true",
                   help="keep the input's orientation, as `dars train --no-upright` (default: as dars train loads it)")
    q.add_argument("--yaw-from", choices=("lines", "points"), default=YAW_FROM_DEFAULT,
                   help="the walls' directions: lines — the photos' straight edges, falling back to the sparse points "
                        "where they give no clear direction; points — the sparse points' histograms (before "
                        f"2026-12-05) (default: {YAW_FROM_DEFAULT})")
    q.set_defaults(func=cmd_layout)
    _add_sh_probe(stages)


def _common(q: argparse.ArgumentParser, stage: str) -> None:
    q.add_argument("scene", help=SCENE_HELP)
    q.add_argument("--split", default="train", help="split to process (default: train)")
    q.add_argument("--downscale", type=POSITIVE, default=1, metavar="N",
                   help="shrink the photos N times on load (default: 1; `dars train` reads maps made at another "
                        "--downscale, resized)")
    q.add_argument("--out", default=None, help=f"output directory (default: <scene>/priors/{stage})")
    q.add_argument("--masks", default="auto", choices=["auto", "ignore", "alpha", "off"],
                   help="what the frames' mask_path maps mean, as for dars train: auto (default) reads masks that "
                        "outline an object as the photos' alpha (the photos are composited on the background, as "
                        "dars train sees them), other masks as pixels to ignore")
    q.add_argument("--force", action="store_true",
                   help="write into a non-empty folder beside its files (files dars did not write are never replaced)")
    q.add_argument("--json", action="store_true", help="print only JSON on stdout")


def _add_light(sub: argparse._SubParsersAction) -> None:
    q = sub.add_parser("light", help="SH lighting from the photos with the light estimation network (eq. 11)",
                       description="Run the light network on every image of a split and write priors/light/light.json "
                                   "(mean of the per-image SH; dars train initialises l_env from it).")
    _common(q, "light")
    q.add_argument("--weights", default=None, help="light-network weights (default: toolkit/weights/lightnet_small.pt)")
    q.add_argument("--reduce", choices=["mean", "median"], default="mean", help="combine per-image SH (default: mean)")
    q.add_argument("--batch-size", type=POSITIVE, default=32)
    q.set_defaults(func=cmd_light)


def _add_sh_probe(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sh-probe",
        help="fit 27 SH coefficients (SPEC convention) to an HDR probe (.hdr/.exr)",
        description="Project an HDR environment map (lat-long or angular light probe) onto order-2 real spherical "
        "harmonics of incident radiance, SPEC convention (world +z up). Angular probes are captured +y up: pass "
        "--rotate-x 90 to bring them into the +z-up world.",
    )
    p.add_argument("file", help="environment map, Radiance .hdr or OpenEXR .exr")
    p.add_argument("--layout", choices=["latlong", "angular"], default="latlong", help="map parametrisation (default: latlong)")
    p.add_argument("--rotate-x", type=FINITE, default=0.0, metavar="DEG",
                   help="rotate map directions about +x by DEG degrees before fitting (90 for a +y-up probe)")
    p.add_argument("--out", default=None, help="also write the JSON document to this file (default: only print)")
    p.add_argument("--no-save", action="store_true", help="do not write a file, only print (the default)")
    p.add_argument("--force", action="store_true", help="replace --out if it exists")
    p.add_argument("--json", action="store_true", help="print only machine-readable JSON on stdout")
    p.set_defaults(func=cmd_sh_probe)


# ============================================================================ handlers
def _out(args: argparse.Namespace, scene, stage: str):
    """The stage's output folder (``--out`` or ``<scene>/priors/<stage>``), checked before any work."""
    from ..priors import OutputDir

    if args.out:
        return OutputDir(args.out, stage, force=args.force).check()
    option = f"the default output folder (SCENE/priors/{stage}; --out picks another)"
    return OutputDir(scene.priors_dir(stage), stage, force=args.force, option=option).check()


def _load(args: argparse.Namespace, split: str | None = None, **kw):
    """The scene of a prior stage, its masks read as ``--masks`` says (:func:`toolkit.train.config.resolve_masks`)."""
    from ..scene import load_scene
    from ..train.config import resolve_masks

    scene = load_scene(args.scene, split or args.split, downscale=args.downscale, **kw)
    return resolve_masks(args.masks, scene, log=lambda m: print(m, file=sys.stderr))[1]


def cmd_weights(args: argparse.Namespace) -> int:
    from ..edges import WeightMapConfig
    from ..priors import priors_weights

    scene = _load(args)
    cfg = WeightMapConfig(alpha=args.alpha, beta=args.beta, gamma=args.gamma, lambda_reg=args.lambda_reg)
    seg = args.segment
    if seg is None and args.out and (Path(args.out).parent / "segment").is_dir():
        seg = Path(args.out).parent / "segment"
    with _out(args, scene, "weights").guard() as out:
        s = priors_weights(scene, out, cfg, labels=args.labels, use_metal=not args.no_metal, metal=args.metal,
                           segment_dir=seg)
    if args.json:
        print_json(s)
        return 0
    print(f"{'frame':<28} {'mean W':>7} {'W>0.7':>7} {'L_dist':>9}  labels  metal")
    for r in s["images"]:
        print(f"{r['key'][:28]:<28} {r['mean']:7.3f} {r['frac_above_tau']:7.3f} {r['distortion_loss']:9.5f}  "
              f"{r['labels']:<6}  {'yes' if r['metal'] else 'no'}")
    print(f"{len(s['images'])} weight maps (alpha={cfg.alpha}, beta={cfg.beta}, gamma={cfg.gamma}, "
          f"lambda_reg={cfg.lambda_reg}); mean L_distortion {s['mean_distortion_loss']:.5f} -> {s['out']}")
    print(f"labels: {s['labels']}; metal mask: {s['metal']}; ground truth used: {s['ground_truth_inputs']}")
    return 0


def cmd_segment(args: argparse.Namespace) -> int:
    from export.onnx import export_segmenter_onnx

    from ..priors import priors_segment
    from ..scene import list_splits
    from ..segment import TrainSegmenterConfig

    scene = _load(args)
    eval_scene = None
    if args.eval_split != "none" and args.eval_split != args.split and args.eval_split in list_splits(args.scene):
        eval_scene = _load(args, args.eval_split)
    tcfg = (TrainSegmenterConfig(steps=args.steps, seed=args.seed, lr=1e-3, progress=True)
            if args.backend == "builtin" else None)
    if args.model and not Path(args.model).is_file():
        raise DarsError(f"--model {args.model}: file not found")
    with _out(args, scene, "segment").guard() as out:
        info = priors_segment(scene, out, args.backend, args.model, args.train_every, eval_scene, tcfg,
                              export_onnx=None if args.no_onnx else export_segmenter_onnx,
                              scene_prior=args.scene_prior == "on")
    if args.json:
        print_json(info)
        return 0
    print(f"segmented {len(scene)} frames of '{scene.split}' with backend '{args.backend}' -> {info['out']}")
    for name in ("heldout", "eval"):
        if f"miou_{name}" in info:
            what = (f"{info['heldout_views']} held-out views of '{scene.split}'" if name == "heldout"
                    else f"{info['eval_views']} views of '{info['eval_split']}'")
            per = ", ".join(f"{c} {v:.3f}" if v is not None else f"{c} -" for c, v in info[f"per_class_{name}"].items())
            print(f"mIoU {info[f'miou_{name}']:.3f} on {what}  ({per})")
            if info.get(f"metal_iou_{name}") is not None:
                print(f"metal-mask IoU {info[f'metal_iou_{name}']:.3f} on the same views")
    if "onnx" in info:
        print(f"segmenter.onnx: opset {info['onnx']['opset']}, max |onnxruntime - torch| = {info['onnx']['max_abs_err']:.2e}")
    return 0


def cmd_colour(args: argparse.Namespace) -> int:
    from ..colour import ColourConfig
    from ..priors import priors_colour

    scene = _load(args)
    cfg = ColourConfig(detector=args.detector, gauge="reference" if args.reference is not None else args.gauge,
                       reference=args.reference or 0, srgb=scene.srgb, progress=True)
    if args.reference is not None and args.reference >= len(scene):
        raise DarsError(f"--reference {args.reference}: split '{scene.split}' has {len(scene)} images "
                        f"(0-{len(scene) - 1})")
    with _out(args, scene, "colour").guard() as out:
        d = priors_colour(scene, out, cfg)
    if args.json:
        print_json(d)
        return 0
    print(f"{'frame':<28} {'gain R':>7} {'gain G':>7} {'gain B':>7} {'stops':>6}")
    for im in d["images"]:
        flag = "" if im["connected"] else "  (not matched to the rest)"
        print(f"{im['key'][:28]:<28} {im['gain'][0]:7.3f} {im['gain'][1]:7.3f} {im['gain'][2]:7.3f} "
              f"{im['stops']:+6.2f}{flag}")
    st = d["stats"]
    print(f"{st['pairs_used']}/{st['pairs_tried']} pairs, {st['matches_used']} matches, residual "
          f"{st['residual_rms_log']:.4f} (log); gauge {d['gauge']} -> {Path(d['out']) / 'colour.json'}")
    return 0


def cmd_light(args: argparse.Namespace) -> int:
    from ..priors import priors_light

    scene = _load(args)
    with _out(args, scene, "light").guard() as out:
        info = priors_light(scene, out, args.weights, args.reduce, args.batch_size)
    if args.json:
        print_json(info)
        return 0
    ev = info["evaluation"]
    head = f"{'k':>2} {'(l,m)':>7} {'R':>9} {'G':>9} {'B':>9}" + (f"   {'GT R':>8} {'GT G':>8} {'GT B':>8}" if ev else "")
    print(f"SH lighting of {info['scene']} [{info['split']}, {info['views']} views], {info['reduce']} of the "
          f"per-image predictions of {info['model']['arch']} ({info['model']['path']})")
    print(head)
    for k, (lm, rgb) in enumerate(zip(_LM, info["coeffs"])):
        line = f"{k:>2} {lm:>7} " + " ".join(f"{v:9.4f}" for v in rgb)
        if ev:
            line += "   " + " ".join(f"{v:8.4f}" for v in ev["gt"][k])
        print(line)
    if ev:
        parts = [f"network {ev['env_light_l2']:.4f} (per image {ev['env_light_l2_per_image_mean']:.4f})"]
        if "baseline_train_mean_sh" in ev:
            parts.append(f"baseline training-set mean SH {ev['baseline_train_mean_sh']:.4f}")
        parts.append(f"baseline image mean colour {ev['baseline_mean_colour']:.4f}")
        print("Env-light L2 vs GT (eq. 36): " + "; ".join(parts))
    print(f"-> {Path(info['out']) / 'light.json'}")
    return 0


_YAW_SOURCE = {"lines": "photos' edges", "points": "sparse points", "cameras": "cameras (too few sparse points)"}


def cmd_layout(args: argparse.Namespace) -> int:
    from ..layout import LayoutConfig
    from ..priors import priors_layout

    scene = _load(args, upright="off" if args.no_upright else "auto")
    log = None if args.json else (lambda m: print(m, file=sys.stderr))
    with _out(args, scene, "layout").guard() as out:
        d = priors_layout(scene, out, cfg=LayoutConfig(yaw_from=args.yaw_from), log=log)
    if args.json:
        print_json(d)
        return 0
    size = [round(b - a, 2) for a, b in zip(d["lo"], d["hi"])]
    print(f"room box of {d['scene']} [{d['split']}, {d['photos']} photos, {d['sparse_points']} sparse points]: "
          f"{size} scene units; walls' directions from the {_YAW_SOURCE.get(d.get('yaw'), 'sparse points')}")
    for name, f in d["faces"].items():
        print(f"  {name:>8}: {'counts' if f['confident'] else 'no face'}  (contrast {f['contrast']:.2f}, "
              f"{100 * f['coverage']:.0f} % of the pixels)")
    print(f"-> {Path(d['out']) / 'layout.json'}, {Path(d['out']) / 'layout.png'}")
    return 0


def _sh_table(payload: dict) -> str:
    lines = [f"SH probe of {payload['file']} ({payload['layout']}, {payload['shape'][0]}x{payload['shape'][1]})",
             f"{'k':>2} {'(l,m)':>7} {'R':>12} {'G':>12} {'B':>12}"]
    for k, (lm, rgb) in enumerate(zip(_LM, payload["coeffs"])):
        lines.append(f"{k:>2} {lm:>7} " + " ".join(f"{v:12.6f}" for v in rgb))
    dc = payload["dc_irradiance"]
    lines.append(f"DC irradiance (π · mean radiance): {dc[0]:.5g} {dc[1]:.5g} {dc[2]:.5g}")
    return "\n".join(lines)


def cmd_sh_probe(args: argparse.Namespace) -> int:
    from ..io import write_json
    from ..outputs import check_output_file
    from ..priors import sh_probe_json

    path = Path(args.file)
    out = None
    if args.out and not args.no_save:
        out = check_output_file(args.out, args.force, suffixes=(".json",))
    payload = sh_probe_json(path, args.layout, float(args.rotate_x))
    if out is not None:
        write_json(out, payload)
    if args.json:
        sys.stdout.write(json.dumps(payload) + "\n")
    else:
        print(_sh_table(payload))
        if out is not None:
            print(f"wrote {out}")
    return 0
