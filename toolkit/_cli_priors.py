"""``dars priors ...`` — the prior stages on a scene, written next to it.

Sub-commands here: ``weights`` (stage 6), ``segment`` (stage 3), ``colour`` (stage 2). Others register through the
hook :data:`PRIORS_SUBCOMMANDS` (a list of ``register(subparsers)`` callables, each adding one sub-command whose
parser sets ``func``); ``toolkit/_cli_sh.py`` (``add_parser(subparsers)`` + ``main(args)``) is picked up
automatically when it exists.

Outputs go to ``--out DIR`` or ``Scene.priors_dir(stage)`` (``<scene>/priors/<stage>``). Writes are atomic, and a
``manifest.json`` lists what dars wrote there: a file that exists but is not in the manifest is the user's and is
never overwritten unless ``--force``. Read-only scene folders fail early with a message suggesting ``--out``.

The ``priors_*`` functions are the orchestration (load, run a stage, write) and can be called from Python.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from dataclasses import asdict
from pathlib import Path
from typing import Callable, Iterable

from ._checks import DarsError

__all__ = ["PRIORS_SUBCOMMANDS", "add_parser", "priors_weights", "priors_segment", "priors_colour",
           "prepare_out_dir", "OutputDir"]

PRIORS_SUBCOMMANDS: list[Callable[[argparse._SubParsersAction], None]] = []
"""Hook: callables ``register(priors_subparsers)`` that add more ``dars priors <name>`` sub-commands."""

TAU = 0.7
MANIFEST = "manifest.json"


# ============================================================================ output directory handling
class OutputDir:
    """A priors output folder: checks writability and ownership, records what we write in ``manifest.json``."""

    def __init__(self, path: Path, stage: str, force: bool = False):
        self.path = Path(path)
        self.stage = stage
        self.force = force
        self.written: list[str] = []
        self._previous: set[str] = set()

    def check(self, planned: Iterable[str]) -> "OutputDir":
        """Raise :class:`DarsError` if the folder is not writable or a planned file belongs to the user."""
        _check_writable(self.path)
        man = self.path / MANIFEST
        ours: set[str] = set()
        foreign_manifest = False
        if man.exists():
            try:
                data = json.loads(man.read_text())
                if data.get("tool") != "dars":
                    raise ValueError("not ours")
                ours = set(data.get("files", []))
            except (ValueError, AttributeError):
                foreign_manifest = True
        self._previous = ours
        if self.force:
            return self
        if foreign_manifest:
            raise DarsError(f"{man} exists and was not written by dars; refusing to overwrite it "
                            "(pass --force, or choose another --out)")
        clash = [f for f in planned if f != MANIFEST and (self.path / f).exists() and f not in ours]
        if clash:
            more = f" and {len(clash) - 3} more" if len(clash) > 3 else ""
            raise DarsError(f"refusing to overwrite files dars did not write in {self.path}: "
                            f"{', '.join(clash[:3])}{more} (pass --force, or choose another --out)")
        return self

    def file(self, name: str) -> Path:
        """Path of an output file; records it for the manifest."""
        self.written.append(name)
        return self.path / name

    def finish(self, extra: dict | None = None) -> None:
        from .io import write_json

        files = sorted(set(self.written) | self._previous)
        write_json(self.path / MANIFEST, {"tool": "dars", "stage": self.stage, "files": files, **(extra or {})})


def _check_writable(path: Path) -> None:
    hint = ("pass --out DIR to write the priors somewhere else (the scene folder may be read-only, "
            "e.g. /work/shared/data)")
    p = Path(path).absolute()
    anc = p
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        raise DarsError(f"cannot write priors to {p}: {anc} is a file; {hint}")
    st = anc.stat()
    # root bypasses permission bits: honour a folder marked read-only (no write bit) anyway
    if not os.access(anc, os.W_OK) or not (st.st_mode & 0o222):
        raise DarsError(f"cannot write priors to {p}: {anc} is read-only; {hint}")
    try:
        p.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".dars-write-test.", dir=p)
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        raise DarsError(f"cannot write priors to {p}: {e.strerror or e}; {hint}") from e


def prepare_out_dir(scene, stage: str, out: "str | os.PathLike | OutputDir | None", planned: Iterable[str],
                    force: bool = False) -> OutputDir:
    """The output folder for ``stage``: ``out`` or ``scene.priors_dir(stage)``, checked (see :class:`OutputDir`).

    An :class:`OutputDir` passed as ``out`` is checked for ``planned`` too and returned.
    """
    if isinstance(out, OutputDir):
        return out.check(list(planned) + [MANIFEST])
    path = Path(out) if out else scene.priors_dir(stage)
    return OutputDir(path, stage, force).check(list(planned) + [MANIFEST])


def _progress(it, desc: str, total: int | None = None):
    from tqdm import tqdm

    return tqdm(it, desc=desc, total=total, file=sys.stderr, leave=False, disable=None)


def _labels_for(scene, i: int, source: str, segment_dir: Path | None):
    """Labels of frame i from the scene or from a segment priors folder, or None."""
    import numpy as np
    import torch

    if source in ("auto", "scene") and "semantic" in scene.frames[i].extras:
        return scene.load_extra(i, "semantic"), "scene"
    if source in ("auto", "segment") and segment_dir is not None:
        f = segment_dir / f"{scene.frames[i].key}.png"
        if f.is_file():
            from .io import read_map

            lab = read_map(f, f"predicted labels {f}")
            lab = lab[..., 0] if lab.ndim == 3 else lab
            return torch.from_numpy(np.asarray(lab, np.int64)), "segment"
    if source in ("scene", "segment"):
        raise DarsError(f"frame {i} ('{scene.frames[i].name}') has no {source} labels (use --labels auto or none)")
    return None, "none"


# ============================================================================ weights
def priors_weights(scene, out_dir=None, cfg=None, labels: str = "auto", use_metal: bool = True,
                   force: bool = False) -> dict:
    """Write distortion weight maps of every frame: ``<key>.npy`` (float16 W), ``<key>_overlay.png`` and
    ``weights.json``; returns the summary written to ``weights.json``.

    Args:
        scene: a loaded :class:`toolkit.scene.Scene`.
        out_dir: output folder (path or :class:`OutputDir`; ``None``: ``scene.priors_dir("weights")``).
        cfg: :class:`toolkit.edges.WeightMapConfig` (default config if ``None``).
        labels: ``auto`` (scene labels, else ``priors/segment`` predictions, else none), ``scene``, ``segment``
            or ``none``.
        use_metal: use the scene's ``metal`` masks when present.
        force: overwrite files in the folder that dars did not write.

    Raises:
        DarsError: the folder is not writable, or holds files of the user's that would be overwritten.
    """
    import numpy as np

    from .edges import WeightMapConfig, weight_map, weight_overlay
    from .io import write_png

    cfg = cfg or WeightMapConfig()
    keys = [f.key for f in scene.frames]
    out = prepare_out_dir(scene, "weights", out_dir,
                          [f"{k}.npy" for k in keys] + [f"{k}_overlay.png" for k in keys] + ["weights.json"], force)
    seg_dir = scene.priors_dir("segment")
    rows = []
    for i in _progress(range(len(scene)), "weights", len(scene)):
        f = scene.frames[i]
        img = scene.load_image(i)
        lab, lab_src = _labels_for(scene, i, labels, seg_dir) if labels != "none" else (None, "none")
        metal = scene.load_extra(i, "metal") if use_metal and "metal" in f.extras else None
        wm = weight_map(img[None], None if lab is None else lab[None], None if metal is None else metal[None], cfg)
        w = wm.weights[0]
        _save_npy(out.file(f"{f.key}.npy"), w.numpy().astype(np.float16))
        write_png(out.file(f"{f.key}_overlay.png"), weight_overlay(img, w))
        rows.append({"key": f.key, "name": f.name, "mean": float(w.mean()), "frac_above_tau": float((w > TAU).float().mean()),
                     "distortion_loss": float(wm.distortion_loss[0]), "labels": lab_src, "metal": metal is not None})
    from .io import write_json

    summary = {
        "scene": str(scene.source), "split": scene.split, "tau": TAU, "config": asdict(cfg),
        "distortion_loss_definition": "lambda_reg * (sum (D_x W)^2 + sum (D_y W)^2) / (H W), per image",
        "mean_distortion_loss": float(np.mean([r["distortion_loss"] for r in rows])) if rows else 0.0,
        "mean_weight": float(np.mean([r["mean"] for r in rows])) if rows else 0.0,
        "images": rows, "out": str(out.path),
    }
    write_json(out.file("weights.json"), summary)
    out.finish({"scene": str(scene.source), "split": scene.split})
    return summary


def _save_npy(path: Path, arr) -> None:
    import numpy as np

    from .io import atomic_write

    with atomic_write(path) as fh:
        np.save(fh, arr)


# ============================================================================ segment
def priors_segment(scene, out_dir=None, backend: str = "provided", model: str | None = None,
                   train_every: int = 4, eval_scene=None, train_cfg=None, export_onnx: bool = True,
                   force: bool = False) -> dict:
    """Label every frame of ``scene`` and write ``<key>.png`` (uint8 ids), ``<key>_preview.png`` and
    ``segment.json`` (mIoU where ground-truth labels exist); for ``builtin`` also ``segmenter.pt`` and
    ``segmenter.onnx`` (with the ONNX parity figure).

    Args:
        scene: the frames to label.
        out_dir: output folder (path or :class:`OutputDir`; ``None``: ``scene.priors_dir("segment")``).
        backend: ``provided``, ``builtin`` or ``onnx``.
        model: ``builtin``: a ``segmenter.pt`` to use instead of training; ``onnx``: the ONNX file (required).
        train_every: ``builtin`` without ``model``: train on every n-th labelled frame of ``scene``; mIoU is then
            reported on the other frames (``miou_heldout``).
        eval_scene: another labelled split (e.g. test) to report ``miou_eval`` on (not written).
        train_cfg: :class:`toolkit.segment.TrainSegmenterConfig`.
        export_onnx: write ``segmenter.onnx`` for ``builtin``.
        force: overwrite files in the folder that dars did not write.

    Raises:
        DarsError / SegmentationError: unwritable folder, user files in the way, missing labels or model.
    """
    import numpy as np
    import torch

    from .io import write_json, write_png
    from .preview import colourise_labels, tile
    from .segment import (SegmentConfig, SegmentationError, TrainSegmenterConfig, load_segmenter, mean_iou,
                          save_segmenter, segment_images, train_segmenter)

    keys = [f.key for f in scene.frames]
    planned = [f"{k}.png" for k in keys] + [f"{k}_preview.png" for k in keys] + ["segment.json"]
    if backend == "builtin":
        planned += ["segmenter.pt"] + (["segmenter.onnx"] if export_onnx else [])
    out = prepare_out_dir(scene, "segment", out_dir, planned, force)
    has_gt = scene.has_extra("semantic")
    info: dict = {"scene": str(scene.source), "split": scene.split, "backend": backend}
    net = None
    train_idx: list[int] = []
    if backend == "builtin":
        if model:
            net = load_segmenter(model)
            info["model"] = str(model)
        else:
            if not has_gt:
                raise SegmentationError(
                    f"{scene.source}: backend 'builtin' trains on labelled views, but split '{scene.split}' has no "
                    "semantic_path labels; pass --model segmenter.pt (a trained one) or use --backend onnx")
            if train_every < 1:
                raise SegmentationError(f"--train-every {train_every} must be >= 1")
            train_idx = list(range(0, len(scene), train_every))
            imgs = scene.load_images(train_idx)
            labs = torch.stack([scene.load_extra(i, "semantic") for i in train_idx])
            cfg = train_cfg or TrainSegmenterConfig(progress=True)
            res = train_segmenter(imgs, labs, cfg)
            net = res.model
            info.update(train_views=[scene.frames[i].key for i in train_idx], train_seconds=round(res.seconds, 1),
                        train_miou=res.train_miou, final_loss=float(np.mean(res.losses[-20:])) if res.losses else None,
                        parameters=net.num_parameters(), train_config=asdict(cfg))
        save_segmenter(out.file("segmenter.pt"), net, {"scene": str(scene.source)})
        if export_onnx:
            from export.onnx import export_segmenter_onnx

            h, w = scene.image_size
            rep = export_segmenter_onnx(net, out.file("segmenter.onnx"), image_size=(h, w))
            info["onnx"] = {"path": str(rep.path), "opset": rep.opset, "max_abs_err": rep.max_abs_err,
                            "inputs_checked": rep.inputs_checked, "file_size": rep.file_size}
    elif backend == "onnx":
        if not model:
            raise SegmentationError("backend 'onnx' needs --model FILE.onnx")
        info["model"] = str(model)
    scfg = SegmentConfig(backend=backend)

    preds, gts = [], []
    for i in _progress(range(len(scene)), "segment", len(scene)):
        f = scene.frames[i]
        img = scene.load_image(i)
        gt = scene.load_extra(i, "semantic") if "semantic" in f.extras else None
        if backend == "provided":
            if gt is None:
                raise SegmentationError(f"frame {i} ('{f.name}') has no semantic_path labels for backend 'provided'")
            seg = segment_images(img[None], scfg, labels=gt[None])
        else:
            seg = segment_images(img[None], scfg, model=net if backend == "builtin" else model)
        lab = seg.labels[0]
        write_png(out.file(f"{f.key}.png"), lab.numpy().astype(np.uint8))
        row = [img.permute(1, 2, 0).numpy(), colourise_labels(lab)]
        if gt is not None:
            row.append(colourise_labels(gt))
        write_png(out.file(f"{f.key}_preview.png"), tile([row]))
        if gt is not None and i not in train_idx:
            preds.append(lab)
            gts.append(gt)
    from .scene import SEMANTIC_CLASSES

    def _report(p, g):
        miou, per = mean_iou(torch.stack(p), torch.stack(g))
        return miou, {c: (None if v != v else v) for c, v in zip(SEMANTIC_CLASSES, per)}

    if gts:
        info["miou_heldout"], info["per_class_heldout"] = _report(preds, gts)
        info["heldout_views"] = len(gts)
    if eval_scene is not None and eval_scene.has_extra("semantic") and backend != "provided":
        ep, eg = [], []
        for i in _progress(range(len(eval_scene)), f"segment eval ({eval_scene.split})", len(eval_scene)):
            seg = segment_images(eval_scene.load_image(i)[None], scfg, model=net if backend == "builtin" else model)
            ep.append(seg.labels[0])
            eg.append(eval_scene.load_extra(i, "semantic"))
        info["miou_eval"], info["per_class_eval"] = _report(ep, eg)
        info["eval_split"] = eval_scene.split
        info["eval_views"] = len(eg)
    info["out"] = str(out.path)
    write_json(out.file("segment.json"), info)
    out.finish({"scene": str(scene.source), "split": scene.split})
    return info


# ============================================================================ colour
def priors_colour(scene, out_dir=None, cfg=None, force: bool = False) -> dict:
    """Estimate per-image colour transforms of ``scene`` and write ``colour.json``; returns its content.

    Args:
        scene: a loaded scene (camera poses choose the pairs to match).
        out_dir: output folder (path or :class:`OutputDir`; ``None``: ``scene.priors_dir("colour")``).
        cfg: :class:`toolkit.colour.ColourConfig`.
        force: overwrite files in the folder that dars did not write.
    """
    import torch

    from .colour import ColourConfig, estimate_colour_transforms
    from .io import write_json

    cfg = cfg or ColourConfig(srgb=scene.srgb, progress=True)
    out = prepare_out_dir(scene, "colour", out_dir, ["colour.json"], force)
    images = torch.stack([scene.load_image(i) for i in _progress(range(len(scene)), "colour: load", len(scene))])
    tr = estimate_colour_transforms(images, cfg, c2w=scene.cameras.c2w, keys=[f.key for f in scene.frames])
    d = tr.to_json()
    d.update(scene=str(scene.source), split=scene.split, config=asdict(cfg),
             usage="photo_linear = gain * consensus_linear + offset; toolkit.colour.ColourTransforms.from_json")
    write_json(out.file("colour.json"), d)
    out.finish({"scene": str(scene.source), "split": scene.split})
    d["out"] = str(out.path)
    return d


# ============================================================================ handlers
def _print_json(obj) -> None:
    sys.stdout.write(json.dumps(obj, indent=2) + "\n")


def cmd_weights(args: argparse.Namespace) -> int:
    from .edges import WeightMapConfig
    from .scene import load_scene

    scene = load_scene(args.scene, args.split)
    cfg = WeightMapConfig(alpha=args.alpha, beta=args.beta, gamma=args.gamma, lambda_reg=args.lambda_reg)
    s = priors_weights(scene, args.out, cfg, labels=args.labels, use_metal=not args.no_metal, force=args.force)
    if args.json:
        _print_json(s)
        return 0
    print(f"{'frame':<28} {'mean W':>7} {'W>0.7':>7} {'L_dist':>9}  labels  metal")
    for r in s["images"]:
        print(f"{r['key'][:28]:<28} {r['mean']:7.3f} {r['frac_above_tau']:7.3f} {r['distortion_loss']:9.5f}  "
              f"{r['labels']:<6}  {'yes' if r['metal'] else 'no'}")
    print(f"{len(s['images'])} weight maps (alpha={cfg.alpha}, beta={cfg.beta}, gamma={cfg.gamma}, "
          f"lambda_reg={cfg.lambda_reg}); mean L_distortion {s['mean_distortion_loss']:.5f} -> {s['out']}")
    return 0


def cmd_segment(args: argparse.Namespace) -> int:
    from .scene import list_splits, load_scene
    from .segment import TrainSegmenterConfig

    scene = load_scene(args.scene, args.split)
    eval_scene = None
    if args.eval_split != "none" and args.eval_split != args.split and args.eval_split in list_splits(args.scene):
        eval_scene = load_scene(args.scene, args.eval_split)
    tcfg = TrainSegmenterConfig(steps=args.steps, seed=args.seed, progress=True) if args.backend == "builtin" else None
    info = priors_segment(scene, args.out, args.backend, args.model, args.train_every, eval_scene, tcfg,
                          export_onnx=not args.no_onnx, force=args.force)
    if args.json:
        _print_json(info)
        return 0
    print(f"segmented {len(scene)} frames of '{scene.split}' with backend '{args.backend}' -> {info['out']}")
    for name in ("heldout", "eval"):
        if f"miou_{name}" in info:
            what = (f"{info['heldout_views']} held-out views of '{scene.split}'" if name == "heldout"
                    else f"{info['eval_views']} views of '{info['eval_split']}'")
            per = ", ".join(f"{c} {v:.3f}" if v is not None else f"{c} -" for c, v in info[f"per_class_{name}"].items())
            print(f"mIoU {info[f'miou_{name}']:.3f} on {what}  ({per})")
    if "onnx" in info:
        print(f"segmenter.onnx: opset {info['onnx']['opset']}, max |onnxruntime - torch| = {info['onnx']['max_abs_err']:.2e}")
    return 0


def cmd_colour(args: argparse.Namespace) -> int:
    from .colour import ColourConfig
    from .scene import load_scene

    scene = load_scene(args.scene, args.split)
    cfg = ColourConfig(detector=args.detector, gauge="reference" if args.reference is not None else args.gauge,
                       reference=args.reference or 0, srgb=scene.srgb, progress=True)
    d = priors_colour(scene, args.out, cfg, force=args.force)
    if args.json:
        _print_json(d)
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


# ============================================================================ parser
def _common(q: argparse.ArgumentParser) -> None:
    q.add_argument("scene", help="scene directory, transforms JSON, COLMAP model or tiny-NeRF .npz")
    q.add_argument("--split", default="train", help="split to process (default: train)")
    q.add_argument("--out", default=None, help="output directory (default: <scene>/priors/<stage>)")
    q.add_argument("--force", action="store_true", help="overwrite files in the output directory that dars did not write")
    q.add_argument("--json", action="store_true", help="print only JSON on stdout")


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``dars priors`` and its sub-commands (plus :data:`PRIORS_SUBCOMMANDS` and ``_cli_sh``)."""
    p = subparsers.add_parser("priors", help="prior stages: weights, segment, colour (light, sh-probe if installed)",
                              description="Prior stages on a scene; outputs go next to the scene unless --out.")
    sub = p.add_subparsers(dest="priors_command", metavar="STAGE")
    sub.required = True

    q = sub.add_parser("weights", help="distortion weight maps W (eqs. 2-4, 8) + heat-map overlays")
    _common(q)
    q.add_argument("--alpha", type=float, default=0.5, help="gradient weight (default 0.5)")
    q.add_argument("--beta", type=float, default=0.3, help="semantic edge weight (default 0.3)")
    q.add_argument("--gamma", type=float, default=0.2, help="metal mask weight (default 0.2)")
    q.add_argument("--lambda-reg", type=float, default=0.3, help="smoothness weight of eq. 8 (default 0.3)")
    q.add_argument("--labels", choices=["auto", "scene", "segment", "none"], default="auto",
                   help="labels for the semantic edges: scene's, predicted (priors/segment), or none (default: auto)")
    q.add_argument("--no-metal", action="store_true", help="ignore the scene's metal masks")
    q.set_defaults(func=cmd_weights)

    q = sub.add_parser("segment", help="7-class semantic labels (provided, builtin network, or an ONNX model)")
    _common(q)
    q.add_argument("--backend", choices=["provided", "builtin", "onnx"], default="provided")
    q.add_argument("--model", default=None, help="builtin: a trained segmenter.pt; onnx: the .onnx file")
    q.add_argument("--train-every", type=int, default=4, help="builtin: train on every n-th labelled view (default 4)")
    q.add_argument("--eval-split", default="test", help="also report mIoU on this split if labelled ('none' to skip)")
    q.add_argument("--steps", type=int, default=500, help="builtin: training steps (default 500)")
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--no-onnx", action="store_true", help="builtin: do not write segmenter.onnx")
    q.set_defaults(func=cmd_segment)

    q = sub.add_parser("colour", help="per-image exposure / white-balance gains against the scene's consensus")
    _common(q)
    q.add_argument("--detector", choices=["orb", "sift"], default="orb")
    q.add_argument("--gauge", choices=["median", "mean"], default="median",
                   help="median: the typical photo has gain 1 (default; robust to a few odd exposures); "
                        "mean: the geometric-mean gain is 1")
    q.add_argument("--reference", type=int, default=None,
                   help="fix this image's gain to 1 instead (overrides --gauge)")
    q.set_defaults(func=cmd_colour)

    from . import _cli_light  # stage 4, the light network

    if _cli_light.register not in PRIORS_SUBCOMMANDS:
        PRIORS_SUBCOMMANDS.append(_cli_light.register)
    for register in PRIORS_SUBCOMMANDS:
        _register(sub, register, None)
    try:  # the SH-probe engineer's module, when present
        from . import _cli_sh  # type: ignore
    except ImportError:
        _cli_sh = None
    if _cli_sh is not None and hasattr(_cli_sh, "add_parser") and _cli_sh.add_parser not in PRIORS_SUBCOMMANDS:
        _register(sub, _cli_sh.add_parser, getattr(_cli_sh, "main", None))
    return p


def _register(sub: argparse._SubParsersAction, register, default_func) -> None:
    before = set(sub.choices)
    register(sub)
    if default_func is not None:
        for name in set(sub.choices) - before:
            if sub.choices[name].get_default("func") is None:
                sub.choices[name].set_defaults(func=default_func)
