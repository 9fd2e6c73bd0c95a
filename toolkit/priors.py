"""The priors folder: the prior stages run on a scene, written next to it, and read back by the trainer.

Stages (each writes ``<scene>/priors/<stage>/`` or ``--out DIR``):

* :func:`priors_colour` — stage 2, per-image exposure / white-balance gains (``colour.json``);
* :func:`priors_segment` — stage 3, 7-class labels per frame (``<key>.png``, ``segment.json``);
* :func:`priors_light` — stage 4, the light network's SH estimate (``light.json``);
* :func:`priors_weights` — stage 6, distortion weight maps W (``<key>.npy``, ``weights.json``);
* :func:`sh_probe_json` — stage 5 on an HDR probe file (``dars priors sh-probe``).

Layout and ownership: :class:`OutputDir` / :func:`prepare_out_dir`, the one output-folder policy of
:mod:`toolkit.outputs`. Writes are atomic, and ``dars_manifest.json`` lists what dars wrote in a folder: a file that
exists but is not in the manifest is the user's and is never overwritten (``force`` only lets dars write beside such
files). Read-only scene folders fail early with a message suggesting ``--out``.

Reading: :func:`read_priors` gathers what the trainer uses (labels, metal masks, W maps, ``light.json``,
``colour.json``) from the scene and from ``priors_root/<stage>/`` (default: :meth:`toolkit.scene.Scene.priors_dir`);
:func:`labels_for` is the one place that decides where a frame's semantic labels come from.
"""

from __future__ import annotations

import json
import math
import os
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Literal

import numpy as np
import torch

from . import outputs
from ._checks import ConfigError, DarsError
from .io import atomic_write, linear_to_srgb, read_json, read_map, write_json, write_png
from .outputs import MANIFEST
from .pixels import PackedViews

if TYPE_CHECKING:
    from .scene import Scene

__all__ = ["OutputDir", "prepare_out_dir", "priors_path", "labels_for", "label_source", "frame_labels", "priors_weights", "priors_segment",
           "priors_colour", "priors_light", "sh_probe_json", "TrainingPriors", "read_priors", "TAU", "MANIFEST"]

TAU = 0.7
"""The sampler's high-distortion threshold (SPEC stage 7); ``weights.json`` reports the fraction of W above it."""
LabelSource = Literal["auto", "scene", "segment", "none"]


# ============================================================================ output directory handling
class OutputDir(outputs.OutputDir):
    """A priors output folder: :class:`toolkit.outputs.OutputDir` for the command ``priors STAGE`` (the one
    output-folder policy: new, empty or dars's; user files never overwritten; ``--force`` writes beside them)."""

    def __init__(self, path: str | os.PathLike, stage: str, force: bool = False, option: str = "--out"):
        super().__init__(path, f"priors {stage}", force=force, option=option)
        self.stage = stage

    def check(self, planned: Iterable[str] = ()) -> "OutputDir":
        try:
            return super().check(planned)
        except DarsError as e:
            if "read-only" in str(e) or "is a file" in str(e):
                raise DarsError(f"{e} (priors go next to the scene unless --out DIR: the scene folder may be "
                                "read-only, e.g. /work/shared/data)") from e
            raise


def prepare_out_dir(scene, stage: str, out: "str | os.PathLike | outputs.OutputDir | None", planned: Iterable[str],
                    force: bool = False) -> outputs.OutputDir:
    """The output folder for ``stage``: ``out`` or ``scene.priors_dir(stage)``, checked for ``planned`` (see
    :mod:`toolkit.outputs`). An :class:`~toolkit.outputs.OutputDir` passed as ``out`` is checked and returned.

    Raises:
        DarsError: the folder is not writable, holds other files (without ``force``), or holds a user's file that a
            planned output would replace.
    """
    if isinstance(out, outputs.OutputDir):
        return out.check(planned)
    path = Path(out) if out else scene.priors_dir(stage)
    return OutputDir(path, stage, force).check(planned)


def _progress(it, desc: str, total: int | None = None):
    from tqdm import tqdm

    return tqdm(it, desc=desc, total=total, file=sys.stderr, leave=False, disable=None)


def priors_path(scene: "Scene", stage: str, priors_root: str | os.PathLike | None = None) -> Path:
    """The folder of prior ``stage``: ``priors_root/<stage>`` when given, else ``scene.priors_dir(stage)``."""
    return Path(priors_root) / stage if priors_root is not None else scene.priors_dir(stage)


def labels_for(scene: "Scene", source: LabelSource, segment_dir: str | os.PathLike | None,
               frames: Iterable[int] | None = None) -> tuple[torch.Tensor | None, str]:
    """Semantic labels of some frames, all from one source.

    Args:
        scene: the scene.
        source: ``auto`` — the scene's labels (``semantic_path``) when every requested frame has them, else the
            predictions ``<segment_dir>/<key>.png`` when every requested frame has one, else none; ``scene`` or
            ``segment`` — that source (raises when a frame lacks it); ``none`` — no labels.
        segment_dir: folder of ``dars priors segment`` predictions (None: no predictions).
        frames: frame indices (default: every frame); they must share one size (see :func:`frame_labels` for one
            frame at a time).

    Returns:
        (int64 [n, H, W] class ids (255 unlabelled) or None, the source used: ``scene``, ``segment`` or ``none``).

    Raises:
        DarsError: ``source`` is ``scene`` or ``segment`` and a frame has no such labels.
    """
    idx = list(range(len(scene))) if frames is None else [int(i) for i in frames]
    src = label_source(scene, source, segment_dir, idx)
    if src == "none":
        return None, "none"
    return torch.stack([frame_labels(scene, i, src, segment_dir) for i in idx]), src


