"""Stage 11 — two-stage training of the decoupled field (paper eqs. 21–23), presets, checkpoints, runs.

Training state is explicit (:class:`TrainState`; ``state = init_state(cfg, data)``, ``train_step(state, ...)``)
so resume is exact: a checkpoint holds the field, optimiser, l_env, occupancy grid, RNG state and the step, and
a resumed ``--steps`` run reproduces an uninterrupted one bit for bit on CPU.

Stages:
  (a) pretrain (first ``pretrain_fraction`` of the run): the light estimate l_env is frozen; the field is
      optimised on L_rgb + λ L_ssim + λ L_mat (eq. 21);
  (b) alternate, every ``light_period`` steps: ``light_steps`` steps that fix the field and optimise l_env on
      the L1 reprojection error (eq. 22), then field steps with l_env fixed on eq. 23 (+ L_psnr, L_eikonal).
  ``fixed_light`` skips the l_env steps (the "fixed lighting" ablation).

A run directory holds ``config.json``, ``checkpoint.pt``, ``log.jsonl``, ``loss_curves.png`` and
``snapshots/`` (field states at the ``snapshot_minutes`` milestones).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from dataclasses import dataclass, replace
from dataclasses import field as dc_field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import nn

from ._checks import ConfigError, DarsError, check_choice
from .encoding import HashGridConfig
from .field import DarsField, FieldConfig
from .io import atomic_write, linear_to_srgb, srgb_to_linear, write_json
from .losses import (LossWeights, compactness_loss, light_residual_loss, material_loss, normal_consistency_loss, orientation_loss,
                     psnr_loss, rgb_l1, semantic_loss, ssim_loss)
from .pipeline import Background, DarsContext, render_rays
from .sampling import OccupancyGrid, SamplerConfig, build_ray_sampler, neighbour_views, select_rays
from .scene import Scene, UNLABELLED, generate_rays, load_scene

__all__ = ["TrainConfig", "make_config", "PRESETS", "TrainData", "TrainState", "prepare_data", "init_state",
           "train_step", "light_step", "train", "save_checkpoint", "load_checkpoint", "Run", "load_run",
           "TrainingDiverged", "grey_ambient_sh", "resolve_config", "field_callables", "load_field_callables"]


class TrainingDiverged(DarsError):
    """The loss became NaN or inf; the last good checkpoint is kept."""


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (saved as ``config.json``)."""

    preset: str = "fast"
    field: FieldConfig = dc_field(default_factory=FieldConfig)
    sampler: SamplerConfig = dc_field(default_factory=SamplerConfig)
    """Training samples (perturbed)."""
    render_sampler: SamplerConfig = dc_field(default_factory=lambda: SamplerConfig(n_coarse=128, perturb=False))
    """Samples for rendering test views (paper: 128 per ray)."""
    losses: LossWeights = dc_field(default_factory=LossWeights)
    batch_rays: int = 4096
    """Rays per step (paper: 1024)."""
    ssim_patches: int = 4
    """16x16 patches per step for L_ssim (their rays are part of the batch)."""
    ssim_patch_size: int = 16
    steps: int = 0
    """Total steps (0: use ``minutes``)."""
    minutes: float = 0.0
    """Wall-clock training budget (0: use ``steps``)."""
    lr_grid: float = 1e-2
    lr_net: float = 2e-3
    lr_light: float = 5e-3
    lr_colour: float = 2e-4
    """Per-image colour gains (stage 2). Ten times below ``lr_net``: each image sees ~1/B of a batch, and at
    ``lr_net`` Adam's noisy steps let the gains random-walk several per cent in 1000 steps (measured on the
    perturbed-sample benchmark), absorbing what the field should learn."""
    lr_final_factor: float = 0.1
    """Learning rates decay exponentially to this factor by the end of the run."""
    weight_decay: float = 1e-6
    occupancy_resolution: int = 64
    occupancy_every: int = 16
    occupancy_warmup: int = 64
    auto_resolution: bool = True
    """Set the hash grid's finest resolution from the data (:func:`resolve_config`)."""
    pretrain_fraction: float = 0.3
    """Stage (a) length as a fraction of the run (steps or minutes)."""
    light_period: int = 50
    light_steps: int = 5
    deferred: bool = False
    """Heads and PBR shading once per ray on the accumulated feature (cheaper per step, but it learns more
    slowly from a transparent start); False (default): per sample, then composited."""
    shading: Literal["pbr", "radiance"] = "pbr"
    """``pbr``: decomposed (material + SH light); ``radiance``: plain NeRF colour head (baseline)."""
    semantics: bool = True
    """Semantic guidance: semantic loss, labels in L_mat and in W; off = the "w/o semantics" ablation."""
    fixed_light: bool = False
    albedo_supervision: bool = False
    """Use ground-truth albedo maps in L_mat (eq. 20 a_gt) when the scene has them. Off by default: a real
    capture has none, and evaluating albedo MAE against the same maps would be circular."""
    colour_correction: Literal["auto", "on", "off"] = "auto"
    """Per-image gains (stage 2): ``auto`` = on when ``priors/colour/colour.json`` exists."""
    background: Literal["auto", "constant", "learned", "env"] = "auto"
    """``auto``: the scene's background colour for RGBA images, else a learned lat-long environment."""
    scene_type: Literal["auto", "unbounded", "room", "object"] = "auto"
    """``unbounded`` (``room`` is an alias): space is contracted beyond the scene box (:mod:`toolkit.space`) and
    a learned environment lies beyond the far radius — rooms, galleries, outdoor and real object captures with their
    surroundings; ``object``: an isolated object on a known background colour, nothing modelled outside the box.
    ``auto``: ``object`` when the photos have real transparency (RGBA with alpha < 1), else ``unbounded``."""
    scene_box: tuple | None = None
    """The scene box ``((xmin, ymin, zmin), (xmax, ymax, zmax))`` the run was trained with (filled by
    :func:`resolve_config`: the file's ``aabb`` or one fitted to sparse points, :mod:`toolkit.bounds`)."""
    scene_box_source: str = ""
    """Where :attr:`scene_box` came from."""
    seed: int = 0
    checkpoint_every: int = 500
    log_every: int = 25
    calibration_steps: int = 96
    """The first steps, whose schedule does not depend on the run's length (stage a, constant learning rate). A
    ``minutes`` budget becomes a step count after them, timed over their last 24 steps (after the occupancy
    warm-up of ``occupancy_warmup`` steps, so the timing is that of the rest of the run)."""
    snapshot_minutes: tuple[float, ...] = ()
    """Save the field at these elapsed training minutes (benchmarks evaluate them)."""
    device: str = "auto"

    def __post_init__(self):
        check_choice(self.shading, ("pbr", "radiance"), "shading")
        check_choice(self.colour_correction, ("auto", "on", "off"), "colour_correction")
        check_choice(self.background, ("auto", "constant", "learned", "env"), "background")
        check_choice(self.scene_type, ("auto", "unbounded", "room", "object"), "scene_type")
        if self.batch_rays < 16:
            raise ConfigError(f"batch_rays={self.batch_rays} must be >= 16")
        if self.steps < 0 or self.minutes < 0:
            raise ConfigError(f"steps={self.steps} and minutes={self.minutes} must be >= 0")
        if not 0.0 <= self.pretrain_fraction <= 1.0:
            raise ConfigError(f"pretrain_fraction={self.pretrain_fraction} must be in [0, 1]")
        if self.light_steps >= self.light_period:
            raise ConfigError(f"light_steps={self.light_steps} must be < light_period={self.light_period}")
        n_patch = self.ssim_patches * self.ssim_patch_size ** 2
        if n_patch >= self.batch_rays:
            raise ConfigError(f"ssim patches use {n_patch} rays, more than batch_rays={self.batch_rays}")
        if self.ssim_patches and self.ssim_patch_size <= 5:
            raise ConfigError(f"ssim_patch_size={self.ssim_patch_size} must be > 5 for the 11x11 window")
        for lr in ("lr_grid", "lr_net", "lr_light", "lr_colour"):
            if not getattr(self, lr) > 0:
                raise ConfigError(f"{lr}={getattr(self, lr)} must be positive")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        d = dict(d)
        fd = dict(d.pop("field"))
        fd["grid"] = HashGridConfig(**fd["grid"])
        if "shell_faces" in fd:
            fd["shell_faces"] = tuple(bool(f) for f in fd["shell_faces"])
        fd.setdefault("contraction", False)  # runs made before unbounded scenes were bounded
        if d.get("scene_box") is not None:
            d["scene_box"] = tuple(tuple(float(v) for v in row) for row in d["scene_box"])
        samplers = {k: dict(d.pop(k)) for k in ("sampler", "render_sampler")}
        for v in samplers.values():
            v.setdefault("normalise", "none")  # runs made before W was rank-normalised
        return cls(field=FieldConfig(**fd), sampler=SamplerConfig(**samplers["sampler"]),
                   render_sampler=SamplerConfig(**samplers["render_sampler"]), losses=LossWeights(**d.pop("losses")),
                   snapshot_minutes=tuple(d.pop("snapshot_minutes", ())), **d)


