"""Stage 12 — evaluation of a trained run (paper section III.C; Tables 5-6, Figs. 6-8).

:func:`evaluate_run` renders every view of a split with the run's render sampler and computes every metric the data
supports, with the functions of :mod:`toolkit.metrics` (it never re-implements a metric):

=====================  ===============================================================================================
key                    definition (computed when ...)
=====================  ===============================================================================================
``psnr``               mean over views of the per-view PSNR (dB) of the displayed render (linear → clamp [0, 1] → sRGB
                       when the scene's images are sRGB) against the stored image. Always.
``ssim``               mean per-view SSIM, 11x11 Gaussian window, "valid" padding. Images of at least 11x11.
``flip``               mean per-view LDR-ꟻLIP of the sRGB images (no learned weights). Always.
``lpips``              mean per-view LPIPS-AlexNet — only with local weights (``EvalConfig.lpips_weights`` or the
                       ``DARS_LPIPS_WEIGHTS`` variable), never approximated; otherwise null with the reason.
``albedo_mae``         pooled over the pixels of all views (eq. 34, per channel): rendered linear albedo vs the
                       scene's ``albedo`` maps, on :func:`toolkit.metrics.material_mask` — labelled pixels that are
                       not glass (``display``) and not unlabelled, with a ground-truth surface (GT depth > 0) when GT
                       depth exists. Without GT labels: GT depth > 0, else GT normal ≠ 0, else every pixel.
                       Needs GT albedo and a decomposed (``pbr``) run.
``roughness_rmse``     pooled RMSE (eq. 35) of rendered vs GT ``roughness`` on the same mask. Same conditions.
(details)              ``details.materials``, beside the table: ``albedo_mae_aligned`` — the albedo MAE after a
                       per-channel least-squares scale to the GT (:func:`toolkit.metrics.albedo_mae_aligned`; photos
                       fix albedo and light only up to a common scale, so this is the error light cannot explain) with
                       that ``albedo_scale`` (> 1: the albedo is too dark); ``metallic_mae`` on the same mask when the
                       split has GT ``metallic`` maps.
(details)              ``details.normal_vs_depth``, on every run (no ground truth): the mean angle between the
                       rendered normals and the normals of the rendered depth map, and the share facing away from the
                       camera (:func:`normal_depth_agreement`); per view ``normal_vs_depth_deg``.
``env_light_l2``       ``||l_env - sh_gt||_2`` over the 27 SH coefficients (eq. 36): the run's global light vs the
                       scene's ``sh``. Needs GT SH and a ``pbr`` run (a standard NeRF has no light model).
``view_consistency``   eqs. 37-38: sample std over K = 10 uniformly spaced views (among the evaluated views in which
                       the patch is visible) of the mean luminance of one 3D surface patch (see below), in relative
                       luminance of the *rendered linear* radiance (lux only with ``EvalConfig.lux_factor``). The same
                       figure for the ground-truth images (sRGB decoded to linear) is reported beside it.
``normal_mae``         pooled mean angle (degrees) between rendered and GT world normals on GT surface pixels (GT
                       normal ≠ 0). Needs GT normals.
``miou``               mean IoU over the 7 classes of the rendered semantics (argmax of the rendered logits, 255
                       where the rendered opacity < 0.5) against GT labels, pooled over views. Needs GT labels and a
                       run trained with semantic input and labels.
=====================  ===============================================================================================

**The view-consistency patch.** A square of side ``size`` in a surface plane, projected into each view with
:func:`toolkit.metrics.patch_masks` (back-facing views get an empty mask; pixels where the depth map is nearer than
the plane are occluded — GT depth when the split has it, else the render's own depth). Its plane comes from, in order:
``EvalConfig.patch_centre/patch_normal``; the scene JSON's ``scene.painting_plane`` (the bundled gallery sample:
the painting's centre and normal, side = half the painting's shorter edge); otherwise it is chosen automatically —
the surface point and normal *rendered* at the centre pixel of the first evaluated view (from the rendered depth and
normal; the nearest pixel with opacity ≥ 0.5 when the centre pixel is empty), with a side that spans ~1/8 of that
image's width.

A :class:`EvalResult` serialises (:meth:`EvalResult.to_json`) to the document ``dars eval`` writes as
``RUN/eval/metrics.json``: top-level metric keys exactly :data:`METRIC_KEYS` (a number or null), then
``unavailable`` ({key: reason} for every null), ``per_view``, ``details``, ``training`` and ``eval``.

The ablations (Table 6) train the variants of one trainer under one budget: :mod:`toolkit.ablation`.
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ._checks import DarsError
from .io import linear_to_srgb, srgb_to_linear
from .losses import PAINTING_ROUGHNESS
from .metrics import (MetricUnavailable, albedo_mae, albedo_mae_aligned, env_light_l2, flip, load_lpips_weights, lpips,
                      material_mask, mean_iou, metallic_mae, normal_mae_deg, patch_masks, psnr, roughness_rmse, ssim,
                      uniform_view_indices, view_consistency)
from .scene import SEMANTIC_CLASSES, UNLABELLED, Cameras, Scene, load_scene, photos_have_transparency

__all__ = ["METRIC_KEYS", "JSON_SECTIONS", "EvalConfig", "EvalResult", "EvalFigures", "evaluate_run",
           "training_info", "variant_of", "training_sample_counts", "choose_patch", "chamfer_to_reference",
           "normal_depth_agreement"]

METRIC_KEYS: tuple[str, ...] = ("psnr", "ssim", "flip", "lpips", "albedo_mae", "roughness_rmse", "env_light_l2",
                                "view_consistency", "normal_mae", "miou")
"""The top-level metric keys of ``metrics.json`` (SPEC, ``dars eval``), in order."""

JSON_SECTIONS: tuple[str, ...] = ("unavailable", "per_view", "details", "training", "eval")
"""The other top-level keys of ``metrics.json``."""

_ALIGNED_MAX_PIXELS = 4_000_000
"""At most this many masked pixels (a stride over each view's) feed ``details.materials.albedo_mae_aligned``."""

_PER_VIEW_KEYS = ("psnr", "ssim", "flip", "lpips", "albedo_mae", "roughness_rmse", "normal_mae", "miou")


@dataclass(frozen=True)
class EvalConfig:
    """Options of :func:`evaluate_run`.

    Attributes:
        limit: evaluate at most this many views, evenly spaced over the split (0 = all).
        lpips_weights: LPIPS weight file(s)/folder; None reads ``DARS_LPIPS_WEIGHTS``; without either LPIPS is null.
        k_views: K of eqs. 37-38 (paper: 10); fewer when fewer views see the patch.
        patch_centre: view-consistency patch centre, world metres (with ``patch_normal``); None = from the scene
            JSON or automatic (module docstring).
        patch_normal: the patch's normal (toward the side it is seen from).
        patch_size: side of the square patch, metres; None = from the scene/automatic rule.
        patch_source: how a given patch was chosen (recorded in the report; e.g. by an earlier variant).
        patch_min_pixels: a view "sees" the patch when its mask has at least this many pixels.
        lux_factor: lux per unit of linear luminance; when given, view consistency is reported in lux.
        reference_mesh: a mesh file (PLY/OBJ/...) in the scene's world frame; when given, the field is meshed
            (marching cubes, :func:`toolkit.mesh.extract_mesh`) and the Chamfer distance is reported under
            ``details.chamfer``.
        mesh_resolution: marching-cubes cells along the longest box edge for the Chamfer mesh.
        chamfer_samples: surface points per mesh for the Chamfer distance.
        figure_views: test views kept (as images) for the report's grid.
        weight_views: training views for the W heat maps and sample-count maps (Fig. 7); 0 = none.
        chunk: rays per render call.
        progress: progress bar on stderr.
    """

    limit: int = 0
    lpips_weights: str | None = None
    k_views: int = 10
    patch_centre: tuple[float, float, float] | None = None
    patch_normal: tuple[float, float, float] | None = None
    patch_size: float | None = None
    patch_source: str | None = None
    patch_min_pixels: int = 4
    lux_factor: float | None = None
    reference_mesh: str | None = None
    mesh_resolution: int = 128
    chamfer_samples: int = 20000
    figure_views: int = 4
    weight_views: int = 3
    chunk: int = 8192
    progress: bool = False

    def __post_init__(self):
        if not isinstance(self.limit, int) or self.limit < 0:
            raise DarsError(f"EvalConfig.limit={self.limit!r} must be a non-negative integer (0 = every view)")
        if not isinstance(self.k_views, int) or self.k_views < 2:
            raise DarsError(f"EvalConfig.k_views={self.k_views!r} must be an integer >= 2 (paper: 10)")
        if (self.patch_centre is None) != (self.patch_normal is None):
            raise DarsError("EvalConfig: give patch_centre and patch_normal together (or neither)")
        if self.patch_size is not None and not (math.isfinite(self.patch_size) and self.patch_size > 0):
            raise DarsError(f"EvalConfig.patch_size={self.patch_size!r} must be a positive length in metres")
        if self.lux_factor is not None and not (math.isfinite(self.lux_factor) and self.lux_factor > 0):
            raise DarsError(f"EvalConfig.lux_factor={self.lux_factor!r} must be a positive number (lux per unit)")
        if self.mesh_resolution < 8 or self.chamfer_samples < 1 or self.chunk < 1:
            raise DarsError("EvalConfig: mesh_resolution must be >= 8, chamfer_samples and chunk >= 1")
        if self.figure_views < 0 or self.weight_views < 0:
            raise DarsError("EvalConfig: figure_views and weight_views must be >= 0")


@dataclass
class EvalFigures:
    """Images kept for the report (not serialised). Images are float H-W-3 in [0, 1]; maps float [H, W].

    Attributes:
        grid: per figure view, ``{"key", "gt", "render", "albedo", "roughness", "metallic", "normal", "semantic",
            "error"}`` (``error``: float [H, W] mean absolute error of the displayed images; missing maps absent).
        weights: per training view, ``{"key", "image", "W", "samples", "fine", "w_source"}`` (``samples`` / ``fine``
            float [H, W]: all / fine samples per ray under the training sampler, DARS budgets when the run has DARS).
        patch_views: per K view, ``{"key", "render", "mask"}`` (the render with the patch mask, bool [H, W]).
        log_path: the run's ``log.jsonl`` (training curves).
    """

    grid: list[dict] = field(default_factory=list)
    weights: list[dict] = field(default_factory=list)
    patch_views: list[dict] = field(default_factory=list)
    log_path: Path | None = None


@dataclass
class EvalResult:
    """What :func:`evaluate_run` measured.

    Attributes:
        metrics: {key: float or None} for every key of :data:`METRIC_KEYS`.
        unavailable: {key: reason} for every None in ``metrics``.
        per_view: one dict per evaluated view: ``index``, ``key`` and the per-view metrics (None where unavailable).
        details: supporting figures: ``view_consistency`` (patch, views, per-view means of render and GT, GT std,
            units), ``miou_per_class``, ``pixels`` (mask sizes of the pooled metrics), ``sampling`` (samples per ray),
            ``chamfer`` (with a reference mesh), ``definitions``.
        training: :func:`training_info` of the run.
        info: run, split, evaluated views, checkpoint step, LPIPS weights used.
        figures: images for the report (not serialised).
    """

    metrics: dict[str, float | None]
    unavailable: dict[str, str]
    per_view: list[dict]
    details: dict
    training: dict
    info: dict
    figures: EvalFigures = field(default_factory=EvalFigures, repr=False)

    def to_json(self) -> dict:
        """The ``metrics.json`` document: :data:`METRIC_KEYS` first, then :data:`JSON_SECTIONS`."""
        doc: dict[str, Any] = {k: _num(self.metrics.get(k)) for k in METRIC_KEYS}
        doc["unavailable"] = {k: self.unavailable[k] for k in METRIC_KEYS if doc[k] is None}
        doc["per_view"] = _clean(self.per_view)
        doc["details"] = _clean(self.details)
        doc["training"] = _clean(self.training)
        doc["eval"] = _clean(self.info)
        return doc


def _num(x) -> float | None:
    if x is None:
        return None
    v = float(x)
    return v if math.isfinite(v) else None


def _clean(obj):
    """JSON-safe copy: tensors/arrays to lists, non-finite floats to None, paths to strings."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, torch.Tensor):
        return _clean(obj.detach().cpu().tolist())
    if isinstance(obj, np.ndarray):
        return _clean(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        return _num(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, Path):
        return str(obj)
    return obj


# ============================================================================ run description
def variant_of(cfg) -> str:
    """Name of the Table 6 variant a :class:`~toolkit.train.TrainConfig` is (``full``, ``no_dars``, ``nerf``, ...);
    ``no_semantics_legacy`` for a run saved before the semantic input and L_mat's class terms were separate switches
    (its ``semantics=False`` removed both); ``custom`` for other combinations."""
    if cfg.shading == "radiance":
        return "nerf"
    off = [name for name, is_off in (("no_dars", not cfg.sampler.dars), ("no_semantics", not cfg.semantics),
                                     ("fixed_light", cfg.fixed_light), ("no_mat_loss", cfg.losses.mat <= 0),
                                     ("no_mat_labels", not getattr(cfg, "mat_labels", True) and cfg.losses.mat > 0))
           if is_off]
    if off == ["no_semantics", "no_mat_labels"]:
        return "no_semantics_legacy"
    return "full" if not off else off[0] if len(off) == 1 else "custom"


def training_info(run) -> dict:
    """Training facts of a loaded run: steps, minutes, preset, ablation switches, priors, albedo supervision and the
    last logged training scalars. ``field_steps``: how many of the steps optimised the field (the others are eq. 22
    l_env steps, :func:`toolkit.train.field_steps`)."""
    from .train.step import field_steps

    cfg = run.cfg
    priors = dict(run.meta.get("priors", {}))
    last: dict = {}
    log_path = Path(run.path) / "log.jsonl"
    if log_path.is_file():
        for line in log_path.read_text().splitlines():
            if line.strip():
                try:
                    row = json.loads(line)
                except json.JSONDecodeError:
                    continue
                if row.get("kind") == "train":
                    last = row
    return {
        "steps": int(run.step),
        "field_steps": field_steps(cfg, int(run.step)),
        "minutes": float(run.elapsed) / 60.0,
        "preset": cfg.preset,
        "budget": {"steps": int(cfg.steps), "minutes": float(cfg.minutes)},
        "seed": int(cfg.seed),
        "variant": variant_of(cfg),
        "switches": {"dars": bool(cfg.sampler.dars), "semantics": bool(cfg.semantics),
                     "mat_labels": bool(cfg.mat_labels),
                     "fixed_light": bool(cfg.fixed_light), "mat_loss": bool(cfg.losses.mat > 0),
                     "baseline": "nerf" if cfg.shading == "radiance" else None, "shading": cfg.shading},
        "priors": priors,
        "l_env_source": run.meta.get("l_env_source"),
        "albedo_supervision": bool(cfg.albedo_supervision and "albedo_supervision" in priors),
        "field": cfg.field.encoding,
        "batch_rays": int(cfg.batch_rays),
        "render_samples": {"n_coarse": cfg.render_sampler.n_coarse, "n_fine": cfg.render_sampler.n_fine},
        "scene": run.scene_path,
        "last_log": {k: v for k, v in last.items() if k not in ("kind",)},
    }


# ============================================================================ pieces
def _device_of(run) -> torch.device:
    return next(run.field.parameters()).device


def _render_view(run, cameras: Cameras, i: int, chunk: int) -> dict[str, torch.Tensor]:
    out = run.render(cameras, i, chunk=chunk)
    return {k: v.detach().float().cpu() for k, v in out.as_dict().items()}


@torch.no_grad()
def training_sample_counts(run, index: int, chunk: int = 8192) -> dict[str, torch.Tensor]:
    """Samples per ray the *training* sampler gives every pixel of training view ``index`` (Fig. 7).

    With DARS the fine-sample budget of each ray is ∝ W at its pixel (:func:`toolkit.sampling.ray_budgets`: a fixed
    total of ``n_fine`` x rays over the image, clamped to [budget_min, budget_max], more than ``n_fine`` only where
    W > τ) and its fine samples follow W̄ of the neighbouring views; without DARS every ray gets ``n_fine``. Coarse
    samples in empty space are skipped by the occupancy grid in both cases. (``render_image`` for test views uses
    uniform budgets: a novel view has no W.) Stratified jitter is off, so the maps are deterministic.

    The budgets are shared over the whole image, as over a training batch: a first pass finds the rays with an
    occupied coarse sample (no field query), the budgets are drawn over all of them, and the image is then rendered
    ``chunk`` rays at a time, so the result does not depend on ``chunk`` and memory stays that of one chunk.

    Returns:
        ``{"samples": float [H, W] samples per ray (occupied coarse + fine), "fine": float [H, W] fine samples per
        ray (the budget)}``, CPU.
    """
    from .pipeline import DarsContext, RenderConfig, RenderInputs, render_rays
    from .sampling import coarse_samples, neighbour_views, ray_budgets, stratified_edges
    from .scene import generate_rays

    dev = _device_of(run)
    scene = run.train_scene
    cams = scene.cameras.to(dev)
    if not 0 <= index < len(cams):
        raise DarsError(f"training_sample_counts: view {index} out of range (the run has {len(cams)} training views)")
    if not isinstance(chunk, int) or chunk < 1:
        raise DarsError(f"training_sample_counts: chunk={chunk!r} must be a positive number of rays")
    sampler = replace(run.cfg.sampler, perturb=False)
    h, w = int(cams.height[index]), int(cams.width[index])
    bounds = run.field.space if run.cfg.field.contraction else scene.aabb.to(dev)
    rays = generate_rays(cams, [index], aabb=bounds, near=scene.near, far=scene.far)
    dars = budgets = None
    if sampler.dars and run.weight_maps is not None:
        wm = run.weight_maps.to(dev)
        dars = DarsContext(cams, wm, neighbour_views(scene.cameras, sampler.n_neighbours).to(dev))
        hit = torch.zeros(len(rays), dtype=torch.bool, device=dev)  # rays with an occupied coarse sample
        for s in range(0, len(rays), chunk):
            sub = rays[s:s + chunk]
            coarse, _ = coarse_samples(sub, stratified_edges(sub, sampler.n_coarse, False, None, run.field.space),
                                       run.occupancy)
            hit[s + coarse.ray_indices] = True
        budgets = torch.zeros(len(rays), dtype=torch.long, device=dev)
        budgets[hit] = ray_budgets(wm[index].reshape(-1)[hit], sampler.n_fine, sampler.tau, sampler.budget_min,
                                   sampler.budget_max)
    total, fine = [], []
    for s in range(0, len(rays), chunk):
        out = render_rays(run.field, rays[s:s + chunk],
                          RenderConfig(sampler=sampler, shading=run.cfg.shading, deferred=True),
                          RenderInputs(run.occupancy, run.l_env, run.background, dars=dars),
                          fine_budgets=None if budgets is None else budgets[s:s + chunk])
        total.append(out.samples_per_ray.float().cpu())
        fine.append(out.fine_counts.float().cpu())
    return {"samples": torch.cat(total).reshape(h, w), "fine": torch.cat(fine).reshape(h, w)}


def _scene_patch(scene: Scene) -> tuple[list[float], list[float], float, str] | None:
    block = scene.meta.get("scene")
    if not isinstance(block, dict):
        return None
    plane = block.get("painting_plane")
    if not (isinstance(plane, dict) and "point" in plane and "normal" in plane):
        return None
    size = None
    corners = block.get("painting_corners")
    if isinstance(corners, list) and len(corners) == 4:
        c = np.asarray(corners, dtype=np.float64)
        size = 0.5 * min(np.linalg.norm(c[1] - c[0]), np.linalg.norm(c[3] - c[0]))
    elif isinstance(block.get("config"), dict) and "painting_size" in block["config"]:
        size = 0.5 * min(float(v) for v in block["config"]["painting_size"])
    return ([float(v) for v in plane["point"]], [float(v) for v in plane["normal"]], float(size or 0.3),
            "scene JSON: scene.painting_plane (painting centre and normal; side = half the painting's shorter edge)")


def choose_patch(cameras: Cameras, index: int, depth: torch.Tensor, normal: torch.Tensor, opacity: torch.Tensor,
                 fraction: float = 0.125) -> tuple[list[float], list[float], float, list[int]]:
    """Automatic view-consistency patch from a rendered view: the surface point and normal at the centre pixel.

    Args:
        cameras: the split's cameras.
        index: the rendered camera.
        depth: float [H, W] rendered depth, metres along the camera axis.
        normal: float [H, W, 3] rendered world normals.
        opacity: float [H, W] rendered opacity; the nearest pixel with opacity >= 0.5 to the image centre is used.
        fraction: the patch side spans this fraction of the image width at the point's depth.

    Returns:
        (centre [3], normal [3] facing the camera, side in metres, pixel (u, v)).

    Raises:
        MetricUnavailable: nothing opaque was rendered in the view.
    """
    h, w = depth.shape
    ok = (opacity >= 0.5) & torch.isfinite(depth) & (depth > 0)
    if not bool(ok.any()):
        raise MetricUnavailable(f"view_consistency: view {index} renders no surface (opacity < 0.5 everywhere), so no "
                                "patch can be chosen automatically; give EvalConfig.patch_centre/patch_normal")
    vs, us = torch.nonzero(ok, as_tuple=True)
    d2 = (vs.float() + 0.5 - h / 2) ** 2 + (us.float() + 0.5 - w / 2) ** 2
    k = int(torch.argmin(d2))
    v, u = int(vs[k]), int(us[k])
    c2w = cameras.c2w[index].detach().cpu().double()
    fx, fy = float(cameras.fx[index]), float(cameras.fy[index])
    cx, cy = float(cameras.cx[index]), float(cameras.cy[index])
    z = float(depth[v, u])
    d_cam = torch.tensor([(u + 0.5 - cx) / fx, -(v + 0.5 - cy) / fy, -1.0], dtype=torch.float64)
    origin = c2w[:3, 3]
    point = origin + c2w[:3, :3] @ (d_cam * z)
    n = normal[v, u].double()
    if float(n.norm()) < 1e-6:
        n = -(c2w[:3, :3] @ d_cam)
    n = n / n.norm()
    if float(torch.dot(n, origin - point)) < 0:
        n = -n
    size = fraction * w * z / fx
    return point.tolist(), n.tolist(), float(size), [u, v]


def chamfer_to_reference(run, reference_mesh: str | Path, resolution: int = 128, samples: int = 20000) -> dict:
    """Chamfer distance (metres) between the field's marching-cubes mesh and a reference mesh.

    Returns:
        ``{"value", "mean_ab", "mean_ba", "max", "mean_fraction", "faces", "resolution", "reference"}`` — or
        ``{"value": None, "reason": ...}`` when the field has no surface at the opacity level.
    """
    from .mesh import MeshConfig, extract_mesh, load_mesh, mesh_distance
    from .train.run import field_callables

    ref = load_mesh(reference_mesh)
    density_fn, _ = field_callables(run)
    mesh = extract_mesh(density_fn, run.train_scene.aabb, MeshConfig(resolution=resolution, progress=False))
    if mesh.num_faces == 0:
        return {"value": None, "reason": "the field has no surface at the marching-cubes opacity level (empty mesh)",
                "reference": str(reference_mesh), "resolution": resolution}
    d = mesh_distance(mesh, ref, samples=samples)
    return {"value": d.mean, "mean_ab": d.mean_ab, "mean_ba": d.mean_ba, "max": d.max, "mean_fraction": d.mean_fraction,
            "faces": mesh.num_faces, "resolution": resolution, "reference": str(reference_mesh), "samples": samples,
            "units": "metres (symmetric mean point-to-surface distance, toolkit.mesh.mesh_distance)"}


def _material_region(scene: Scene, i: int, extras: list[str], depth: torch.Tensor | None,
                     labels: torch.Tensor | None) -> tuple[torch.Tensor, str]:
    """The pixels of view ``i`` that material metrics score; ``depth``/``labels``: its GT maps, read once by the
    caller (None where the split has none)."""
    if labels is not None:
        return material_mask(labels, depth), \
            "metrics.material_mask: GT-labelled non-glass pixels" + (" with GT depth > 0" if depth is not None else "")
    if depth is not None:
        return torch.isfinite(depth) & (depth > 0), "GT depth > 0 (no GT labels)"
    if "normal" in extras:
        return scene.load_extra(i, "normal").abs().sum(0) > 0, "GT normal non-zero (no GT labels or depth)"
    h, w = int(scene.cameras.height[i]), int(scene.cameras.width[i])
    return torch.ones(h, w, dtype=torch.bool), "every pixel (no GT labels, depth or normals)"


def _pool(values: list[tuple[float, int]], kind: str) -> float | None:
    """Exact pooled value from per-view (value, pixel count) pairs: a pixel-weighted mean, or RMS for RMSE."""
    vs = [(v, n) for v, n in values if v is not None and n > 0]
    total = sum(n for _, n in vs)
    if not total:
        return None
    if kind == "rmse":
        return math.sqrt(sum(v * v * n for v, n in vs) / total)
    return sum(v * n for v, n in vs) / total


def _error_map(pred_disp: torch.Tensor, gt_disp: torch.Tensor) -> np.ndarray:
    return (pred_disp - gt_disp).abs().mean(0).numpy()


# ============================================================================ the stage
def evaluate_run(run, split: str = "test", cfg: EvalConfig = EvalConfig(), log: Callable[[str], None] | None = None
                 ) -> EvalResult:
    """Render every view of ``split`` and compute every metric the data supports (module docstring).

    Args:
        run: a loaded run (:func:`toolkit.train.load_run`).
        split: split of the run's scene to evaluate (``test`` by default).
        cfg: options (:class:`EvalConfig`).
        log: callable for progress lines (default: stderr).

    Returns:
        :class:`EvalResult` (``to_json()`` gives ``metrics.json``).

    Raises:
        DarsError: ``run`` is not a loaded run, the split is missing or empty, or a patch/LPIPS option is invalid.

    Example:
        >>> res = evaluate_run(load_run("runs/gallery"), "test", EvalConfig(limit=4))
        >>> res.metrics["psnr"], res.unavailable.get("lpips")
    """
    from tqdm import tqdm

    from .train.run import Run

    log = log or (lambda m: print(m, file=sys.stderr))
    if not isinstance(run, Run):
        raise DarsError(f"evaluate_run: expected a loaded run (toolkit.train.load_run(RUN)), got {type(run).__name__}")
    scene = run.load_split(split)
    if len(scene) == 0:
        raise DarsError(f"evaluate_run: split '{split}' of {run.scene_path} has no views")
    dev = _device_of(run)
    cams = scene.cameras.to(dev)
    n_all = len(scene)
    views = list(range(n_all)) if not cfg.limit or cfg.limit >= n_all else uniform_view_indices(n_all, cfg.limit)
    extras = scene.extras_available()
    pbr = run.cfg.shading == "pbr"
    h, w = scene.image_size
    unavailable: dict[str, str] = {}

    # ---- what the data supports (reasons for the nulls)
    lpips_ok = False
    try:
        if min(h, w) < 31:
            raise MetricUnavailable(f"lpips: images of {h}x{w} px are smaller than AlexNet's 31x31 minimum")
        load_lpips_weights(cfg.lpips_weights)
        lpips_ok = True
    except MetricUnavailable as e:
        unavailable["lpips"] = str(e)
    if min(h, w) < 11:
        unavailable["ssim"] = f"images of {h}x{w} px are smaller than the 11x11 SSIM window"
    no_mat = "the run has no material decomposition (standard NeRF baseline: radiance shading)"
    for key, extra, jkey in (("albedo_mae", "albedo", "albedo_path"), ("roughness_rmse", "roughness", "roughness_path"),
                             ("normal_mae", "normal", "normal_path")):
        if extra not in extras:
            unavailable[key] = f"split '{split}' has no ground-truth {extra} maps ('{jkey}' on every frame)"
        elif key != "normal_mae" and not pbr:
            unavailable[key] = no_mat
    sh_gt = scene.sh if scene.sh is not None else run.train_scene.sh
    if sh_gt is None:
        unavailable["env_light_l2"] = "the scene has no ground-truth SH lighting ('sh' or 'sh_path' in the transforms JSON)"
    elif not pbr:
        unavailable["env_light_l2"] = "the run has no light model (standard NeRF baseline: radiance shading)"
    labels_src = str(run.meta.get("priors", {}).get("labels", ""))
    if "semantic" not in extras:
        unavailable["miou"] = f"split '{split}' has no ground-truth semantic labels ('semantic_path' on every frame)"
    elif not run.cfg.semantics or labels_src in ("off", "none", ""):
        unavailable["miou"] = ("the run was trained without semantic supervision (semantic input off or no labels), "
                               "so its semantic head is untrained")

    # ---- the view-consistency patch (may be chosen after the first render)
    patch = None
    if cfg.patch_centre is not None:
        patch = (list(cfg.patch_centre), list(cfg.patch_normal), float(cfg.patch_size or 0.3),
                 cfg.patch_source or "given (EvalConfig.patch_centre/patch_normal)")
    else:
        patch = _scene_patch(scene)
    if patch is not None and cfg.patch_size is not None:
        patch = (patch[0], patch[1], float(cfg.patch_size), patch[3])
    vc_views: list[int] = []
    vc_keep: dict[int, dict] = {}
    vc_error: str | None = None
    patch_pixel = None

    def select_vc_views() -> None:
        nonlocal vc_views, vc_error
        gt_depths = None
        if "depth" in extras:
            gt_depths = torch.stack([scene.load_extra(i, "depth") for i in views])
        try:
            m = patch_masks(scene.cameras, views, patch[0], patch[1], patch[2], depths=gt_depths)
        except DarsError as e:
            vc_error = f"view_consistency: invalid patch ({e})"
            return
        seen = [v for v, c in zip(views, m.sum(dim=(1, 2)).tolist()) if c >= cfg.patch_min_pixels]
        if len(seen) < 2:
            vc_error = (f"view_consistency: the patch ({patch[3]}) is visible (>= {cfg.patch_min_pixels} px) in "
                        f"{len(seen)} of the {len(views)} evaluated views; need at least 2")
            return
        k = min(cfg.k_views, len(seen))
        vc_views = [seen[j] for j in uniform_view_indices(len(seen), k)]

    if patch is not None:
        select_vc_views()

    # ---- render and measure
    grid_views = set(views[j] for j in uniform_view_indices(len(views), min(cfg.figure_views, len(views)))) \
        if cfg.figure_views else set()
    per_view: list[dict] = []
    pooled: dict[str, list[tuple[float, int]]] = {"albedo_mae": [], "roughness_rmse": [], "normal_mae": []}
    aligned_px: list[tuple[torch.Tensor, torch.Tensor]] = []
    pooled_metallic: list[tuple[float, int]] = []
    # per material and GT class: (roughness RMSE or albedo MAE, pixels) per view
    by_class: dict[str, dict[str, list[tuple[float, int]]]] = {"roughness": {}, "albedo": {}}
    albedo_sums: dict[str, torch.Tensor] = {}  # per GT class: sums of predicted and GT albedo, float64 [2, 3]
    geo_px: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]] = []  # |dz|, opacity, GT class (strided)
    nd_px: list[tuple[float, float, int]] = []  # per view: mean normal-vs-depth angle, back-facing share, pixels
    sem_pred, sem_gt = [], []
    mat_rule = ""
    samples_mean: list[float] = []
    figures = EvalFigures(log_path=Path(run.path) / "log.jsonl")
    masks_ignored = scene.masks == "ignore" and any("mask" in f.extras for f in scene.frames)  # the run's --masks
    if masks_ignored:
        log("[dars eval] the test photos' masks (mask_path 0) are left out of the image scores: PSNR over the kept "
            "pixels, SSIM/FLIP/LPIPS with the photo in place of the render where the mask is 0")
    object_alpha = photos_have_transparency(scene)  # an object on a plain background: also score it alone
    log(f"[dars eval] {run.path}: rendering {len(views)} of {n_all} '{split}' views ({h}x{w} px)")
    bar = tqdm(views, desc="eval", unit="view", file=sys.stderr, disable=not cfg.progress)
    for i in bar:
        out = _render_view(run, cams, i, cfg.chunk)
        rgb_lin = out["rgb"].clamp_min(0.0).permute(2, 0, 1)  # [3, H, W] linear radiance
        disp = rgb_lin.clamp(0.0, 1.0)
        pred_disp = linear_to_srgb(disp) if scene.srgb else disp
        rgba = scene.load_image(i, with_alpha=True) if object_alpha else None  # one decode serves both
        gt_stored = rgba[:3] if rgba is not None else scene.load_image(i)
        gt_srgb = gt_stored if scene.srgb else linear_to_srgb(gt_stored.clamp(0, 1))
        pred_srgb = pred_disp if scene.srgb else linear_to_srgb(disp)
        row: dict[str, Any] = {"index": i, "key": scene.frames[i].key}
        keep = scene.valid_mask(i) if masks_ignored else None  # the photo's mask_path: 0 = not scored
        score_disp, score_srgb = pred_disp, pred_srgb
        if keep is not None:  # PSNR over the kept pixels; SSIM/FLIP/LPIPS see the photo where the mask is 0
            row["masked_out"] = float(1.0 - keep.float().mean())
            score_disp = torch.where(keep[None], pred_disp, gt_stored)
            score_srgb = torch.where(keep[None], pred_srgb, gt_srgb)
        row["psnr"] = float(psnr(score_disp, gt_stored, keep))
        if object_alpha:  # the object's pixels alone (alpha >= 0.5): the plain background is easy to match
            obj = rgba[3] >= 0.5
            row["psnr_object"] = float(psnr(score_disp, gt_stored, obj)) if bool(obj.any()) else None
        row["ssim"] = float(ssim(score_disp, gt_stored)) if "ssim" not in unavailable else None
        row["flip"] = float(flip(score_srgb.clamp(0, 1), gt_srgb.clamp(0, 1)))
        row["lpips"] = float(lpips(score_srgb[None], gt_srgb[None], cfg.lpips_weights)[0]) if lpips_ok else None
        gt_lab = scene.load_extra(i, "semantic") if "semantic" in extras else None  # GT maps read once per view
        gt_depth = scene.load_extra(i, "depth") if "depth" in extras else None
        mask = None
        if any(k not in unavailable for k in ("albedo_mae", "roughness_rmse")):
            mask, mat_rule = _material_region(scene, i, extras, gt_depth, gt_lab)
        for key, extra, fn in (("albedo_mae", "albedo", albedo_mae), ("roughness_rmse", "roughness", roughness_rmse)):
            row[key] = None
            if key in unavailable:
                continue
            n_px = int(mask.sum())
            if n_px:
                pred = out["albedo"].permute(2, 0, 1) if extra == "albedo" else out["roughness"]
                gt_map = scene.load_extra(i, extra)
                row[key] = float(fn(pred, gt_map, mask))
                if gt_lab is not None:  # per GT class (details.materials): painting roughness apart, albedo's level
                    for c, name in enumerate(SEMANTIC_CLASSES):
                        m_c = mask & (gt_lab == c)
                        if bool(m_c.any()):
                            by_class[extra].setdefault(name, []).append((float(fn(pred, gt_map, m_c)), int(m_c.sum())))
                            if extra == "albedo":
                                sums = torch.stack([pred[:, m_c].sum(1), gt_map[:, m_c].sum(1)]).double()
                                albedo_sums[name] = albedo_sums.get(name, 0) + sums
                if extra == "albedo":  # a strided subset of the masked pixels for the scale-aligned MAE (details)
                    stride = max(1, math.ceil(n_px * len(views) / _ALIGNED_MAX_PIXELS))
                    aligned_px.append((pred[:, mask][:, ::stride], gt_map[:, mask][:, ::stride]))
            pooled[key].append((row[key], n_px))
        n_mat = 0 if mask is None else int(mask.sum())
        if pbr and n_mat and "metallic" in extras:
            pooled_metallic.append((float(metallic_mae(out["metallic"].reshape(mask.shape),
                                                       scene.load_extra(i, "metallic"), mask)), n_mat))
        row["normal_mae"] = None
        if "normal_mae" not in unavailable:
            n_gt = scene.load_extra(i, "normal")
            nmask = torch.isfinite(n_gt).all(0) & (n_gt.abs().sum(0) > 0)
            if bool(nmask.any()):
                row["normal_mae"] = float(normal_mae_deg(out["normal"].permute(2, 0, 1), n_gt, nmask))
            pooled["normal_mae"].append((row["normal_mae"], int(nmask.sum())))
        row["miou"] = None
        sem = None
        if "semantic_logits" in out:
            sem = out["semantic_logits"].argmax(-1)
            sem = torch.where(out["opacity"] >= 0.5, sem, torch.full_like(sem, UNLABELLED))
        if "miou" not in unavailable:
            v_miou, _ = mean_iou(sem, gt_lab)
            row["miou"] = v_miou if math.isfinite(v_miou) else None
            sem_pred.append(sem.to(torch.uint8).reshape(-1))
            sem_gt.append(gt_lab.to(torch.uint8).reshape(-1))
        if gt_depth is not None:  # geometry by class (details.geometry): a strided subset of the GT-depth pixels
            gt_z = gt_depth.reshape(-1)
            keep = (gt_z > 0).nonzero().squeeze(1)
            keep = keep[::max(1, math.ceil(keep.numel() * len(views) / _ALIGNED_MAX_PIXELS))]
            lab = gt_lab.reshape(-1)[keep] if gt_lab is not None else None
            geo_px.append(((out["depth"].reshape(-1)[keep].cpu() - gt_z[keep]).abs(),
                           out["opacity"].reshape(-1)[keep].cpu(), lab))
        if "normal" in out and "depth" in out:  # the normals against the rendered surface (no ground truth needed)
            ang, back = normal_depth_agreement(scene.cameras, i, out["depth"], out["normal"], out["opacity"])
            row["normal_vs_depth_deg"] = float(ang.mean()) if ang.numel() else None
            if ang.numel():
                nd_px.append((float(ang.mean()), float(back.float().mean()), int(ang.numel())))
        row["samples_per_ray"] = float(out["samples"].mean())
        samples_mean.append(row["samples_per_ray"])
        per_view.append(row)
        # -- automatic patch from the first evaluated view
        if patch is None and i == views[0]:
            try:
                c, nrm, size, patch_pixel = choose_patch(scene.cameras, i, out["depth"], out["normal"], out["opacity"])
                patch = (c, nrm, float(cfg.patch_size or size),
                         f"automatic: surface point and normal rendered at pixel {patch_pixel} of view {i} "
                         f"('{scene.frames[i].key}'), side ~1/8 of the image width")
                select_vc_views()
            except MetricUnavailable as e:
                vc_error = str(e)
        if i in vc_views:
            gt_lin = srgb_to_linear(gt_stored) if scene.srgb else gt_stored
            vc_keep[i] = {"rgb": rgb_lin, "gt": gt_lin, "depth": out["depth"], "display": pred_disp}
        if i in grid_views:
            imgs = _display_maps(out, scene.srgb)
            entry = {"key": scene.frames[i].key, "gt": gt_srgb.permute(1, 2, 0).numpy(),
                     "render": pred_srgb.permute(1, 2, 0).numpy(), "error": _error_map(pred_disp, gt_stored)}
            entry.update({k: v for k, v in imgs.items() if k in ("albedo", "roughness", "metallic", "normal",
                                                                  "semantic") and (pbr or k in ("normal", "semantic"))})
            figures.grid.append(entry)
    bar.close()

    # ---- pooled metrics
    metrics: dict[str, float | None] = {}
    for key in ("psnr", "ssim", "flip", "lpips"):
        vals = [r[key] for r in per_view if r[key] is not None and math.isfinite(r[key])]
        metrics[key] = sum(vals) / len(vals) if vals and key not in unavailable else None
    pixels = {}
    for key in ("albedo_mae", "roughness_rmse", "normal_mae"):
        if key in unavailable:
            metrics[key] = None
            continue
        metrics[key] = _pool(pooled[key], "rmse" if key == "roughness_rmse" else "mean")
        pixels[key] = sum(n for _, n in pooled[key])
        if metrics[key] is None:
            unavailable[key] = "the mask selects no pixel in any evaluated view"
    material_extra = {"albedo_mae_aligned": None, "albedo_scale": None, "metallic_mae": _pool(pooled_metallic, "mean"),
                      "roughness_rmse_by_class": {k: _pool(v, "rmse") for k, v in by_class["roughness"].items()}
                      or None,
                      "albedo_mae_by_class": {k: _pool(v, "mean") for k, v in by_class["albedo"].items()} or None,
                      **{f"{m}_pixels_by_class": {k: sum(n for _, n in v) for k, v in by_class[m].items()} or None
                         for m in ("roughness", "albedo")},
                      "albedo_level_by_class": {k: round(float((v[0] / v[1].clamp_min(1e-12)).mean()), 4)
                                                for k, v in albedo_sums.items()} or None}
    if metrics.get("albedo_mae") is not None and aligned_px:
        p_al, g_al = (torch.cat(t, 1)[:, None] for t in zip(*aligned_px))
        v_al, s_al = albedo_mae_aligned(p_al, g_al, torch.ones(p_al.shape[1:], dtype=torch.bool))
        material_extra.update(albedo_mae_aligned=float(v_al), albedo_scale=[round(float(x), 4) for x in s_al])
    metrics["env_light_l2"] = None
    if "env_light_l2" not in unavailable:
        metrics["env_light_l2"] = float(env_light_l2(run.l_env.detach().cpu().float(), sh_gt.float()))
    miou_per_class = None
    metrics["miou"] = None
    if "miou" not in unavailable:
        v, per_class = mean_iou(torch.cat(sem_pred), torch.cat(sem_gt))
        miou_per_class = dict(zip(SEMANTIC_CLASSES, per_class))
        if math.isfinite(v):
            metrics["miou"] = v
        else:
            unavailable["miou"] = "no labelled pixel in the evaluated views"

    # ---- view consistency
    vc_detail, metrics["view_consistency"] = None, None
    if vc_error is None and patch is not None and vc_views:
        vc_detail, vc_error = _view_consistency(scene, extras, vc_views, vc_keep, patch, cfg, figures)
        if vc_detail is not None:
            metrics["view_consistency"] = vc_detail["value"]
    if metrics["view_consistency"] is None:
        unavailable["view_consistency"] = vc_error or "view_consistency: fewer than 2 evaluated views"
    if patch_pixel is not None and vc_detail is not None:
        vc_detail["patch"]["pixel"] = patch_pixel

    # ---- Fig. 7: W and samples per ray on a few training views
    sampling = {"test_mean_samples_per_ray": sum(samples_mean) / len(samples_mean),
                "test_budget": "uniform: every ray gets n_fine fine samples (no W exists for a novel view)"}
    if cfg.weight_views:
        sampling.update(_weight_figures(run, cfg, figures))

    obj_vals = [r["psnr_object"] for r in per_view if r.get("psnr_object") is not None]
    details = {
        "object_psnr": sum(obj_vals) / len(obj_vals) if obj_vals else None,
        "geometry": _geometry_by_class(geo_px),
        "normal_vs_depth": _normal_depth_summary(nd_px),
        "view_consistency": vc_detail,
        "miou_per_class": miou_per_class,
        "pixels": pixels,
        "materials": material_extra,
        "sampling": sampling,
        "chamfer": None,
        "definitions": {
            "image_space": "sRGB-encoded display images (render: linear -> clamp [0,1] -> sRGB)" if scene.srgb
            else "linear images as stored (FLIP/LPIPS on their sRGB encoding)",
            "material_mask": mat_rule or None,
            "normal_mask": "GT normal non-zero (surface pixels)",
            "albedo_mae_aligned": "albedo MAE after a per-channel least-squares scale to the ground truth "
                                  "(metrics.albedo_mae_aligned; albedo_scale > 1: the albedo is too dark), same mask",
            "metallic_mae": "mean |metallic - GT metallic| on the material mask",
            "roughness_rmse_by_class": "roughness RMSE on the material mask split by ground-truth class (painting "
                                       f"apart: L_mat pulls painting roughness to {PAINTING_ROUGHNESS:g}, so that "
                                       "class is the one to read against the scene's true painting roughness)",
            "albedo_mae_by_class": "albedo MAE on the material mask split by ground-truth class "
                                   "(albedo_pixels_by_class: the pixels each covers, so a class's share of the pooled "
                                   "error is MAE x pixels / sum); albedo_level_by_class: the class's mean predicted "
                                   "over mean GT albedo, averaged over channels (above 1: too bright)",
            "semantics": "argmax of rendered logits; 255 where rendered opacity < 0.5",
            "normal_vs_depth": "no ground truth: mean angle (degrees) between the rendered normal and the normal "
                               "of the rendered depth map (central differences), over the pixels whose 3x3 "
                               "neighbourhood is opaque (opacity >= 0.5), pooled over views; back_facing_share: "
                               "the share of those pixels whose rendered normal faces away from the camera. Low "
                               "angles mean the normals (shading, relighting, the GLB's normal map) follow the "
                               "geometry; 90 is no relation",
            "geometry": "on pixels with a ground-truth depth: median |rendered depth - GT depth| (metres, along the "
                        "camera axis) and mean rendered opacity, over all of them and per ground-truth class; "
                        "opacity well below 1 on a class means the learned background shows through it",
            "masks": ("the test photos' mask_path 0 pixels are not scored: PSNR over the kept pixels, SSIM/FLIP/LPIPS "
                      "with the photo in place of the render there (per_view masked_out: the share left out)")
            if masks_ignored else None,
            "object_psnr": "photos with transparency (RGBA, or masks read as alpha): mean over views of the PSNR "
                           "over the pixels whose alpha is at least 0.5, the object alone (per_view psnr_object); "
                           "psnr also counts the plain background, which is easy to match" if object_alpha else None,
            "pooling": "psnr/ssim/flip/lpips: mean of per-view values; albedo/roughness/normal: over all masked "
                       "pixels of all views; miou: one confusion over all views",
        },
    }
    if cfg.reference_mesh:
        try:
            details["chamfer"] = chamfer_to_reference(run, cfg.reference_mesh, cfg.mesh_resolution, cfg.chamfer_samples)
        except DarsError as e:
            details["chamfer"] = {"value": None, "reason": str(e), "reference": str(cfg.reference_mesh)}
    for k in list(unavailable):  # reasons read "key: why" in a listing: drop a repeated "key: " prefix
        while unavailable[k].startswith(f"{k}: "):
            unavailable[k] = unavailable[k][len(k) + 2:]
    for k in METRIC_KEYS:
        if metrics.get(k) is not None and not math.isfinite(metrics[k]):
            unavailable[k] = f"the value is not finite ({metrics[k]})"
            metrics[k] = None
        if metrics.get(k) is None and k not in unavailable:
            unavailable[k] = "not computed"
        if metrics.get(k) is not None:
            unavailable.pop(k, None)
    info = {"run": str(run.path), "split": split, "views": len(views), "views_in_split": n_all,
            "view_indices": views, "checkpoint_step": int(run.step), "image_size": [w, h],
            "ground_truth": extras, "gt_sh": sh_gt is not None,
            "lpips_weights": (cfg.lpips_weights or "DARS_LPIPS_WEIGHTS") if lpips_ok else None}
    return EvalResult(metrics=metrics, unavailable=unavailable, per_view=per_view, details=details,
                      training=training_info(run), info=info, figures=figures)


def _normal_depth_summary(px: list[tuple[float, float, int]]) -> dict | None:
    """``details.normal_vs_depth``: the per-view figures of :func:`normal_depth_agreement`, pooled by pixels."""
    n = sum(p[2] for p in px)
    if not n:
        return None
    return {"angle_mean_deg": sum(a * k for a, _, k in px) / n, "back_facing_share": sum(b * k for _, b, k in px) / n,
            "pixels": n}


def _geometry_by_class(px: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]]) -> dict | None:
    """``details.geometry``: median depth error and mean opacity on GT-depth pixels, overall and per GT class."""
    if not px:
        return None
    dz = torch.cat([p[0] for p in px]).float()
    op = torch.cat([p[1] for p in px]).float()

    def stats(m: torch.Tensor | None) -> dict:
        d, o = (dz, op) if m is None else (dz[m], op[m])
        return {"depth_error_median_m": float(d.median()), "opacity_mean": float(o.mean()), "pixels": int(d.numel())}

    res = {"all": stats(None), "by_class": None}
    if all(p[2] is not None for p in px):
        lab = torch.cat([p[2] for p in px]).long()
        res["by_class"] = {name: {**stats(lab == c), "share": float((lab == c).float().mean())}
                           for c, name in enumerate(SEMANTIC_CLASSES) if bool((lab == c).any())}
    return res


def normal_depth_agreement(cameras: Cameras, index: int, depth: torch.Tensor, normal: torch.Tensor,
                           opacity: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per pixel, the angle (degrees) between the rendered normal and the normal of the rendered depth map, and
    whether the rendered normal faces away from the camera: a check of the normals that needs no ground truth.

    The depth normal is :func:`toolkit.losses.depth_normals` of the rendered surface points (central differences
    over ±1 pixel, turned toward the camera). Only pixels whose 3 x 3 neighbourhood is all opaque (rendered opacity
    ≥ 0.5) count, so silhouettes, where the depth jumps, do not.

    Args:
        cameras: the evaluated split's cameras; ``index`` the view.
        depth, opacity: float [H, W] rendered depth (along the camera axis) and opacity.
        normal: float [H, W, 3] rendered unit world normals.

    Returns:
        (angles float [N], back-facing bool [N]) over the N counted pixels (N may be 0).
    """
    from .losses import depth_map_normals

    nd, d = depth_map_normals(cameras.to("cpu"), index, depth)
    solid = (opacity >= 0.5).float()[None, None]
    solid = (-torch.nn.functional.max_pool2d(-solid, 3, stride=1))[0, 0] > 0.5  # [H-2, W-2]: all 9 opaque
    ok = solid & (nd.square().sum(-1) > 0.5) & torch.isfinite(depth[1:-1, 1:-1])
    n = torch.nn.functional.normalize(normal[1:-1, 1:-1].float(), dim=-1, eps=1e-6)
    cos = (n * nd).sum(-1).clamp(-1.0, 1.0)
    back = (n * d[1:-1, 1:-1]).sum(-1) > 0
    return torch.rad2deg(torch.arccos(cos[ok])), back[ok]


def _display_maps(out: dict[str, torch.Tensor], srgb: bool) -> dict[str, np.ndarray]:
    from .visualise import render_output_images

    keep = {k: v for k, v in out.items() if k in ("rgb", "albedo", "roughness", "metallic", "normal", "semantic_logits",
                                                    "opacity")}
    return render_output_images(keep, srgb=srgb)


def _view_consistency(scene: Scene, extras: list[str], vc_views: list[int], keep: dict[int, dict], patch, cfg: EvalConfig,
                      figures: EvalFigures) -> tuple[dict | None, str | None]:
    """Eqs. 37-38 on the kept K views, for the render and for the ground truth (same masks)."""
    centre, normal, size, source = patch
    if "depth" in extras:
        depths = torch.stack([scene.load_extra(i, "depth") for i in vc_views])
        occl = "GT depth"
    else:
        depths = torch.stack([keep[i]["depth"] for i in vc_views])
        occl = "rendered depth (no GT depth)"
    masks = patch_masks(scene.cameras, vc_views, centre, normal, size, depths=depths)
    images = torch.stack([keep[i]["rgb"] for i in vc_views])
    gts = torch.stack([keep[i]["gt"] for i in vc_views])
    try:
        std, means = view_consistency(images, masks, "linear", cfg.lux_factor)
        gt_std, gt_means = view_consistency(gts, masks, "linear", cfg.lux_factor)
    except MetricUnavailable as e:
        return None, str(e)
    for k, i in enumerate(vc_views):
        figures.patch_views.append({"key": scene.frames[i].key, "render": keep[i]["display"].permute(1, 2, 0).numpy(),
                                    "mask": masks[k].numpy()})
    units = "lux (lux_factor x relative luminance)" if cfg.lux_factor else \
        "relative luminance (Rec. 709 Y) of the rendered linear radiance (unclamped); GT: sRGB images decoded to linear"
    return {"value": float(std), "gt_value": float(gt_std), "k": len(vc_views), "units": units,
            "lux_factor": cfg.lux_factor, "views": vc_views, "keys": [scene.frames[i].key for i in vc_views],
            "render_means": means.tolist(), "gt_means": gt_means.tolist(),
            "pixels": masks.sum(dim=(1, 2)).tolist(), "occlusion": occl,
            "patch": {"centre": [float(c) for c in centre], "normal": [float(c) for c in normal], "size": float(size),
                      "source": source}}, None


def _weight_figures(run, cfg: EvalConfig, figures: EvalFigures) -> dict:
    """W overlays and training-sampler sample counts for ``cfg.weight_views`` training views (Fig. 7)."""
    tr = run.train_scene
    idx = uniform_view_indices(len(tr), min(cfg.weight_views, len(tr)))
    if run.weight_maps is not None:
        wmaps = [run.weight_maps[i].float().cpu() for i in idx]
        w_source = "the run's W maps (used by its DARS sampler)"
    else:
        from .edges import WeightMapConfig, weight_map

        from .scene import SceneError

        wmaps, missing = [], []
        for i in idx:  # one view at a time: views may differ in size
            maps = {}
            for kind in ("semantic", "metal"):
                try:
                    maps[kind] = tr.load_extra(i, kind)[None] if tr.has_extra(kind) else None
                except SceneError as e:  # a figure is no reason to lose the evaluation: W without that map
                    maps[kind] = None
                    missing.append(str(e))
            wmaps.append(weight_map(tr.load_image(i)[None], maps["semantic"], maps["metal"],
                                    WeightMapConfig()).weights[0].float().cpu())
        w_source = "recomputed (the run does not sample by W: DARS off)"
        if missing:
            w_source += f"; without {len(missing)} unreadable label/metal map(s) of the training views ({missing[0]})"
    stats: dict[str, list[float]] = {k: [] for k in ("mean", "min", "max", "fine_mean", "fine_min", "fine_max")}
    for k, i in enumerate(idx):
        c = training_sample_counts(run, i)
        for name, t in (("", c["samples"]), ("fine_", c["fine"])):
            stats[f"{name}mean"].append(float(t.mean()))
            stats[f"{name}min"].append(float(t.min()))
            stats[f"{name}max"].append(float(t.max()))
        figures.weights.append({"key": tr.frames[i].key, "image": tr.load_image(i).permute(1, 2, 0).numpy(),
                                "W": wmaps[k].numpy(), "samples": c["samples"].numpy(), "fine": c["fine"].numpy(),
                                "w_source": w_source})
    sc = run.cfg.sampler
    return {"train_views": [tr.frames[i].key for i in idx], "train_view_indices": idx,
            "train_mean_samples_per_ray": stats["mean"], "train_min_samples_per_ray": stats["min"],
            "train_max_samples_per_ray": stats["max"], "train_mean_fine_per_ray": stats["fine_mean"],
            "train_min_fine_per_ray": stats["fine_min"], "train_max_fine_per_ray": stats["fine_max"],
            "train_budget": (f"DARS: fine samples per ray ∝ W, clamped to [{sc.budget_min}, {sc.budget_max}], above "
                             f"{sc.n_fine} only where W > {sc.tau}, fixed total {sc.n_fine} x rays") if sc.dars
            else f"uniform: {sc.n_fine} fine samples per ray", "w_source": w_source}