def label_source(scene: "Scene", source: LabelSource, segment_dir: str | os.PathLike | None,
                 frames: Iterable[int] | None = None) -> str:
    """Where the labels of ``frames`` come from (the rule of :func:`labels_for`, nothing decoded): ``scene``,
    ``segment`` or ``none``.

    Raises:
        DarsError: ``source`` is ``scene`` or ``segment`` and a frame has no such labels.
    """
    idx = list(range(len(scene))) if frames is None else [int(i) for i in frames]
    if source == "none":
        return "none"
    if source in ("auto", "scene") and all("semantic" in scene.frames[i].extras for i in idx):
        return "scene"
    files = [Path(segment_dir) / f"{scene.frames[i].key}.png" for i in idx] if segment_dir is not None else []
    if source in ("auto", "segment") and files and all(f.is_file() for f in files):
        return "segment"
    if source in ("scene", "segment"):
        missing = [i for i in idx if ("semantic" not in scene.frames[i].extras if source == "scene"
                                      else not (segment_dir is not None
                                                and (Path(segment_dir) / f"{scene.frames[i].key}.png").is_file()))]
        i = missing[0]
        raise DarsError(f"frame {i} ('{scene.frames[i].name}') has no {source} labels (use --labels auto or none)")
    return "none"


def frame_labels(scene: "Scene", i: int, source: Literal["scene", "segment"],
                 segment_dir: str | os.PathLike | None) -> torch.Tensor:
    """int64 [H, W] class ids of frame ``i`` from ``source`` (see :func:`label_source`). Predictions made at another
    image size (``dars priors segment`` run with another ``--downscale``) are resized to the frame's (nearest)."""
    if source == "scene":
        return scene.load_extra(i, "semantic")
    f = Path(segment_dir) / f"{scene.frames[i].key}.png"
    lab = read_map(f, f"predicted labels {f}")
    lab = np.asarray(lab[..., 0] if lab.ndim == 3 else lab)
    return torch.from_numpy(_fit_to_frame(scene, i, lab.astype(np.uint8), nearest=True).astype(np.int64))


def frame_metal(scene: "Scene", i: int, segment_dir: str | os.PathLike) -> torch.Tensor:
    """bool [H, W] predicted metal mask of frame ``i`` (``<segment_dir>/<key>_metal.png``, resized to the frame's
    size like :func:`frame_labels`)."""
    f = Path(segment_dir) / f"{scene.frames[i].key}_metal.png"
    m = np.asarray(read_map(f, f"predicted metal mask {f}"))
    m = (m[..., 0] if m.ndim == 3 else m) > 0
    return torch.from_numpy(_fit_to_frame(scene, i, m.astype(np.uint8), nearest=True) > 0)


def _fit_to_frame(scene: "Scene", i: int, arr: np.ndarray, nearest: bool) -> np.ndarray:
    """A prior map [h, w] of frame ``i`` resized to the frame's image size (a prior computed at another
    ``--downscale``): nearest for labels, area (shrinking) or linear (enlarging) for W."""
    h, w = int(scene.cameras.height[i]), int(scene.cameras.width[i])
    if arr.shape[:2] == (h, w):
        return arr
    import cv2

    ah, aw = arr.shape[:2]
    if abs(ah / h - aw / w) > 0.02 * max(ah / h, aw / w):
        raise DarsError(f"prior map of frame {i} ('{scene.frames[i].name}') is {aw}x{ah}, not a scaled copy of the "
                        f"{w}x{h} image; re-run the prior stage on this scene")
    interp = cv2.INTER_NEAREST if nearest else (cv2.INTER_AREA if ah > h else cv2.INTER_LINEAR)
    return cv2.resize(arr, (w, h), interpolation=interp)


# ============================================================================ colour (stage 2)
def priors_colour(scene, out_dir=None, cfg=None, force: bool = False) -> dict:
    """Estimate per-image colour transforms of ``scene`` and write ``colour.json``; returns its content.

    Args:
        scene: a loaded scene (camera poses choose the pairs to match).
        out_dir: output folder (path or :class:`OutputDir`; ``None``: ``scene.priors_dir("colour")``).
        cfg: :class:`toolkit.colour.ColourConfig`.
        force: write into a folder holding other files (beside them; never over them).
    """
    from .colour import ColourConfig, estimate_colour_transforms

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