PRESETS = ("fast", "paper")


def make_config(preset: str = "fast", **overrides: Any) -> TrainConfig:
    """A named preset with overrides (``field=...``, ``steps=...``, ablation switches ...).

    ``paper``: the paper's setting — ``mlp`` field (PE + 8x256 LayerNorm backbone), 64 train / 128 test
    stratified samples + DARS fine samples, 1024-ray batches, AdamW at 5e-4 (the paper's 5e-14 is a typo)
    decaying to 5e-5, L_eikonal after step 2000. GPU-scale.
    ``fast``: the same decomposition, heads, PBR shading and DARS on CPU: hash-grid field (finest resolution
    from the data), 32 coarse + 8 fine samples, 4096-ray batches, L_eikonal after step 500.

    Ablation switches (Table 6): ``dars=False`` (w/o DARS), ``semantics=False`` (w/o semantic guidance),
    ``fixed_light=True``, ``mat_loss=False`` (w/o L_mat), ``baseline="nerf"`` (standard NeRF: stratified +
    hierarchical samples, radiance head, no priors, no room prior).
    """
    check_choice(preset, PRESETS, "preset")
    if preset == "paper":
        cfg = TrainConfig(
            preset="paper",
            field=FieldConfig(encoding="mlp", head_hidden=128),
            sampler=SamplerConfig(n_coarse=64, n_fine=8),
            render_sampler=SamplerConfig(n_coarse=128, n_fine=8, perturb=False),
            batch_rays=1024, ssim_patches=1, lr_net=5e-4, lr_light=5e-3, occupancy_resolution=128,
            losses=LossWeights(eikonal_start=2000),
        )
    else:
        cfg = TrainConfig(
            preset="fast",
            field=FieldConfig(encoding="grid"),
            sampler=SamplerConfig(n_coarse=32, n_fine=8),
            render_sampler=SamplerConfig(n_coarse=64, n_fine=8, perturb=False),
            batch_rays=4096, ssim_patches=4, losses=LossWeights(eikonal_start=500),
        )
    dars = overrides.pop("dars", None)
    mat_loss = overrides.pop("mat_loss", None)
    baseline = overrides.pop("baseline", None)
    if baseline not in (None, "nerf"):
        raise ConfigError(f"baseline={baseline!r}: the only baseline is 'nerf'")
    if baseline == "nerf":
        overrides.setdefault("shading", "radiance")
        overrides.setdefault("semantics", False)
        dars, mat_loss = False, False
        overrides.setdefault("fixed_light", True)
        overrides.setdefault("scene_type", "object")  # no room prior either: a plain transparent start
    if dars is not None:
        cfg = replace(cfg, sampler=replace(cfg.sampler, dars=bool(dars)),
                      render_sampler=replace(cfg.render_sampler, dars=bool(dars)))
    if mat_loss is False:
        cfg = replace(cfg, losses=replace(cfg.losses, mat=0.0))
    if "batch_rays" in overrides and "ssim_patches" not in overrides:  # patches take at most half a batch
        s = overrides.get("ssim_patch_size", cfg.ssim_patch_size)
        overrides["ssim_patches"] = min(cfg.ssim_patches, int(overrides["batch_rays"]) // (2 * s * s))
    return replace(cfg, **overrides)


SHELL_FADE = 0.1
"""Fraction of the run over which the (legacy, bounded-only) room prior's layer fades in, after stage (a)."""


def photos_have_transparency(scene: Scene, n: int = 3) -> bool:
    """Whether the photos are RGBA with real transparency (alpha < 1 somewhere in the first, middle or last
    photo): an object rendered on a known background. An alpha channel that is 255 everywhere does not count."""
    f0 = scene.frames[0]
    if f0.image_path is None or f0.image_path.suffix.lower() != ".png":
        return False
    from PIL import Image

    with Image.open(f0.image_path) as im:
        if im.mode not in ("RGBA", "LA"):
            return False
    idx = sorted({0, len(scene) // 2, len(scene) - 1})[:n]
    return any(bool((scene.load_image(i, with_alpha=True)[3] < 0.999).any()) for i in idx)


def resolve_scene_box(cfg: TrainConfig, scene: Scene, log=None) -> tuple[Scene, TrainConfig]:
    """The scene box of a run: ``cfg.scene_box`` when set (a resumed or loaded run), the file's ``aabb``, or one
    fitted to sparse points (the scene's own, else triangulated from the photos; :mod:`toolkit.bounds`)."""
    from dataclasses import replace as _r

    if cfg.scene_box is not None:
        return _r(scene, aabb=torch.tensor(cfg.scene_box, dtype=torch.float32)), cfg
    if scene.meta.get("aabb_source") == "file":
        box, src = scene.aabb.numpy().astype(np.float64), "file"
    else:
        from .bounds import scene_box_from_points, triangulate_sparse_points

        pts = triangulate_sparse_points(scene, log=log)
        c2w = scene.cameras.c2w.double().numpy()
        sb = scene_box_from_points(pts.points, c2w, scene.cameras.fx.double().numpy(),
                                   scene.cameras.width.double().numpy())
        box, src = sb.aabb, sb.source
    if log is not None:
        lo, hi = box
        log(f"[dars] scene box ({src}): [{lo[0]:.2f}, {lo[1]:.2f}, {lo[2]:.2f}] .. [{hi[0]:.2f}, {hi[1]:.2f}, {hi[2]:.2f}] m")
    cfg = _r(cfg, scene_box=tuple(tuple(float(v) for v in row) for row in box), scene_box_source=src)
    return _r(scene, aabb=torch.tensor(box, dtype=torch.float32)), cfg


def resolve_config(cfg: TrainConfig, scene: Scene, log=None) -> tuple[TrainConfig, Scene]:
    """Fill data-dependent settings; returns the config and the scene with its resolved box.

    * ``scene_type`` (``auto`` → ``unbounded`` or ``object``) and with it the field's contraction;
    * the scene box (:func:`resolve_scene_box`);
    * with ``auto_resolution`` the hash grid's finest level resolves a quarter of the pixel footprint at the median
      camera distance — ``next_pow2(4 · box extent / footprint)`` (twice that with contraction: the box spans half
      of each grid axis), clamped to [256, 2048].
    """
    kind = cfg.scene_type
    if kind == "auto":
        kind = "object" if photos_have_transparency(scene) else "unbounded"
    if kind == "room":
        kind = "unbounded"
    if cfg.scene_type != kind or cfg.field.contraction != (kind == "unbounded"):
        cfg = replace(cfg, scene_type=kind, field=replace(cfg.field, contraction=kind == "unbounded", shell=0.0))
    scene, cfg = resolve_scene_box(cfg, scene, log)
    if not cfg.auto_resolution or cfg.field.encoding != "grid":
        return cfg, scene
    cams = scene.cameras
    centre = scene.aabb.mean(0)
    dist = float((cams.origins - centre).norm(dim=-1).median())
    footprint = dist / float(cams.fx.median())
    extent = float((scene.aabb[1] - scene.aabb[0]).max())
    k = 8.0 if cfg.field.contraction else 4.0
    res = 2 ** math.ceil(math.log2(max(k * extent / footprint, 1.0)))
    res = int(min(2048, max(256, res)))
    grid = replace(cfg.field.grid, max_resolution=res, base_resolution=min(cfg.field.grid.base_resolution, res))
    return replace(cfg, field=replace(cfg.field, grid=grid), auto_resolution=False), scene


# ============================================================================ data
@dataclass
class TrainData:
    """Training-view tensors (CPU) and priors.

    Attributes:
        scene: the training split.
        images: float [V, 3, H, W] targets as stored (sRGB when ``scene.srgb``).
        labels: uint8 [V, H, W] class ids (255 unlabelled) or None.
        metal: bool [V, H, W] or None.
        weights: float [V, H, W] DARS weight maps W.
        distortion: float [V] L_distortion of each map.
        albedo_gt: float [V, 3, H, W] linear ground-truth albedo (only with albedo supervision) or None.
        l_env_init: float [9, 3] initial light and where it came from.
        colour_init: ColourTransforms or None.
    """

    scene: Scene
    images: torch.Tensor
    labels: torch.Tensor | None
    metal: torch.Tensor | None
    weights: torch.Tensor
    distortion: torch.Tensor
    albedo_gt: torch.Tensor | None
    l_env_init: torch.Tensor
    l_env_source: str
    colour_init: Any
    priors_used: dict


def grey_ambient_sh(mean_linear: float) -> torch.Tensor:
    """[9, 3] SH of a constant grey radiance that renders an albedo-0.5 Lambertian surface at ``mean_linear``."""
    sh = torch.zeros(9, 3)
    sh[0] = 2.0 * mean_linear / 0.282095
    return sh


def _priors_dir(scene: Scene, stage: str, priors_root: Path | None) -> Path:
    return Path(priors_root) / stage if priors_root is not None else scene.priors_dir(stage)


def _labels_for(scene: Scene, semantics: bool, priors_root: Path | None) -> tuple[torch.Tensor | None, str]:
    if not semantics:
        return None, "off"
    if scene.has_extra("semantic"):
        return torch.stack([scene.load_extra(i, "semantic") for i in range(len(scene))]).to(torch.uint8), "provided"
    d = _priors_dir(scene, "segment", priors_root)
    files = [d / f"{f.key}.png" for f in scene.frames]
    if d.is_dir() and all(p.is_file() for p in files):
        from .io import read_map

        labs = []
        for p in files:
            lab = np.asarray(read_map(p, "predicted labels"))
            labs.append(torch.from_numpy(lab[..., 0] if lab.ndim == 3 else lab))
        return torch.stack(labs).to(torch.uint8), f"predicted ({d})"
    return None, "none"


def prepare_data(scene: Scene, cfg: TrainConfig, log=print, priors_root: str | Path | None = None) -> TrainData:
    """Load training images and priors (labels, metal mask, W maps, light, colour) for ``scene``.

    Priors come from the scene (provided labels and metal masks) or from the prior stages' outputs under
    ``priors_root/<stage>/`` (default ``<scene>/priors/<stage>/``); W maps are computed here when absent. Without
    any priors: uniform weights, no labels, SH initialised to a grey ambient — training still works.
    """
    from .edges import WeightMapConfig, weight_map

    priors_root = Path(priors_root) if priors_root is not None else None
    images = scene.load_images()
    V, _, H, W = images.shape
    labels, label_src = _labels_for(scene, cfg.semantics, priors_root)
    metal = None
    if scene.has_extra("metal"):
        metal = torch.stack([scene.load_extra(i, "metal") for i in range(V)])
    priors: dict = {"labels": label_src, "metal": "provided" if metal is not None else "none"}
    wdir = _priors_dir(scene, "weights", priors_root)
    wfiles = [wdir / f"{f.key}.npy" for f in scene.frames]
    if wdir.is_dir() and all(p.is_file() for p in wfiles) and cfg.semantics:
        wm = torch.from_numpy(np.stack([np.load(p).astype(np.float32) for p in wfiles]))
        meta_p = wdir / "weights.json"
        dist = torch.zeros(V)
        if meta_p.is_file():
            meta = json.loads(meta_p.read_text())
            per = {d["key"]: d.get("distortion_loss", 0.0) for d in meta.get("images", []) if "key" in d}
            dist = torch.tensor([float(per.get(f.key, 0.0)) for f in scene.frames])
        priors["weights"] = f"loaded ({wdir})"
    else:
        wcfg = WeightMapConfig()
        maps_w, maps_d = [], []
        for i in range(0, V, 16):
            wm_i = weight_map(images[i:i + 16], None if labels is None else labels[i:i + 16].long(),
                              None if metal is None else metal[i:i + 16], wcfg)
            maps_w.append(wm_i.weights.float())
            maps_d.append(wm_i.distortion_loss.float())
        wm, dist = torch.cat(maps_w), torch.cat(maps_d)
        priors["weights"] = "computed (G" + ("+E" if labels is not None else "") + ("+M" if metal is not None else "") + ")"
    albedo_gt = None
    if cfg.albedo_supervision and scene.has_extra("albedo"):
        albedo_gt = torch.stack([scene.load_extra(i, "albedo") for i in range(V)])
        priors["albedo_supervision"] = "ground truth"
    lin = srgb_to_linear(images) if scene.srgb else images
    fg = lin
    if scene.background is not None:  # RGBA photos on a known background: the ambient level of the object only
        bg = torch.tensor(scene.background, dtype=images.dtype).view(1, 3, 1, 1)
        obj = ((images - bg).abs().amax(1, keepdim=True) > 0.02).expand_as(lin)
        if bool(obj.any()):
            fg = lin[obj]
    l_env, l_src = grey_ambient_sh(float(fg.mean())), "grey ambient"
    light_json = _priors_dir(scene, "light", priors_root) / "light.json"
    if light_json.is_file():
        d = json.loads(light_json.read_text())
        l_env, l_src = torch.tensor(d["coeffs"], dtype=torch.float32).reshape(9, 3), f"light network ({light_json})"
    priors["light"] = l_src
    colour_init = None
    cjson = _priors_dir(scene, "colour", priors_root) / "colour.json"
    if cfg.colour_correction != "off" and cjson.is_file():
        from .colour import ColourTransforms

        colour_init = ColourTransforms.from_json(json.loads(cjson.read_text()))
        if colour_init.keys is not None:
            order = {k: i for i, k in enumerate(colour_init.keys)}
            missing = [f.key for f in scene.frames if f.key not in order]
            if missing:
                raise DarsError(f"{cjson} has no colour transform for frames {missing[:5]}; re-run `dars priors colour`")
            colour_init = colour_init.subset([order[f.key] for f in scene.frames])
        priors["colour"] = f"loaded ({cjson})"
    elif cfg.colour_correction == "on":
        priors["colour"] = "identity (learned)"
    log(f"[dars] priors: " + ", ".join(f"{k}={v}" for k, v in priors.items()))
    wm = wm.clamp(0, 1)
    if cfg.sampler.normalise == "quantile":
        from .edges import quantile_normalise

        wm = quantile_normalise(wm)
    return TrainData(scene=scene, images=images, labels=labels, metal=metal, weights=wm, distortion=dist,
                     albedo_gt=albedo_gt, l_env_init=l_env, l_env_source=l_src, colour_init=colour_init,
                     priors_used=priors)


# ============================================================================ state
@dataclass
class TrainState:
    cfg: TrainConfig
    field: DarsField
    background: Background
    l_env: nn.Parameter
    colour: nn.Module | None
    optimizer: torch.optim.Optimizer
    light_optimizer: torch.optim.Optimizer
    occupancy: OccupancyGrid
    generator: torch.Generator
    ray_sampler: Any
    dars: DarsContext
    device: torch.device
    step: int = 0
    elapsed: float = 0.0
    snapshots_done: list = dc_field(default_factory=list)
    bad_steps: int = 0
    """Consecutive steps skipped for non-finite gradients (see :data:`MAX_BAD_STEPS`)."""


MAX_BAD_STEPS = 5
"""A step whose gradients are not finite is skipped (no update); this many in a row stop the run."""


def _device(cfg: TrainConfig) -> torch.device:
    if cfg.device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(cfg.device)


def _border_colour(images: torch.Tensor, srgb: bool) -> tuple[float, float, float]:
    """Median colour (linear) of the outermost pixel ring of all training images: the background a learned
    background model starts from (starting it wrong lets the optimiser hide it behind a shell of density)."""
    ring = torch.cat([images[:, :, 0, :], images[:, :, -1, :], images[:, :, :, 0], images[:, :, :, -1]], -1)
    med = ring.permute(1, 0, 2).reshape(3, -1).median(-1).values
    lin = srgb_to_linear(med) if srgb else med
    return tuple(float(c) for c in lin.clamp(0.0, 1.0))


def _background_for(scene: Scene, cfg: TrainConfig, images: torch.Tensor | None = None) -> Background:
    mode = cfg.background
    if mode == "auto":
        mode = "constant" if cfg.scene_type == "object" and photos_have_transparency(scene) else "env"
    if mode == "constant" or images is None:
        colour = tuple(float(c) for c in srgb_to_linear(np.asarray(scene.background, np.float64)))
    else:
        colour = _border_colour(images, scene.srgb)
    return Background(mode, colour)


def init_state(cfg: TrainConfig, data: TrainData) -> TrainState:
    """Fresh training state for ``data`` (seeded)."""
    dev = _device(cfg)
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    scene = data.scene
    fld = DarsField(cfg.field, scene.aabb).to(dev)
    bg = _background_for(scene, cfg, data.images).to(dev)
    l_env = nn.Parameter(data.l_env_init.clone().to(dev))
    colour = None
    if cfg.colour_correction == "on" or (cfg.colour_correction == "auto" and data.colour_init is not None):
        from .colour import ColourCorrection

        colour = ColourCorrection(len(scene), data.colour_init).to(dev)
    grid_params = [p for n, p in fld.named_parameters() if n.startswith("grid.")]
    net_params = [p for n, p in fld.named_parameters() if not n.startswith("grid.")]
    groups = [{"params": net_params, "lr": cfg.lr_net, "weight_decay": cfg.weight_decay, "name": "net"}]
    if grid_params:
        groups.append({"params": grid_params, "lr": cfg.lr_grid, "weight_decay": 0.0, "name": "grid"})
    if list(bg.parameters()):
        groups.append({"params": list(bg.parameters()), "lr": cfg.lr_grid, "weight_decay": 0.0, "name": "background"})
    if colour is not None:
        groups.append({"params": list(colour.parameters()), "lr": cfg.lr_colour, "weight_decay": 0.0, "name": "colour"})
    opt = torch.optim.AdamW(groups, betas=(0.9, 0.99), eps=1e-15)
    for g in opt.param_groups:
        g["initial_lr"] = g["lr"]
    light_opt = torch.optim.Adam([l_env], lr=cfg.lr_light, betas=(0.9, 0.99))
    for g in light_opt.param_groups:
        g["initial_lr"] = g["lr"]
    V, H, W = data.weights.shape
    extent = float((scene.aabb[1] - scene.aabb[0]).norm())
    occ = OccupancyGrid(scene.aabb, cfg.occupancy_resolution, step=extent / 1024.0, contraction=cfg.field.contraction,
                        far_radius=cfg.field.far_radius).to(dev)
    ray_sampler = build_ray_sampler(data.weights if cfg.sampler.dars else None, (V, H, W), cfg.sampler.rho)
    nb = neighbour_views(scene.cameras, cfg.sampler.n_neighbours)
    dars = DarsContext(scene.cameras.to(dev), data.weights.to(dev), nb.to(dev))
    return TrainState(cfg=cfg, field=fld, background=bg, l_env=l_env, colour=colour, optimizer=opt,
                      light_optimizer=light_opt, occupancy=occ, generator=gen, ray_sampler=ray_sampler, dars=dars,
                      device=dev)


def progress(state: TrainState) -> float:
    """Fraction of the run done, in [0, 1], by steps (a ``minutes`` budget is turned into steps by
    :func:`calibrate_steps`; until then the run is in its first, length-independent steps: 0)."""
    cfg = state.cfg
    return min(1.0, state.step / cfg.steps) if cfg.steps else 0.0


def lr_progress(state: TrainState) -> float:
    """Fraction of the learning-rate decay done: none during the first :attr:`TrainConfig.calibration_steps`
    steps (their schedule must not depend on the run's length), then exponential decay to the end."""
    cfg = state.cfg
    k = min(cfg.calibration_steps, max(0, cfg.steps - 1)) if cfg.steps else cfg.calibration_steps
    if not cfg.steps or state.step <= k:
        return 0.0
    return min(1.0, (state.step - k) / max(1, cfg.steps - k))


def calibrate_steps(state: TrainState, budget_minutes: float, t_window: float, n_window: int, log=print) -> dict:
    """Turn a wall-clock budget into the run's step count, once, after :attr:`TrainConfig.calibration_steps`:
    the seconds per step of the last ``n_window`` steps (after the occupancy warm-up, when a step costs what it
    will cost for the rest of the run) divide what is left of the budget. The run then follows a step schedule, so
    ``--steps N`` with the logged N reproduces it exactly on any machine (the first ``calibration_steps`` steps
    do not depend on the run's length). Returns the record kept in ``config.json``."""
    per_step = t_window / max(1, n_window)
    left = 60.0 * budget_minutes - state.elapsed
    steps = max(state.step, state.step + int(left / per_step))
    rec = {"minutes": budget_minutes, "seconds_per_step": round(per_step, 4), "at_step": state.step,
           "elapsed": round(state.elapsed, 2), "steps": steps}
    log(f"[dars] timing calibration: {per_step:.3f} s/step on this machine -> {steps} steps for {budget_minutes:g} min "
        f"(reproduce exactly with --steps {steps})")
    return rec


def _set_lr(state: TrainState) -> None:
    f = state.cfg.lr_final_factor ** lr_progress(state)
    for opt in (state.optimizer, state.light_optimizer):
        for g in opt.param_groups:
            g["lr"] = g["initial_lr"] * f


# ============================================================================ one step
@dataclass
class Batch:
    rays: Any
    target: torch.Tensor  # [R, 3] as stored
    iw: torch.Tensor  # [R]
    views: torch.Tensor  # [R]
    labels: torch.Tensor | None
    metal: torch.Tensor | None
    wray: torch.Tensor  # [R] W at each pixel
    albedo_gt: torch.Tensor | None
    n_random: int
    patch_iw: torch.Tensor | None  # [P]


def sample_batch(state: TrainState, data: TrainData) -> Batch:
    cfg = state.cfg
    gen = state.generator
    V, _, H, W = data.images.shape
    s = cfg.ssim_patch_size
    P = cfg.ssim_patches if (cfg.losses.ssim > 0 and H > s and W > s) else 0
    n_rand = cfg.batch_rays - P * s * s
    idx, iw = select_rays(state.ray_sampler, n_rand, gen)
    views, rem = idx // (H * W), idx % (H * W)
    rows, cols = rem // W, rem % W
    patch_iw = None
    if P:
        pidx, patch_iw = select_rays(state.ray_sampler, P, gen)
        pv, prem = pidx // (H * W), pidx % (H * W)
        pr = (prem // W - s // 2).clamp(0, H - s)
        pc = (prem % W - s // 2).clamp(0, W - s)
        dr, dc = torch.meshgrid(torch.arange(s), torch.arange(s), indexing="ij")
        views = torch.cat([views, pv.repeat_interleave(s * s)])
        rows = torch.cat([rows, (pr[:, None] + dr.reshape(1, -1)).reshape(-1)])
        cols = torch.cat([cols, (pc[:, None] + dc.reshape(1, -1)).reshape(-1)])
        iw = torch.cat([iw, patch_iw.repeat_interleave(s * s)])
    dev = state.device
    cams = state.dars.cameras
    scene = data.scene
    bounds = state.field.space if state.cfg.field.contraction else scene.aabb.to(dev)
    rays = generate_rays(cams, views.to(dev), pixels=torch.stack([cols, rows], -1).to(dev),
                         aabb=bounds, near=scene.near, far=scene.far)
    target = data.images[views, :, rows, cols].to(dev)
    labels = data.labels[views, rows, cols].long().to(dev) if data.labels is not None else None
    metal = data.metal[views, rows, cols].to(dev) if data.metal is not None else None
    albedo_gt = data.albedo_gt[views, :, rows, cols].to(dev) if data.albedo_gt is not None else None
    wray = data.weights[views, rows, cols].to(dev)
    return Batch(rays, target, iw.to(dev), views.to(dev), labels, metal, wray, albedo_gt, n_rand,
                 None if patch_iw is None else patch_iw.to(dev))


def _to_target_space(state: TrainState, data: TrainData, rgb_linear: torch.Tensor, views: torch.Tensor) -> torch.Tensor:
    if state.colour is not None:
        rgb_linear = state.colour(rgb_linear, views)
    # clamp forward, pass the gradient straight through: a hard clamp has zero gradient where the shaded colour
    # overshoots (e.g. a bright initial light on a white-background scene) and the run would stay saturated
    rgb_linear = rgb_linear - (rgb_linear - rgb_linear.clamp(0.0, 1.0)).detach()
    return linear_to_srgb(rgb_linear) if data.scene.srgb else rgb_linear


def _render(state: TrainState, batch: Batch, l_env: torch.Tensor):
    cfg = state.cfg
    return render_rays(state.field, batch.rays, cfg.sampler, state.occupancy, l_env, state.background,
                       cfg.shading, state.dars if cfg.sampler.dars else None,
                       batch.wray if cfg.sampler.dars else None, state.generator, deferred=cfg.deferred)


def _density_gradient(fld: DarsField, points: torch.Tensor, eps: float) -> torch.Tensor:
    offs = torch.eye(3, device=points.device, dtype=points.dtype) * eps
    pts = torch.cat([points + o for o in offs] + [points - o for o in offs])
    sig = fld.density(pts).reshape(6, -1)
    return torch.stack([(sig[i] - sig[i + 3]) / (2 * eps) for i in range(3)], -1)


def train_step(state: TrainState, data: TrainData) -> dict:
    """One field step (stage a: eq. 21; stage b: eq. 23). Returns the logged scalars."""
    cfg, lw = state.cfg, state.cfg.losses
    stage_b = progress(state) >= cfg.pretrain_fraction
    if hasattr(state.field, "shell_weight"):  # the room prior fades in over SHELL_FADE of the run after stage (a)
        w = min(1.0, max(0.0, (progress(state) - cfg.pretrain_fraction) / SHELL_FADE))
        if w > 0.0 and float(state.field.shell_weight) == 0.0:
            # the environment learned the room's walls in stage (a); left as it is, the optimiser would cancel the
            # layer wherever the environment already explains the photo. It restarts dark and relearns only what
            # is seen through the faces without a layer (sky, open doors).
            with torch.no_grad():
                for p in state.background.parameters():
                    p.copy_(state.background.dark_raw().to(p))
                    state.optimizer.state.pop(p, None)
        state.field.shell_weight.fill_(w)
    batch = sample_batch(state, data)
    out = _render(state, batch, state.l_env.detach())
    pred = _to_target_space(state, data, out.rgb, batch.views)
    terms: dict[str, torch.Tensor] = {}
    terms["rgb"] = rgb_l1(pred, batch.target, batch.iw)
    if batch.patch_iw is not None:
        s, P = cfg.ssim_patch_size, batch.patch_iw.shape[0]
        pp = pred[batch.n_random:].reshape(P, s, s, 3).permute(0, 3, 1, 2)
        tp = batch.target[batch.n_random:].reshape(P, s, s, 3).permute(0, 3, 1, 2)
        terms["ssim"] = ssim_loss(pp, tp, batch.patch_iw)
    if cfg.shading == "pbr" and lw.mat > 0:
        terms["mat"] = material_loss(out.albedo, out.roughness, out.metallic, batch.labels, batch.metal,
                                     batch.albedo_gt, batch.iw)
    if stage_b:
        terms["psnr_loss"] = psnr_loss(pred, batch.target, batch.iw)
        if lw.eikonal > 0 and state.step >= lw.eikonal_start and out.weights.numel():
            m = min(2048, out.weights.numel())
            sel = torch.multinomial(out.weights.detach().float() + 1e-8, m, replacement=False, generator=state.generator
                                    if out.weights.device.type == "cpu" else None)
            ext = float((data.scene.aabb[1] - data.scene.aabb[0]).mean())
            grad = _density_gradient(state.field, out.sample_points[sel].detach(), ext / 512.0)
            if out.deferred:
                n_pred = nn.functional.normalize(state.field.normal_head(out.sample_features[sel]), dim=-1, eps=1e-6)
            else:
                n_pred = state.field(out.sample_points[sel].detach(), shading="none").normal
            terms["eikonal"] = normal_consistency_loss(n_pred, grad, out.weights[sel])
    if cfg.shading == "pbr" and lw.orientation > 0 and out.weights.numel():
        if out.sample_normals is not None:
            terms["orientation"] = orientation_loss(out.sample_normals, batch.rays.directions[out.sample_ray_indices],
                                                    out.weights)
        else:
            terms["orientation"] = orientation_loss(out.normal, batch.rays.directions, out.opacity)
    if cfg.semantics and batch.labels is not None and lw.semantic > 0:
        terms["semantic"] = semantic_loss(out.semantic_logits, batch.labels, batch.iw)
    if out.light_residual is not None and lw.light_reg > 0 and out.weights.numel():
        lw_w = out.opacity if out.deferred else out.weights
        terms["light_reg"] = light_residual_loss(out.light_residual, state.l_env, lw_w)
    if lw.compactness > 0 and out.sample_s is not None:
        terms["compactness"] = compactness_loss(out.weights, out.sample_s[0], out.sample_s[1],
                                                out.sample_ray_indices, len(batch.rays))
    if state.colour is not None and lw.colour_reg > 0:
        terms["colour_reg"] = state.colour.regulariser()
    weight = {"rgb": lw.rgb, "ssim": lw.ssim, "mat": lw.mat, "psnr_loss": lw.psnr, "eikonal": lw.eikonal,
              "orientation": lw.orientation, "semantic": lw.semantic, "light_reg": lw.light_reg, "colour_reg": lw.colour_reg,
              "compactness": lw.compactness}
    loss = sum(weight[k] * v for k, v in terms.items())
    if not torch.isfinite(loss):
        bad = [k for k, v in terms.items() if not torch.isfinite(v)]
        raise TrainingDiverged(f"loss is {loss.item()} at step {state.step} (non-finite terms: {bad or 'sum'}); "
                               "training stopped, the last good checkpoint is kept — lower the learning rate "
                               "(--lr-scale) or check the input images")
    state.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    grads = [(g.get("name", "?"), p.grad) for g in state.optimizer.param_groups for p in g["params"]
             if p.grad is not None]
    finite = torch.stack([torch.isfinite(gr).all() for _, gr in grads]).tolist() if grads else []  # one sync per step
    if not all(finite):
        state.bad_steps += 1
        state.optimizer.zero_grad(set_to_none=True)
        if state.bad_steps >= MAX_BAD_STEPS:
            bad = sorted({name for (name, _), ok in zip(grads, finite) if not ok})
            raise TrainingDiverged(f"non-finite gradients in {bad} for {state.bad_steps} steps in a row "
                                   f"(last at step {state.step}); training stopped, the last good checkpoint is kept "
                                   "— lower the learning rate (--lr-scale) or check the input images")
    else:
        state.bad_steps = 0
        state.optimizer.step()
    with torch.no_grad():
        mse = (pred - batch.target).square().mean()
        res = {k: float(v) for k, v in terms.items()}
        res.update(loss=float(loss), psnr=float(-10 * torch.log10(mse.clamp_min(1e-10))),
                   distortion=float(data.distortion.mean()), samples_per_ray=float(out.samples_per_ray.float().mean()),
                   fine_per_ray=float(out.fine_counts.float().mean()), stage="b" if stage_b else "a")
        fc = out.fine_counts[out.fine_counts > 0]
        if fc.numel():
            res.update(fine_min=int(fc.min()), fine_max=int(fc.max()),
                       fine_changed=float((fc != cfg.sampler.n_fine).float().mean()))
    return res


def light_step(state: TrainState, data: TrainData) -> dict:
    """Eq. 22: the field fixed, l_env optimised on the L1 reprojection error."""
    batch = sample_batch(state, data)
    req = [p.requires_grad for p in state.field.parameters()]
    for p in state.field.parameters():
        p.requires_grad_(False)
    try:
        out = _render(state, batch, state.l_env)
        pred = _to_target_space(state, data, out.rgb, batch.views)
        loss = rgb_l1(pred, batch.target, batch.iw)
        if not torch.isfinite(loss):
            raise TrainingDiverged(f"light step loss is {loss.item()} at step {state.step}; training stopped")
        state.light_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        state.light_optimizer.step()
    finally:
        for p, r in zip(state.field.parameters(), req):
            p.requires_grad_(r)
    return {"reproj": loss.item()}


# ============================================================================ checkpoints
def _checkpoint_dict(state: TrainState) -> dict:
    return {
        "version": 1,
        "config": state.cfg.to_dict(),
        "step": state.step,
        "elapsed": state.elapsed,
        "field": state.field.state_dict(),
        "background": state.background.state_dict(),
        "background_mode": state.background.mode,
        "l_env": state.l_env.detach().cpu(),
        "colour": None if state.colour is None else state.colour.state_dict(),
        "optimizer": state.optimizer.state_dict(),
        "light_optimizer": state.light_optimizer.state_dict(),
        "occupancy": state.occupancy.state_dict(),
        "generator": state.generator.get_state(),
        "snapshots_done": list(state.snapshots_done),
    }


def save_checkpoint(state: TrainState, path: Path) -> None:
    """Write the state atomically (temp file + rename)."""
    with atomic_write(path) as f:
        torch.save(_checkpoint_dict(state), f)


def load_checkpoint(path: Path, state: TrainState) -> TrainState:
    """Restore ``state`` (built by :func:`init_state` with the same config) from ``path``."""
    ck = torch.load(path, map_location=state.device, weights_only=False)
    state.field.load_state_dict(ck["field"])
    state.background.load_state_dict(ck["background"])
    with torch.no_grad():
        state.l_env.copy_(ck["l_env"].to(state.device))
    if state.colour is not None and ck.get("colour") is not None:
        state.colour.load_state_dict(ck["colour"])
    state.optimizer.load_state_dict(ck["optimizer"])
    state.light_optimizer.load_state_dict(ck["light_optimizer"])
    state.occupancy = OccupancyGrid.from_state_dict(ck["occupancy"]).to(state.device)
    state.generator.set_state(ck["generator"])
    state.step = int(ck["step"])
    state.elapsed = float(ck["elapsed"])
    state.snapshots_done = list(ck.get("snapshots_done", []))
    return state


# ============================================================================ the loop
def _plot_curves(log_path: Path, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [json.loads(ln) for ln in log_path.read_text().splitlines() if ln.strip()]
    rows = [r for r in rows if r.get("kind") == "train"]
    if not rows:
        return
    keys = [k for k in ("loss", "rgb", "ssim", "psnr_loss", "mat", "eikonal", "orientation", "semantic", "light_reg", "distortion")
            if any(k in r for r in rows)]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for k in keys:
        xs = [r["step"] for r in rows if k in r]
        ys = [r[k] for r in rows if k in r]
        if k == "psnr":
            continue
        axes[0].plot(xs, ys, label=f"L_{k}" if k != "loss" else "L_total")
    axes[0].set_yscale("symlog", linthresh=1e-3)
    axes[0].set_xlabel("step")
    axes[0].set_title("training losses (Fig. 6)")
    axes[0].legend(fontsize=7)
    axes[1].plot([r["step"] for r in rows], [r["psnr"] for r in rows], color="tab:green")
    axes[1].set_xlabel("step")
    axes[1].set_ylabel("batch PSNR (dB)")
    axes[1].set_title("training PSNR")
    fig.tight_layout()
    tmp = out.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, out)


def train(scene_path: str | Path, out_dir: str | Path, cfg: TrainConfig, resume: bool = False, split: str = "train",
          progress_bar: bool = True, log=None, stop_at: int | None = None,
          priors_root: str | Path | None = None) -> Path:
    """Train on ``scene_path`` into the run directory ``out_dir``; returns the checkpoint path.

    With ``resume`` the run continues from ``out_dir/checkpoint.pt`` with the saved config (``cfg`` may only
    raise ``steps``/``minutes``). Without it, an existing run directory with a checkpoint is refused (nothing
    is overwritten). ``stop_at`` ends this call after that step (checkpointed) without changing the run's
    schedule, so a later ``resume`` continues exactly (time-sliced jobs). ``priors_root``: where the prior
    stages wrote their outputs (default: next to the scene); recorded in the run.
    """
    from tqdm import tqdm

    log = log or (lambda m: print(m, file=sys.stderr))
    out = Path(out_dir)
    ck_path = out / "checkpoint.pt"
    cfg_path = out / "config.json"
    if resume:
        if not ck_path.is_file():
            raise DarsError(f"--resume: no checkpoint at {ck_path}")
        saved = json.loads(cfg_path.read_text())
        base = TrainConfig.from_dict(saved["config"])
        steps = base.steps
        if cfg.steps:
            steps = max(cfg.steps, base.steps)
        elif cfg.minutes and base.minutes and cfg.minutes > base.minutes:  # a longer budget: same rate
            steps = int(round(base.steps * cfg.minutes / base.minutes))
        cfg = replace(base, steps=steps, minutes=max(cfg.minutes, base.minutes))
        saved_calibration = saved.get("calibration")
        scene_path = saved["scene"]
        split = saved.get("split", split)
        priors_root = saved.get("priors_root")
    else:
        saved_calibration = None
    if not resume and ck_path.exists():
        raise DarsError(f"{out} already holds a run (checkpoint.pt); pass --resume to continue it or choose another --out")
    if not cfg.steps and not cfg.minutes:
        raise ConfigError("give a training length: --steps N or --minutes M")
    if cfg.device != "auto" and cfg.device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device={cfg.device} requested but CUDA is not available")
    scene = load_scene(scene_path, split)
    cfg, scene = resolve_config(cfg, scene, log)
    out.mkdir(parents=True, exist_ok=True)
    data = prepare_data(scene, cfg, log, priors_root)
    state = init_state(cfg, data)
    if resume:
        load_checkpoint(ck_path, state)
        log(f"[dars] resumed {out} at step {state.step} ({state.elapsed / 60:.1f} min)")
    def write_run_config(calibration):
        write_json(cfg_path, {"config": cfg.to_dict(), "scene": str(Path(scene_path).resolve()), "split": split,
                              "priors_root": str(Path(priors_root).resolve()) if priors_root else None,
                              "priors": data.priors_used, "l_env_init": data.l_env_init.tolist(),
                              "l_env_source": data.l_env_source, "torch": torch.__version__,
                              "calibration": calibration})

    write_run_config(saved_calibration)
    log_path = out / "log.jsonl"
    if not resume and log_path.exists():
        log_path.unlink()
    total = cfg.steps if cfg.steps else None
    bar = tqdm(total=total, initial=state.step, disable=not progress_bar, file=sys.stderr, dynamic_ncols=True,
               unit="step", desc="train")
    t_last_ck = time.monotonic()
    t_window = None
    last = {}
    try:
        while True:
            if cfg.steps and state.step >= cfg.steps:
                break
            if stop_at is not None and state.step >= stop_at:
                break
            t0 = time.monotonic()
            _set_lr(state)
            if state.step % cfg.occupancy_every == 0:
                state.occupancy.update(state.field.density, state.generator,
                                       all_cells=state.step < cfg.occupancy_warmup,
                                       warmup=state.step < cfg.occupancy_warmup)
            in_b = progress(state) >= cfg.pretrain_fraction
            if (in_b and not cfg.fixed_light and cfg.shading == "pbr"
                    and state.step % cfg.light_period < cfg.light_steps):
                res = light_step(state, data)
                res["stage"] = "b-light"
            else:
                res = train_step(state, data)
            state.step += 1
            state.elapsed += time.monotonic() - t0
            last.update(res)
            if not cfg.steps:  # a minutes budget: fix the step count once the first steps are timed
                n_win = max(1, min(24, cfg.calibration_steps // 4))
                if state.step == cfg.calibration_steps - n_win:
                    t_window = state.elapsed
                if state.step >= cfg.calibration_steps or state.elapsed >= 60.0 * cfg.minutes:
                    t0_win = t_window if state.step >= cfg.calibration_steps and t_window is not None else 0.0
                    n_done = n_win if t0_win else state.step
                    rec = calibrate_steps(state, cfg.minutes, state.elapsed - t0_win, n_done, log)
                    cfg = replace(cfg, steps=rec["steps"])
                    state.cfg = cfg
                    bar.total = cfg.steps
                    write_run_config(rec)
            if state.step % cfg.log_every == 0 or state.step == 1:
                rec = {"kind": "train", "step": state.step, "elapsed": round(state.elapsed, 2),
                       "lr": state.optimizer.param_groups[0]["lr"], "occupancy": state.occupancy.occupancy_fraction(),
                       **{k: v for k, v in last.items()}}
                with open(log_path, "a") as f:
                    f.write(json.dumps(rec) + "\n")
            for m in cfg.snapshot_minutes:
                if m not in state.snapshots_done and state.elapsed >= 60.0 * m:
                    save_checkpoint(state, out / "snapshots" / f"checkpoint_{m:g}min.pt")
                    state.snapshots_done.append(m)
            if state.step % cfg.checkpoint_every == 0 or time.monotonic() - t_last_ck > 300:
                save_checkpoint(state, ck_path)
                t_last_ck = time.monotonic()
            bar.update(1)
            if "psnr" in last:
                eta = ""
                bar.set_postfix_str(f"loss {last.get('loss', float('nan')):.4f} psnr {last['psnr']:.2f} "
                                    f"{last.get('stage', '')} {eta}".strip())
    except TrainingDiverged as e:
        bar.close()
        log(f"[dars] {e}")
        raise
    except KeyboardInterrupt:
        bar.close()
        save_checkpoint(state, ck_path)
        log(f"[dars] interrupted at step {state.step}; checkpoint saved, continue with --resume")
        raise
    bar.close()
    save_checkpoint(state, ck_path)
    for m in cfg.snapshot_minutes:  # a budget that ends exactly at a milestone
        if m not in state.snapshots_done and state.elapsed >= 60.0 * m - 1.0:
            save_checkpoint(state, out / "snapshots" / f"checkpoint_{m:g}min.pt")
    try:
        _plot_curves(log_path, out / "loss_curves.png")
    except Exception as e:  # noqa: BLE001 - a plot must never lose a finished run
        log(f"[dars] could not plot loss curves: {e}")
    log(f"[dars] trained {state.step} steps in {state.elapsed / 60:.1f} min -> {ck_path}")
    return ck_path


# ============================================================================ runs
@dataclass
class Run:
    """A trained run loaded for rendering, evaluation and export."""

    path: Path
    cfg: TrainConfig
    scene_path: str
    split: str
    field: DarsField
    background: Background
    l_env: torch.Tensor
    occupancy: OccupancyGrid
    train_scene: Scene
    weight_maps: torch.Tensor | None
    step: int
    elapsed: float
    meta: dict

    def dars_for(self, c2w: torch.Tensor):
        """DARS render context for a camera pose (None when the run has DARS off)."""
        from .pipeline import render_dars_context

        if not self.cfg.render_sampler.dars or self.weight_maps is None:
            return None
        return render_dars_context(self.train_scene.cameras, self.weight_maps, c2w, self.cfg.render_sampler.n_neighbours)

    def priors_dir(self, stage: str) -> Path:
        """Where this run read (or would have read) the ``stage`` prior: ``--priors DIR`` if training had one."""
        return _priors_dir(self.train_scene, stage, self.meta.get("priors_root"))


def load_run(run_dir: str | Path, checkpoint: str | Path | None = None, device: str = "cpu",
             with_weights: bool = True) -> Run:
    """Load a run directory written by :func:`train` (``checkpoint`` picks a snapshot)."""
    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.json"
    ck_path = Path(checkpoint) if checkpoint else run_dir / "checkpoint.pt"
    if not cfg_path.is_file() or not ck_path.is_file():
        raise DarsError(f"{run_dir} is not a training run (needs config.json and checkpoint.pt); "
                        "create one with `dars train SCENE --out RUN`")
    meta = json.loads(cfg_path.read_text())
    cfg = TrainConfig.from_dict(meta["config"])
    ck = torch.load(ck_path, map_location=device, weights_only=False)
    scene = load_scene(meta["scene"], meta.get("split", "train"))
    if cfg.scene_box is not None:
        scene = replace(scene, aabb=torch.tensor(cfg.scene_box, dtype=torch.float32))
    fld = DarsField(cfg.field, scene.aabb).to(device)
    fld.load_state_dict(ck["field"])
    fld.eval()
    bg = Background(ck.get("background_mode", "env"))
    bg.load_state_dict(ck["background"])
    wm = None
    if with_weights and cfg.render_sampler.dars:
        data_cfg = replace(cfg, albedo_supervision=False)
        wm = prepare_data(scene, data_cfg, log=lambda m: None, priors_root=meta.get("priors_root")).weights
    return Run(path=run_dir, cfg=cfg, scene_path=meta["scene"], split=meta.get("split", "train"), field=fld,
               background=bg.to(device), l_env=ck["l_env"].to(device),
               occupancy=OccupancyGrid.from_state_dict(ck["occupancy"]).to(device), train_scene=scene,
               weight_maps=wm, step=int(ck["step"]), elapsed=float(ck["elapsed"]), meta=meta)


def field_callables(run: Run, chunk: int = 65536):
    """(density_fn, material_fn) of a loaded run, for meshing and baking (no gradients, chunked).

    ``density_fn(points [N, 3]) -> [N]``; ``material_fn(points [N, 3], normals=None) -> dict`` with ``albedo``
    [N, 3] (linear), ``roughness`` [N], ``metallic`` [N], ``normal`` [N, 3] (the normal head, unit) and
    ``semantic`` [N] (argmax class id). A ``radiance`` run (standard NeRF) has no materials: its albedo is
    its view-averaged radiance seen from above and roughness/metallic take defaults (1, 0).
    """
    fld = run.field
    dev = next(fld.parameters()).device

    @torch.no_grad()
    def density_fn(points: torch.Tensor) -> torch.Tensor:
        pts = torch.as_tensor(points, dtype=torch.float32)
        return torch.cat([fld.density(pts[i:i + chunk].to(dev)).cpu() for i in range(0, pts.shape[0], chunk)]) \
            if pts.shape[0] else pts.new_zeros(0)

    @torch.no_grad()
    def material_fn(points: torch.Tensor, normals: torch.Tensor | None = None) -> dict:
        pts = torch.as_tensor(points, dtype=torch.float32)
        keys = ("albedo", "roughness", "metallic", "normal", "semantic")
        parts: dict[str, list] = {k: [] for k in keys}
        for i in range(0, pts.shape[0], chunk):
            p = pts[i:i + chunk].to(dev)
            if run.cfg.shading == "pbr":
                o = fld(p, None, None, "pbr")
                parts["albedo"].append(o.albedo.cpu())
                parts["roughness"].append(o.roughness.cpu())
                parts["metallic"].append(o.metallic.cpu())
            else:
                d = torch.tensor([[0.0, 0.0, -1.0]], device=dev).expand(p.shape[0], 3)
                o = fld(p, d, None, "radiance")
                parts["albedo"].append(o.radiance.cpu())
                parts["roughness"].append(torch.ones(p.shape[0]))
                parts["metallic"].append(torch.zeros(p.shape[0]))
            parts["normal"].append(o.normal.cpu())
            parts["semantic"].append(o.semantic_logits.argmax(-1).cpu())
        return {k: torch.cat(v) for k, v in parts.items()}

    return density_fn, material_fn


def load_field_callables(run_dir: str | Path, checkpoint: str | Path | None = None):
    """``(density_fn, material_fn, aabb [2, 3], sh [9, 3], cameras)`` of a run directory (see
    :func:`field_callables`); ``cameras`` are the training cameras (for TSDF fusion and unseen-face removal)."""
    run = load_run(run_dir, checkpoint, with_weights=False)
    d, m = field_callables(run)
    return d, m, run.train_scene.aabb.clone(), run.l_env.detach().cpu().clone(), run.train_scene.cameras