# ============================================================================ segment (stage 3)
def priors_segment(scene, out_dir=None, backend: str = "shipped", model: str | None = None,
                   train_every: int = 4, eval_scene=None, train_cfg=None,
                   export_onnx: Callable[..., Any] | None = None, force: bool = False,
                   scene_prior: bool = True) -> dict:
    """Label every frame of ``scene`` and write ``<key>.png`` (uint8 ids), ``<key>_metal.png`` (the predicted metal
    mask, 0/255, networks with a metal channel), ``<key>_preview.png`` and ``segment.json`` (mIoU and metal IoU where
    ground truth exists, on frames the network was not trained on); for ``builtin`` also ``segmenter.pt`` and
    ``segmenter.onnx`` (with the ONNX parity figure).

    Args:
        scene: the frames to label.
        out_dir: output folder (path or :class:`OutputDir`; ``None``: ``scene.priors_dir("segment")``).
        backend: ``shipped`` (default: the shipped network, or ``model``, on any photos — no labels needed),
            ``builtin`` (fine-tune the shipped network, or ``model``, on every ``train_every``-th labelled frame),
            ``provided`` (the scene's own labels) or ``onnx`` (``model`` is the ONNX file).
        model: ``shipped``/``builtin``: a ``segmenter.pt`` instead of the shipped one; ``onnx``: the file (required).
        train_every: ``builtin``: train on every n-th labelled frame of ``scene``; mIoU is then reported on the other
            frames (``miou_heldout``).
        eval_scene: another labelled split (e.g. test) to report ``miou_eval`` on (not written).
        train_cfg: :class:`toolkit.segment.TrainSegmenterConfig`.
        export_onnx: for ``builtin``, the ONNX exporter that writes ``segmenter.onnx`` —
            ``export_onnx(net, path, image_size=(H, W))`` returning a report with ``path``, ``opset``,
            ``max_abs_err``, ``inputs_checked`` and ``file_size`` (``dars priors segment`` passes
            :func:`export.onnx.export_segmenter_onnx`; the toolkit itself never imports ``export``). None: no ONNX.
        force: write into a folder holding other files (beside them; never over them).
        scene_prior: relabel with the scene's own class prior (:func:`toolkit.segment.estimate_scene_prior`: EM over
            every photo of ``scene``, then every photo's and ``eval_scene``'s probabilities re-weighted by it), for a
            network that records the class prior it was trained under (the shipped one and ``builtin``
            fine-tunes); ``segment.json``'s ``scene_prior`` says what was done.

    Raises:
        DarsError / SegmentationError: unwritable folder, user files in the way, missing labels or model.
    """
    from .segment import (DEFAULT_SEGMENTER, METAL_THRESHOLD, SCENE_PRIOR_FLOOR, SegmentConfig, SegmentationError,
                          TrainSegmenterConfig, apply_scene_prior, estimate_scene_prior, load_segmenter, mean_iou,
                          metal_iou, save_segmenter, segment_images, segmenter_train_prior, train_segmenter)
    from .visualise import colourise_labels, tile

    if backend not in ("shipped", "builtin", "provided", "onnx"):
        raise SegmentationError(f"backend {backend!r}: choose 'shipped', 'builtin', 'provided' or 'onnx'")
    keys = [f.key for f in scene.frames]
    net = None
    if backend in ("shipped", "builtin"):
        net = load_segmenter(model)  # None: the shipped network
    with_metal = net is not None and net.cfg.metal
    planned = [f"{k}.png" for k in keys] + [f"{k}_preview.png" for k in keys] + ["segment.json", "contact_sheet.png"]
    planned += [f"{k}_metal.png" for k in keys] if with_metal else []
    if backend == "builtin":
        planned += ["segmenter.pt"] + (["segmenter.onnx"] if export_onnx is not None else [])
    out = prepare_out_dir(scene, "segment", out_dir, planned, force)
    has_gt = scene.has_extra("semantic")
    info: dict = {"scene": str(scene.source), "split": scene.split, "backend": backend}
    if net is not None:
        info["model"] = str(model) if model else f"shipped ({DEFAULT_SEGMENTER.name})"
        info["metal_mask"] = "predicted" if with_metal else "none (the network has no metal channel)"
        if with_metal:
            info["metal_threshold"] = METAL_THRESHOLD
    train_idx: list[int] = []
    if backend == "builtin":
        if not has_gt:
            raise SegmentationError(
                f"{scene.source}: backend 'builtin' fine-tunes on labelled views, but split '{scene.split}' has no "
                "semantic_path labels; use the default backend 'shipped' (no labels needed)")
        if train_every < 1:
            raise SegmentationError(f"--train-every {train_every} must be >= 1")
        train_idx = list(range(0, len(scene), train_every))
        hw = [(int(h), int(w)) for h, w in zip(scene.cameras.height, scene.cameras.width)]
        train_idx = [i for i in train_idx if hw[i] == hw[train_idx[0]]]
        imgs = scene.load_images(train_idx)  # photos of one size (the first's) train it; it segments any size
        labs = torch.stack([scene.load_extra(i, "semantic") for i in train_idx])
        metal = (torch.stack([scene.load_extra(i, "metal").bool() for i in train_idx])
                 if with_metal and all("metal" in scene.frames[i].extras for i in train_idx) else None)
        cfg = train_cfg or TrainSegmenterConfig(progress=True, lr=1e-3)
        res = train_segmenter(imgs, labs, cfg, model=net, metal=metal)
        net = res.model
        info.update(train_views=[scene.frames[i].key for i in train_idx], train_seconds=round(res.seconds, 1),
                    train_miou=res.train_miou, final_loss=float(np.mean(res.losses[-20:])) if res.losses else None,
                    parameters=net.num_parameters(), train_config=asdict(cfg),
                    ground_truth_inputs=f"labels{' and metal masks' if metal is not None else ''} of the "
                                        f"{len(train_idx)} training views (fine-tuning)")
        net.meta = {**getattr(net, "meta", {}), "class_pixels": res.class_pixels, "class_balance": cfg.class_balance}
        save_segmenter(out.file("segmenter.pt"), net, {"scene": str(scene.source), "fine_tuned_from": info["model"],
                                                       "class_pixels": res.class_pixels,
                                                       "class_balance": cfg.class_balance})
        if export_onnx is not None:
            h, w = scene.image_size
            rep = export_onnx(net, out.file("segmenter.onnx"), image_size=(h, w))
            info["onnx"] = {"path": str(rep.path), "opset": rep.opset, "max_abs_err": rep.max_abs_err,
                            "inputs_checked": rep.inputs_checked, "file_size": rep.file_size}
    elif backend == "onnx":
        if not model:
            raise SegmentationError("backend 'onnx' needs --model FILE.onnx")
        info["model"] = str(model)
    scfg = SegmentConfig(backend="builtin" if backend == "shipped" else backend)

    def _run(img):
        return segment_images(img[None], scfg, model=net if net is not None else model)

    prior_t = segmenter_train_prior(net) if net is not None else None
    prior_s = None
    if backend == "provided" or not scene_prior:
        info["scene_prior"] = {"applied": False, "reason": "provided labels" if backend == "provided" else
                               "turned off (--scene-prior off)"}
    elif prior_t is None:
        info["scene_prior"] = {"applied": False, "reason": "the network records no training class prior (an ONNX "
                               "model, or weights saved without class_pixels)"}
    else:  # pass 1: the scene's class prior from a subsample of every photo's probabilities
        samples = []
        for i in _progress(range(len(scene)), "segment (scene prior)", len(scene)):
            pr = _run(scene.load_image(i)).probabilities[0]
            step = max(1, int(math.sqrt(pr.shape[1] * pr.shape[2] / 4096)))
            samples.append(pr[:, ::step, ::step].reshape(pr.shape[0], -1).T)
        prior_s = estimate_scene_prior(torch.cat(samples), prior_t, SCENE_PRIOR_FLOOR)
        info["scene_prior"] = {"applied": True, "floor": SCENE_PRIOR_FLOOR,
                               "train_prior": [round(float(v), 5) for v in prior_t],
                               "scene_prior": [round(float(v), 5) for v in prior_s],
                               "pixels": int(sum(x.shape[0] for x in samples))}

    def _labels(seg):
        if prior_s is None:
            return seg.labels[0]
        return apply_scene_prior(seg.probabilities, prior_s, prior_t)[0].max(0).indices  # first max, as argmax

    preds, gts, mpred, mgt = [], [], [], []
    sheet_idx = set(np.linspace(0, len(scene) - 1, min(8, len(scene))).round().astype(int).tolist())
    sheet_rows = []
    for i in _progress(range(len(scene)), "segment", len(scene)):
        f = scene.frames[i]
        img = scene.load_image(i)
        gt = scene.load_extra(i, "semantic") if "semantic" in f.extras else None
        if backend == "provided":
            if gt is None:
                raise SegmentationError(f"frame {i} ('{f.name}') has no semantic_path labels for backend 'provided'")
            seg = segment_images(img[None], scfg, labels=gt[None])
        else:
            seg = _run(img)
        lab = _labels(seg)
        write_png(out.file(f"{f.key}.png"), lab.numpy().astype(np.uint8))
        row = [img.permute(1, 2, 0).numpy(), colourise_labels(lab)]
        if seg.metal is not None:
            m = seg.metal[0] > METAL_THRESHOLD
            write_png(out.file(f"{f.key}_metal.png"), m.numpy().astype(np.uint8) * 255)
            row.append(np.repeat(m.numpy()[..., None].astype(np.float32), 3, axis=2))
        if gt is not None:
            row.append(colourise_labels(gt))
        write_png(out.file(f"{f.key}_preview.png"), tile([row]))
        if i in sheet_idx and row[0].shape == (sheet_rows[0][0].shape if sheet_rows else row[0].shape):
            sheet_rows.append(row)
        if gt is not None and i not in train_idx:
            preds.append(lab)
            gts.append(gt)
            if seg.metal is not None and "metal" in f.extras:
                mpred.append(seg.metal[0] > METAL_THRESHOLD)
                mgt.append(scene.load_extra(i, "metal").bool())
    from .scene import SEMANTIC_CLASSES

    def _report(name, p, g, mp, mg):
        """miou_<name>, per_class_<name> and, when every scored frame has a true metal mask, metal_iou_<name>."""
        flat = lambda maps: torch.cat([x.reshape(-1) for x in maps])  # noqa: E731
        miou, per = mean_iou(flat(p), flat(g))
        info[f"miou_{name}"] = miou
        info[f"per_class_{name}"] = {c: (None if v != v else v) for c, v in zip(SEMANTIC_CLASSES, per)}
        if mg and len(mg) == len(g):
            info[f"metal_iou_{name}"] = metal_iou(flat(mp), flat(mg), flat(g))

    if gts:
        _report("heldout", preds, gts, mpred, mgt)
        info["heldout_views"] = len(gts)
    if eval_scene is not None and eval_scene.has_extra("semantic") and backend != "provided":
        ep, eg, emp, emg = [], [], [], []
        for i in _progress(range(len(eval_scene)), f"segment eval ({eval_scene.split})", len(eval_scene)):
            seg = _run(eval_scene.load_image(i))
            ep.append(_labels(seg))
            eg.append(eval_scene.load_extra(i, "semantic"))
            if seg.metal is not None and "metal" in eval_scene.frames[i].extras:
                emp.append(seg.metal[0] > METAL_THRESHOLD)
                emg.append(eval_scene.load_extra(i, "metal").bool())
        _report("eval", ep, eg, emp, emg)
        info["eval_split"] = eval_scene.split
        info["eval_views"] = len(eg)
    if sheet_rows:
        from .visualise import labelled_sheet

        cols = ["photo", "labels"] + (["metal mask"] if with_metal else []) + (["ground truth (scored only)"]
                                                                               if len(sheet_rows[0]) > 2 + with_metal else [])
        write_png(out.file("contact_sheet.png"), labelled_sheet(sheet_rows, cols))
    info["out"] = str(out.path)
    write_json(out.file("segment.json"), info)
    out.finish({"scene": str(scene.source), "split": scene.split})
    return info


# ============================================================================ all a run needs, from photos alone
def scene_has_priors(scene: "Scene", priors_root: str | os.PathLike | None = None) -> bool:
    """True when ``priors_root`` (default: next to the scene) holds a segmentation or a light estimate."""
    return any((priors_path(scene, stage, priors_root) / name).is_file()
               for stage, name in (("segment", "segment.json"), ("light", "light.json")))


def compute_priors(scene: "Scene", root: str | os.PathLike, segmenter: str | os.PathLike | None = None,
                   light_weights: str | os.PathLike | None = None, force: bool = False, log=None) -> dict:
    """The priors a run needs, from the photos alone, into ``root``: ``segment/`` (labels and metal masks of the
    shipped segmenter, or ``segmenter``) and ``light/`` (the SH estimate of the shipped light network, or
    ``light_weights``); ``root/priors.json`` records which model produced each. W maps are not written: training
    computes them from the photos and these predictions (eqs. 2-4, 8). No ground truth is read (scene labels are
    only scored in ``segment.json`` when present).

    Returns:
        the content of ``priors.json``.
    """
    import time

    from .segment import DEFAULT_SEGMENTER

    log = log or (lambda m: print(m, file=sys.stderr))
    root = Path(root)
    t0 = time.time()
    seg = priors_segment(scene, root / "segment", "shipped", model=str(segmenter) if segmenter else None, force=force)
    t1 = time.time()
    light = priors_light(scene, root / "light", weights=str(light_weights) if light_weights else None, force=force)
    t2 = time.time()
    rec = {
        "scene": str(scene.source), "split": scene.split,
        "segment": {"model": str(segmenter) if segmenter else str(DEFAULT_SEGMENTER), "seconds": round(t1 - t0, 1),
                    "metal_mask": seg.get("metal_mask"), "miou_vs_scene_labels": seg.get("miou_heldout")},
        "light": {"model": light["model"]["path"], "seconds": round(t2 - t1, 1), "coeffs": light["coeffs"]},
        "photos": ("composited on the background by their masks (an object captured with masks)"
                   if scene.masks == "alpha" and any("mask" in f.extras for f in scene.frames) else "as they are"),
        "weights": "computed by training from the photos and the predicted labels and metal masks",
        "ground_truth_inputs": "none",
    }
    write_json(root / "priors.json", rec)
    miou = seg.get("miou_heldout")
    log(f"[dars] priors from the photos -> {root}: labels + metal masks ({rec['segment']['model']}, "
        f"{t1 - t0:.0f} s{f'; mIoU {miou:.2f} against the scene labels, which are not used' if miou is not None else ''}), "
        f"light ({t2 - t1:.0f} s)")
    return rec


# ============================================================================ layout (the room's box)
def priors_layout(scene, out_dir=None, cfg=None, force: bool = False, log=None) -> dict:
    """Fit the room's box (:func:`toolkit.layout.fit_room_layout`) and write ``layout.json`` and ``layout.png``
    (each face's sweep, and photos tinted by the face their pixels' rays leave through); returns the JSON.

    ``dars train --layout-depth W --priors DIR`` reads ``DIR/layout/layout.json`` instead of fitting the box again
    (:func:`read_layout`), so several runs on one scene share one fit. The record holds every photo's camera centre
    so that a box fitted in another frame (another ``--no-upright``) or on other photos is refused.
    """
    from .bounds import triangulate_sparse_points
    from .layout import FACE_NAMES, LayoutConfig, fit_room_layout, plot_layout

    cfg = cfg or LayoutConfig()
    out = prepare_out_dir(scene, "layout", out_dir, ["layout.json", "layout.png"], force)
    points = triangulate_sparse_points(scene, log=log)
    room = fit_room_layout(scene, points.points, cfg, log=log)
    d = room.to_json()
    d["curves"] = {n: {"offsets": np.asarray(c[0]).tolist(),
                       "costs": [float(x) if np.isfinite(x) else None for x in np.asarray(c[1])]}
                   for n, c in zip(FACE_NAMES, room.curves) if c is not None}
    d.update(scene=str(scene.source), split=scene.split, config=asdict(cfg), sparse_points=int(len(points.points)),
             cameras={f.key: [round(float(x), 6) for x in c]
                      for f, c in zip(scene.frames, scene.cameras.c2w[:, :3, 3].double().tolist())},
             usage="dars train --layout-depth W --priors DIR; toolkit.layout.RoomLayout.from_json",
             ground_truth_inputs="none")
    write_json(out.file("layout.json"), d)
    plot_layout(scene, room, out.file("layout.png"))
    out.finish({"scene": str(scene.source), "split": scene.split})
    d["out"] = str(out.path)
    return d


def read_layout(scene: "Scene", priors_root: str | os.PathLike | None = None):
    """The room's box of ``dars priors layout`` (``<priors>/layout/layout.json``) as a
    :class:`toolkit.layout.RoomLayout`, or None when there is none.

    Raises:
        DarsError: a damaged record, or one fitted on other photos or in another frame than ``scene``'s (a photo of
            ``scene`` it does not list, or a camera more than 0.1 % of the capture's extent from where it was)."""
    from .layout import RoomLayout

    path = priors_path(scene, "layout", priors_root) / "layout.json"
    if not path.is_file():
        return None
    d = read_json(path, "priors layout.json", _rerun("layout", scene))
    cams = d.get("cameras")
    if not isinstance(cams, dict):
        raise DarsError(f"priors layout.json {path} lists no camera centres; {_rerun('layout', scene)}")
    missing = [f.key for f in scene.frames if f.key not in cams]
    if missing:
        raise DarsError(f"{path} was fitted on other photos: it has no frame {missing[:3]}"
                        f"{' ...' if len(missing) > 3 else ''}; {_rerun('layout', scene)}")
    have = scene.cameras.c2w[:, :3, 3].double().numpy()
    rec = np.array([cams[f.key] for f in scene.frames], np.float64).reshape(-1, 3)
    extent = float(np.ptp(have, axis=0).max()) if len(have) > 1 else 1.0
    off = float(np.abs(rec - have).max())
    if off > 1e-3 * max(extent, 1e-3):
        raise DarsError(f"{path} was fitted in another frame: a camera lies {off:.3g} scene units from where this "
                        "scene puts it (the scene loaded with another --no-upright, or its poses changed); "
                        + _rerun("layout", scene))
    try:
        return RoomLayout.from_json(d)
    except ConfigError as e:
        raise DarsError(f"priors layout.json {path}: {e}; {_rerun('layout', scene)}") from e


# ============================================================================ light (stage 4)
OUT_OF_DOMAIN_RGBA = ("the photos are RGBA with transparency (an object on a known background): the light network "
                      "was trained on whole photos of rooms and reads the background colour as light, so this "
                      "estimate is out of its domain; dars train does not use it and starts from the grey ambient "
                      "of the object pixels")
"""Why a light estimate of photos with transparency is flagged (``light.json``'s ``out_of_domain``)."""


def priors_light(scene, out_dir=None, weights: str | None = None, reduce: str = "mean", batch_size: int = 32,
                 force: bool = False) -> dict:
    """Estimate the scene's SH lighting with the light network and write ``light.json``; returns its content.
    On RGBA photos with transparency the estimate is flagged ``out_of_domain`` (:data:`OUT_OF_DOMAIN_RGBA`).

    Args:
        scene: a loaded :class:`toolkit.scene.Scene` (sRGB photos; linear HDR scenes are clipped to [0, 1] and
            sRGB-encoded first, as the network was trained on 8-bit-style photos).
        out_dir: output folder (path or :class:`OutputDir`; ``None``: ``scene.priors_dir("light")``).
        weights: a file written by :func:`toolkit.lightnet.save_lightnet` (``None``: the shipped weights).
        reduce: ``mean`` or ``median`` of the per-image predictions.
        batch_size: images per forward pass (images are loaded batch by batch).
        force: write into a folder holding other files (beside them; never over them).

    Raises:
        LightNetError: missing or corrupt weights; DarsError: unwritable folder, user files in the way.
    """
    from .lightnet import DEFAULT_WEIGHTS, aggregate_sh, load_lightnet, mean_colour_sh, predict_sh
    from .metrics import env_light_l2
    from .scene import photos_have_transparency

    if reduce not in ("mean", "median"):
        raise ConfigError(f"--reduce {reduce!r}: choose 'mean' or 'median'")
    model = load_lightnet(weights)  # fail before touching the output folder
    out = prepare_out_dir(scene, "light", out_dir, ["light.json"], force)
    per, base_b = [], []
    for i in _progress(range(0, len(scene), batch_size), "light", (len(scene) + batch_size - 1) // batch_size):
        batch = [scene.load_image(j) for j in range(i, min(i + batch_size, len(scene)))]
        for k0 in range(len(batch)):  # runs of photos of one size (portrait and landscape may alternate)
            if k0 and batch[k0].shape == batch[k0 - 1].shape:
                continue
            k1 = k0 + 1
            while k1 < len(batch) and batch[k1].shape == batch[k0].shape:
                k1 += 1
            imgs = torch.stack(batch[k0:k1]).float()
            if not scene.srgb:
                imgs = linear_to_srgb(imgs.clamp(0.0, 1.0))
            per.append(predict_sh(model, imgs, batch_size, c2w=scene.cameras.c2w[i + k0:i + k1]))
            base_b.append(mean_colour_sh(imgs))
    per_image = torch.cat(per)
    coeffs = aggregate_sh(per_image, reduce)
    meta = model.meta
    info: dict = {
        "coeffs": coeffs.tolist(),
        "source": "lightnet",
        "reduce": reduce,
        "per_image": [{"key": f.key, "coeffs": c.tolist()} for f, c in zip(scene.frames, per_image)],
        "model": {"path": str(Path(weights) if weights else DEFAULT_WEIGHTS), "arch": model.cfg.name,
                  "parameters": model.num_parameters(), "input_size": model.cfg.input_size,
                  "output_range": model.cfg.output_range, "frame": model.cfg.frame,
                  "training_command": meta.get("training_command"),
                  "heldout_env_light_l2": meta.get("heldout_env_light_l2")},
        "scene": str(scene.source), "split": scene.split, "views": len(scene),
        "convention": "real SH order 2, SPEC order, incident radiance, world frame +z up, coeffs 9 x [r, g, b]",
        "note": ("bands 1-2 predicted relative to each photo's heading and turned into the world frame with its pose"
                 if model.cfg.frame == "heading" else
                 "world-frame bands 1-2 are only meaningful for rooms like the one the network was trained on"),
        "evaluation": None,
    }
    if photos_have_transparency(scene):
        info["out_of_domain"] = OUT_OF_DOMAIN_RGBA
        print(f"[dars] light: {OUT_OF_DOMAIN_RGBA}", file=sys.stderr)
    if scene.sh is not None:
        gt = scene.sh.float()
        ev = {"env_light_l2": float(env_light_l2(coeffs, gt)),
              "env_light_l2_per_image_mean": float(env_light_l2(per_image, gt[None].expand_as(per_image)).mean()),
              "baseline_mean_colour": float(env_light_l2(aggregate_sh(torch.cat(base_b), reduce), gt))}
        if "train_mean_sh" in meta:
            ev["baseline_train_mean_sh"] = float(env_light_l2(torch.tensor(meta["train_mean_sh"]).float(), gt))
        ev["gt"] = gt.tolist()
        info["evaluation"] = ev
    info["out"] = str(out.path)
    write_json(out.file("light.json"), info)
    out.finish({"scene": str(scene.source), "split": scene.split})
    return info


# ============================================================================ SH probe (stage 5)
def sh_probe_json(path: str | os.PathLike, layout: str, rotate_x_deg: float) -> dict[str, Any]:
    """Fit order-2 SH to the HDR environment map at ``path``; returns the ``dars priors sh-probe`` JSON document
    (``coeffs`` 9 x [r, g, b] in the SPEC convention, the three.js and glTF forms, ...). Nothing is written.

    Args:
        path: a Radiance ``.hdr`` or OpenEXR ``.exr`` file.
        layout: ``latlong`` (SPEC lat-long) or ``angular`` (a light probe).
        rotate_x_deg: rotate the map's directions about +x first (90 for a +y-up probe).
    """
    path = Path(path)
    from .sh import fit_sh_probe, read_envmap, rotation_x, sh_to_gltf_ibl, sh_to_threejs_lightprobe

    image = read_envmap(path)
    rotation = rotation_x(rotate_x_deg) if rotate_x_deg else None
    probe = fit_sh_probe(image, layout=layout, rotation=rotation)
    return {
        "coeffs": probe.to_list(),
        "file": str(path),
        "layout": layout,
        "rotate_x_deg": float(rotate_x_deg),
        "shape": list(probe.source_shape),
        "dc_irradiance": [float(v) for v in probe.dc_irradiance.tolist()],
        "convention": "real SH order 2, SPEC order, incident radiance, world +z up, coeffs 9 x [r, g, b]",
        "threejs": sh_to_threejs_lightprobe(probe.coeffs),
        "gltf": sh_to_gltf_ibl(probe.coeffs),
    }


# ============================================================================ weights (stage 6)
def priors_weights(scene, out_dir=None, cfg=None, labels: str = "auto", use_metal: bool = True,
                   force: bool = False, metal: str = "auto", segment_dir: str | os.PathLike | None = None) -> dict:
    """Write distortion weight maps of every frame: ``<key>.npy`` (float16 W), ``<key>_overlay.png`` and
    ``weights.json``; returns the summary written to ``weights.json``.

    Args:
        scene: a loaded :class:`toolkit.scene.Scene`.
        out_dir: output folder (path or :class:`OutputDir`; ``None``: ``scene.priors_dir("weights")``).
        cfg: :class:`toolkit.edges.WeightMapConfig` (default config if ``None``).
        labels: ``auto`` (the predictions in ``segment_dir`` when every frame has one, else none), ``segment``,
            ``scene`` (the scene's ground-truth labels: experiments only, recorded in ``weights.json``) or ``none``.
        use_metal: False: no metal term (as ``metal="none"``).
        force: write into a folder holding other files (beside them; never over them).
        metal: the metal mask of eq. 4: ``auto`` (predicted ``<key>_metal.png`` in ``segment_dir`` when every frame
            has one, else none), ``scene`` (ground truth, experiments only) or ``none``.
        segment_dir: folder of ``dars priors segment`` outputs (default: ``scene.priors_dir("segment")``).

    Raises:
        DarsError: the folder is not writable, or holds files of the user's that would be overwritten.
    """
    from .edges import WeightMapConfig, weight_map, weight_overlay

    cfg = cfg or WeightMapConfig()
    keys = [f.key for f in scene.frames]
    out = prepare_out_dir(scene, "weights", out_dir,
                          [f"{k}.npy" for k in keys] + [f"{k}_overlay.png" for k in keys] + ["weights.json"], force)
    seg_dir = Path(segment_dir) if segment_dir is not None else scene.priors_dir("segment")
    if labels == "auto":  # predictions, never the scene's ground truth unless asked for
        labels = "segment" if all((seg_dir / f"{f.key}.png").is_file() for f in scene.frames) else "none"
    if metal not in ("auto", "scene", "segment", "none"):
        raise ConfigError(f"metal={metal!r}: choose 'auto', 'scene', 'segment' or 'none'")
    metal_files = [seg_dir / f"{f.key}_metal.png" for f in scene.frames]
    if not use_metal:
        metal = "none"
    elif metal == "auto":
        metal = "segment" if all(p.is_file() for p in metal_files) else "none"
    if metal == "segment" and not all(p.is_file() for p in metal_files):
        raise DarsError(f"no predicted metal masks in {seg_dir} (<key>_metal.png); run `dars priors segment` first")
    if metal == "scene" and not scene.has_extra("metal"):
        raise DarsError(f"{scene.source} has no metal_path masks; use --metal auto or none")
    rows = []
    for i in _progress(range(len(scene)), "weights", len(scene)):
        f = scene.frames[i]
        img = scene.load_image(i)
        lab, lab_src = labels_for(scene, labels, seg_dir, [i])  # [1, H, W] or None
        if metal == "scene":
            mask = scene.load_extra(i, "metal")
        elif metal == "segment":
            mask = frame_metal(scene, i, seg_dir)
        else:
            mask = None
        wm = weight_map(img[None], lab, None if mask is None else mask[None], cfg)
        w = wm.weights[0]
        _save_npy(out.file(f"{f.key}.npy"), w.numpy().astype(np.float16))
        write_png(out.file(f"{f.key}_overlay.png"), weight_overlay(img, w))
        rows.append({"key": f.key, "name": f.name, "mean": float(w.mean()), "frac_above_tau": float((w > TAU).float().mean()),
                     "distortion_loss": float(wm.distortion_loss[0]), "labels": lab_src, "metal": mask is not None})
    gt = [w for w, src in (("labels", labels), ("metal masks", metal)) if src == "scene"]
    summary = {
        "scene": str(scene.source), "split": scene.split, "tau": TAU, "config": asdict(cfg),
        "labels": {"segment": f"predicted ({seg_dir})", "scene": "ground truth (scene)"}.get(labels, "none"),
        "metal": {"segment": f"predicted ({seg_dir})", "scene": "ground truth (scene)"}.get(metal, "none"),
        "ground_truth_inputs": " and ".join(gt) if gt else "none",
        "distortion_loss_definition": "lambda_reg * (sum (D_x W)^2 + sum (D_y W)^2) / (H W), per image",
        "mean_distortion_loss": float(np.mean([r["distortion_loss"] for r in rows])) if rows else 0.0,
        "mean_weight": float(np.mean([r["mean"] for r in rows])) if rows else 0.0,
        "images": rows, "out": str(out.path),
    }
    write_json(out.file("weights.json"), summary)
    out.finish({"scene": str(scene.source), "split": scene.split})
    return summary


def _save_npy(path: Path, arr) -> None:
    with atomic_write(path) as fh:
        np.save(fh, arr)


# ============================================================================ reading (the trainer)
@dataclass
class TrainingPriors:
    """What the trainer reads from a scene and its priors folder (:func:`read_priors`).

    Per-pixel priors are packed (:class:`toolkit.pixels.PackedViews`: the views one after another, each its own size).

    Attributes:
        labels: uint8 [P] class ids (255 unlabelled), or None.
        labels_source: ``provided`` (the scene's), ``predicted (<dir>)``, ``none`` or ``off``.
        metal: bool [P] metal masks (the scene's or predicted), or None.
        metal_source: ``provided``, ``predicted (<dir>)`` or ``none``.
        weights: uint8 [P] W maps of ``dars priors weights`` (``quantised``: ``round(255 W)``, read back as floats in
            [0, 1]; rank-normalised first when asked, see :func:`read_priors`), or None (not there, or not asked for).
            Maps written at another image size (another ``--downscale``) are resized to the frames'.
        distortion: float [V] L_distortion of each loaded map (0 where ``weights.json`` lacks it), or None.
        weights_source: ``loaded (<dir>)`` or None.
        light: float32 [9, 3] SH coefficients of ``light.json``, or None.
        light_source: ``light network (<file>)`` or None.
        colour: per-frame :class:`toolkit.colour.ColourTransforms` of ``colour.json`` in scene frame order, or None.
        colour_source: ``loaded (<file>)`` or None.
    """

    labels: PackedViews | None
    labels_source: str
    metal: PackedViews | None
    weights: PackedViews | None = None
    distortion: torch.Tensor | None = None
    weights_source: str | None = None
    light: torch.Tensor | None = None
    light_source: str | None = None
    colour: Any = None
    colour_source: str | None = None
    metal_source: str = "none"


def read_priors(scene: "Scene", priors_root: str | os.PathLike | None = None, *, labels: LabelSource | None = "auto",
                weights: bool = True, colour: bool = True, metal: str = "scene",
                weights_normalise: Literal["quantile", "none"] = "none") -> TrainingPriors:
    """Read the priors of ``scene`` for training, file by file into packed buffers (nothing is computed here).

    Args:
        scene: the training split (its frames may differ in size).
        priors_root: folder holding ``<stage>/`` outputs (default: ``scene.priors_dir(stage)``).
        labels: label source for :func:`labels_for` over every frame (predictions from ``segment/``); None: semantics
            off (``labels_source`` ``off``).
        weights: read ``weights/<key>.npy`` (used only when every frame has one).
        weights_normalise: how each W map is normalised (:func:`toolkit.edges.normalise_weight_map`: clamped to
            [0, 1], rank-normalised for ``quantile``) on the full-precision map, before it is stored at 8 bits.
        colour: read ``colour/colour.json``.
        metal: where the metal mask comes from: ``scene`` (the scene's ``metal_path`` ground truth, when every frame
            has one), ``segment`` (``segment/<key>_metal.png`` predictions, when every frame has one) or ``none``.

    Raises:
        DarsError: ``colour.json`` lacks a transform for a frame of the scene, or a prior map is not a scaled copy
            of its frame.
    """
    V = len(scene)
    hs, ws = scene.cameras.height, scene.cameras.width
    labs = None
    if labels is None:
        lab_src = "off"
    else:
        seg_dir = priors_path(scene, "segment", priors_root)
        src = label_source(scene, labels, seg_dir)
        if src != "none":
            labs = PackedViews.allocate(hs, ws, dtype=torch.uint8)
            for i in range(V):
                labs.write(i, frame_labels(scene, i, src, seg_dir))
        lab_src = {"scene": "provided", "segment": f"predicted ({seg_dir})"}.get(src, "none")
    metal_mask, metal_src = None, "none"
    if metal == "scene" and scene.has_extra("metal"):
        metal_mask, metal_src = PackedViews.allocate(hs, ws, dtype=torch.bool), "provided"
        for i in range(V):
            metal_mask.write(i, scene.load_extra(i, "metal"))
    elif metal == "segment":
        seg_dir = priors_path(scene, "segment", priors_root)
        mfiles = [seg_dir / f"{f.key}_metal.png" for f in scene.frames]
        if all(p.is_file() for p in mfiles):
            metal_mask = PackedViews.allocate(hs, ws, dtype=torch.bool)
            for i in range(V):
                metal_mask.write(i, frame_metal(scene, i, seg_dir))
            metal_src = f"predicted ({seg_dir})"
    out = TrainingPriors(labels=labs, labels_source=lab_src, metal=metal_mask)
    out.metal_source = metal_src
    wdir = priors_path(scene, "weights", priors_root)
    wfiles = [wdir / f"{f.key}.npy" for f in scene.frames]
    if weights and wdir.is_dir() and all(p.is_file() for p in wfiles):
        from .edges import normalise_weight_map

        out.weights = PackedViews.allocate(hs, ws, quantised=True)
        resized = 0
        for i, p in enumerate(wfiles):
            w = _read_weight_map(p)
            fitted = _fit_to_frame(scene, i, w, nearest=False)
            resized += fitted.shape != w.shape
            fitted = torch.from_numpy(np.ascontiguousarray(fitted))
            out.weights.write(i, normalise_weight_map(fitted, weights_normalise))  # ranked before the 8-bit write
        meta_p = wdir / "weights.json"
        out.distortion = torch.zeros(V)
        if meta_p.is_file():
            meta = read_json(meta_p, "priors weights.json", _rerun("weights", scene))
            try:
                per = {d["key"]: float(d.get("distortion_loss", 0.0)) for d in meta.get("images", []) if "key" in d}
            except (TypeError, ValueError, AttributeError) as e:
                raise DarsError(f"priors weights.json {meta_p} has a malformed 'images' list ({e}); "
                                f"{_rerun('weights', scene)}") from e
            out.distortion = torch.tensor([per.get(f.key, 0.0) for f in scene.frames])
        out.weights_source = f"loaded ({wdir})" + (f", {resized} resized to the frames' size" if resized else "")
    light_json = priors_path(scene, "light", priors_root) / "light.json"
    if light_json.is_file():
        d = read_json(light_json, "priors light.json", _rerun("light", scene))
        try:
            from .sh import check_sh_coeffs

            out.light = torch.from_numpy(check_sh_coeffs(d["coeffs"], "coeffs")).float()
        except (KeyError, TypeError, ValueError) as e:
            raise DarsError(f"priors light.json {light_json} has no valid 'coeffs' ({e}); "
                            f"{_rerun('light', scene)}") from e
        out.light_source = f"light network ({light_json})"
    cjson = priors_path(scene, "colour", priors_root) / "colour.json"
    if colour and cjson.is_file():
        from .colour import ColourTransforms

        doc = read_json(cjson, "priors colour.json", _rerun("colour", scene))
        try:
            tr = ColourTransforms.from_json(doc)
        except (KeyError, TypeError, ValueError, IndexError, RuntimeError) as e:
            raise DarsError(f"priors colour.json {cjson} is not a colour estimate dars can read ({e}); "
                            f"{_rerun('colour', scene)}") from e
        if tr.keys is not None:
            order = {k: i for i, k in enumerate(tr.keys)}
            missing = [f.key for f in scene.frames if f.key not in order]
            if missing:
                raise DarsError(f"{cjson} has no colour transform for frames {missing[:5]}; re-run `dars priors colour`")
            tr = tr.subset([order[f.key] for f in scene.frames])
        out.colour, out.colour_source = tr, f"loaded ({cjson})"
    return out


def _rerun(stage: str, scene: "Scene") -> str:
    return f"re-run `dars priors {stage} {scene.source}` (or delete the file to train without it)"


def _read_weight_map(path: Path) -> np.ndarray:
    """A W map written by :func:`priors_weights`, as float32 [H, W] (a damaged file names itself; the size is checked
    against its frame by :func:`_fit_to_frame`, which resizes a map made at another ``--downscale``)."""
    try:
        w = np.asarray(np.load(path, allow_pickle=False), dtype=np.float32)
    except Exception as e:  # noqa: BLE001 - numpy raises several types for a damaged .npy
        raise DarsError(f"priors weight map {path} is truncated or corrupt ({e}); re-run `dars priors weights` "
                        "(or delete the weights folder: the trainer then computes W itself)") from e
    if w.ndim != 2:
        raise DarsError(f"priors weight map {path} has shape {list(w.shape)}, not [H, W]; re-run `dars priors weights` "
                        "on this scene")
    return w
