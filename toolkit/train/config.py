"""Training configuration: :class:`TrainConfig`, the named presets (:func:`make_config`) and the data-dependent
settings filled from the scene (:func:`resolve_config`: scene type and contraction, the scene box, hash-grid
resolution)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, replace
from dataclasses import field as dc_field
from typing import Any, Literal

import numpy as np
import torch

from .._checks import ConfigError, check_choice
from ..defaults import DARS_DEFAULT
from ..encoding import HashGridConfig
from ..field import FieldConfig
from ..losses import LossWeights
from ..sampling import SamplerConfig
from ..scene import Scene, photos_have_transparency

__all__ = ["TrainConfig", "PRESETS", "make_config", "resolve_config", "resolve_scene_box", "SHELL_FADE", "ROOM_LOSSES",
           "OBJECT_LOSSES", "EIKONAL", "photos_have_transparency", "patch_stride"]


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
    patch_stride: int | None = None
    """Photo pixels between neighbouring pixels of the SSIM patches, which the depth-normal and albedo-smoothness terms
    also use. None = from the data (:func:`patch_stride`): L_eikonal's step in pixels, so a patch covers the same
    length of surface at any photo resolution. Runs saved before the option load as 1."""
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
    occupancy_explore: float = 0.0
    """Fraction of the occupancy grid's cells kept sampled at random at each update (density can grow back where
    the grid pruned it too early)."""
    auto_resolution: bool = True
    """Set the hash grid's finest resolution from the data (:func:`resolve_config`)."""
    pretrain_fraction: float = 0.3
    """Stage (a) length as a fraction of the run (steps or minutes)."""
    light_period: int = 50
    light_steps: int = 5
    deferred: bool | None = False
    """True: the heads and the PBR shading run once per ray, on the ray's composited field feature
    h̄ = Σ w h / Σ w (``dars train --shade rays``); False: at every sample, the shaded colours composited
    (``--shade samples``; the ``paper`` preset and the standard-NeRF baseline); None (the ``fast`` preset's default):
    chosen by :func:`resolve_config` from the scene type — once per ray for an unbounded scene (a room), at every
    sample for an object. Per ray, a step costs 0.56x (gallery) to 0.46x (the fox) as much on the CPU, so a
    ``--minutes`` budget takes 1.8-2.2x the steps; at equal time it gave better test PSNR, normals and depth on every
    room pair measured, but on NeRF Lego (an object on a transparent background) 25.83 against 27.79 dB at a 15-minute
    budget (README, "Shading once per ray"). The dataclass default stays False so runs saved before the option load
    as they were trained; a resolved run records True or False."""
    shading: Literal["pbr", "radiance"] = "pbr"
    """``pbr``: decomposed (material + SH light); ``radiance``: plain NeRF colour head (baseline)."""
    semantics: bool = True
    """Semantic input: the semantic head's supervision (L_semantic against the labels) and the labels' edge term E in
    W (eq. 3; with it, W maps precomputed by ``dars priors weights``, which include E). Off = the "w/o semantic input"
    ablation: W is computed here from G (+ M when a metal mask exists) and the semantic head is unsupervised.
    L_mat's class terms are not part of this switch (:attr:`mat_labels`); the metal mask's M term in W is kept."""
    mat_labels: bool = True
    """L_mat's class terms read the labels: painting roughness → 0.8 on painting pixels, metallic → the metal mask on
    labelled pixels (eq. 20). Off: L_mat keeps only its ground-truth albedo term (when ``albedo_supervision``).
    Runs saved before this field existed turned both off with ``semantics=False``; :meth:`TrainConfig.from_dict`
    loads them as ``mat_labels=semantics``, so they resume exactly as they were trained."""
    fixed_light: bool = False
    light_init: Literal["full", "ambient"] = "full"
    """How the light prior starts l_env: ``full`` — all 9 SH coefficients of the estimate; ``ambient`` — only its
    band 0 (level and colour; the directional bands start at 0 and only the eq. 22 light stage learns them)."""
    light_fit: Literal["auto", "on", "off"] = "auto"
    """At the switch to stage (b), fit l_env's directional bands to the photos' shading on the rendered depth's
    normals (:mod:`toolkit.lightfit`): ``auto`` — for an object whose light starts as a grey ambient (no light
    estimate: RGBA photos); ``on`` — whatever the light started from; ``off`` — never. Runs saved before the option
    load as ``off``, as they trained."""
    labels: Literal["predicted", "ground-truth", "none"] = "predicted"
    """Where semantic labels and metal masks come from: ``predicted`` — the segmentation prior
    (``<priors>/segment/``; none when it was not run); ``ground-truth`` — the scene's own ``semantic_path`` and
    ``metal_path`` maps (experiments only: every report says so); ``none`` — no labels."""
    masks: Literal["auto", "ignore", "alpha", "off"] = "auto"
    """What the frames' ``mask_path`` maps mean (nerfstudio's key): ``ignore`` — a mask's 0 pixels (people, a tripod,
    glare) are never drawn and weigh nothing in any photometric term, nor in the geometry targets taken from the
    photos, and ``dars eval`` leaves them out of its image scores; ``alpha`` — the mask is the photo's alpha: the
    capture becomes an object on a known background, as RGBA photos with transparency are; ``off`` — masks are not
    read. ``auto``: ``alpha`` when the training frames' masks outline an object (they keep less than
    :data:`OBJECT_MASK_BORDER` of the photos' borders: NeRD's, IDR's and DTU's object masks), ``ignore`` when they
    have other masks, else ``off`` (resolved by :func:`resolve_config`, recorded in the run)."""
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
    background_start: Literal["auto", "border", "dark"] = "auto"
    """Where a learned background starts: ``border`` — the median colour of the photos' outer pixels; ``dark`` —
    black, so the field must explain what the photos show before the background may. ``auto``: border. Dark was the
    default for unbounded scenes (meant to turn a room's walls into surfaces rather than environment), but on unseen
    galleries it left fog and black holes: 300 steps of validation gallery 1000000 gave 18.4 dB test PSNR, albedo
    MAE 0.65, normal MAE 100° with dark against 22.0 dB, 0.24, 76° with border (one seed; 22.5 dB / 0.17 / 72° with
    border once the occupancy grid stopped pruning density the samples still see)."""
    lr_background: float = 0.0
    """Learning rate of the background (0: ``lr_grid``)."""
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
    schedule_knots: tuple = ()
    """``((step, planned_steps), ...)``: where a ``minutes`` budget was re-timed mid-run (:func:`toolkit.train.step.
    retime_steps`), and the step count planned until then; the schedule's progress is piecewise linear through them
    (empty: ``step / steps``). A first knot ``(c, 0)`` is a ``minutes`` budget's calibration at step ``c``: before it
    the run had no step count and its progress was 0 (stage a), whatever the count it then got. Filled by training;
    ``dars train --steps N --schedule-knots S:N,...`` replays such a run."""
    snapshot_minutes: tuple[float, ...] = ()
    """Save the field at these elapsed training minutes (benchmarks evaluate them)."""
    device: str = "auto"

    def __post_init__(self):
        check_choice(self.shading, ("pbr", "radiance"), "shading")
        check_choice(self.colour_correction, ("auto", "on", "off"), "colour_correction")
        check_choice(self.background, ("auto", "constant", "learned", "env"), "background")
        check_choice(self.scene_type, ("auto", "unbounded", "room", "object"), "scene_type")
        check_choice(self.labels, ("predicted", "ground-truth", "none"), "labels")
        check_choice(self.light_init, ("full", "ambient"), "light_init")
        check_choice(self.light_fit, ("auto", "on", "off"), "light_fit")
        check_choice(self.masks, ("auto", "ignore", "alpha", "off"), "masks")
        if self.batch_rays < 16:
            raise ConfigError(f"batch_rays={self.batch_rays} must be >= 16")
        if self.steps < 0 or self.minutes < 0:
            raise ConfigError(f"steps={self.steps} and minutes={self.minutes} must be >= 0")
        object.__setattr__(self, "schedule_knots", check_knots(self.schedule_knots, self.steps))
        if not 0.0 <= self.pretrain_fraction <= 1.0:
            raise ConfigError(f"pretrain_fraction={self.pretrain_fraction} must be in [0, 1]")
        if self.light_steps >= self.light_period:
            raise ConfigError(f"light_steps={self.light_steps} must be < light_period={self.light_period}")
        n_patch = self.ssim_patches * self.ssim_patch_size ** 2
        if n_patch >= self.batch_rays:
            raise ConfigError(f"ssim patches use {n_patch} rays, more than batch_rays={self.batch_rays}")
        if self.ssim_patches and self.ssim_patch_size <= 5:
            raise ConfigError(f"ssim_patch_size={self.ssim_patch_size} must be > 5 for the 11x11 window")
        if self.patch_stride is not None and self.patch_stride < 1:
            raise ConfigError(f"patch_stride={self.patch_stride} must be >= 1")
        for lr in ("lr_grid", "lr_net", "lr_light", "lr_colour"):
            if not getattr(self, lr) > 0:
                raise ConfigError(f"{lr}={getattr(self, lr)} must be positive")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        d = dict(d)
        # runs saved before "no semantic input" and "no L_mat class terms" were separate switches: semantics=False
        # also dropped the labels from L_mat
        d.setdefault("mat_labels", bool(d.get("semantics", True)))
        d.setdefault("masks", "off")  # runs made before mask_path was read trained on every pixel
        d.setdefault("light_fit", "off")  # runs made before the light was fitted to the shading
        d.setdefault("patch_stride", 1)  # runs made before the patches' stride followed the data
        fd = dict(d.pop("field"))
        fd["grid"] = HashGridConfig(**fd["grid"])
        if "shell_faces" in fd:
            fd["shell_faces"] = tuple(bool(f) for f in fd["shell_faces"])
        fd.setdefault("contraction", False)  # runs made before unbounded scenes were bounded
        fd.setdefault("light_residual_colour", "rgb")  # runs made before the grey residual had a coloured one
        if d.get("scene_box") is not None:
            d["scene_box"] = tuple(tuple(float(v) for v in row) for row in d["scene_box"])
        samplers = {k: dict(d.pop(k)) for k in ("sampler", "render_sampler")}
        for v in samplers.values():
            v.setdefault("normalise", "none")  # runs made before W was rank-normalised
        losses = dict(d.pop("losses"))
        for k in ROOM_LOSSES:
            # a room term a run was saved without did not exist when it trained: off, not today's room default
            # (which --resume would otherwise switch on partway through the run)
            losses.setdefault(k, 0.0)
        losses.setdefault("eikonal_step", EIKONAL["unbounded"][1])  # runs saved before the step was an option
        return cls(field=FieldConfig(**fd), sampler=SamplerConfig(**samplers["sampler"]),
                   render_sampler=SamplerConfig(**samplers["render_sampler"]), losses=LossWeights(**losses),
                   snapshot_minutes=tuple(d.pop("snapshot_minutes", ())), **d)


PRESETS = ("fast", "paper")


def make_config(preset: str = "fast", **overrides: Any) -> TrainConfig:
    """A named preset with overrides (``field=...``, ``steps=...``, ablation switches ...).

    ``paper``: the paper's setting — ``mlp`` field (PE + 8x256 LayerNorm backbone), 64 train / 128 test
    stratified samples + DARS fine samples, 1024-ray batches, AdamW at 5e-4 (the paper's 5e-14 is a typo)
    decaying to 5e-5, L_eikonal after step 2000. GPU-scale.
    ``fast``: the same decomposition, heads, PBR shading and DARS on CPU: hash-grid field (finest resolution
    from the data), 32 coarse + 8 fine samples, 4096-ray batches, L_eikonal after step 500, heads and shading
    once per ray in a room and at every sample on an object (``deferred=None``, resolved by :func:`resolve_config`;
    the ``radiance`` baseline shades every sample).

    Sampler: ``dars=True`` (DARS) or ``False`` (uniform pixel selection and hierarchical fine samples; the "w/o DARS"
    row of Table 6); None or not given: :data:`toolkit.defaults.DARS_DEFAULT`. Other ablation switches (Table 6):
    ``semantics=False`` (w/o semantic input: no L_semantic, no label edges E in W; L_mat keeps its class terms),
    ``fixed_light=True``, ``mat_loss=False`` (w/o L_mat: the whole material loss, class terms included),
    ``baseline="nerf"`` (standard NeRF: stratified + hierarchical samples, radiance head, no priors, no room prior).
    """
    check_choice(preset, PRESETS, "preset")
    if preset == "paper":
        cfg = TrainConfig(
            preset="paper",
            field=FieldConfig(encoding="mlp", head_hidden=128),
            sampler=SamplerConfig(n_coarse=64, n_fine=8),
            render_sampler=SamplerConfig(n_coarse=128, n_fine=8, perturb=False),
            batch_rays=1024, ssim_patches=1, lr_net=5e-4, lr_light=5e-3, occupancy_resolution=128,
            losses=LossWeights(eikonal=EIKONAL["unbounded"][0], eikonal_step=EIKONAL["unbounded"][1],
                               eikonal_start=2000),
        )
    else:
        cfg = TrainConfig(
            preset="fast",
            field=FieldConfig(encoding="grid"),
            sampler=SamplerConfig(n_coarse=32, n_fine=8),
            render_sampler=SamplerConfig(n_coarse=64, n_fine=8, perturb=False),
            batch_rays=4096, ssim_patches=4, losses=LossWeights(eikonal_start=500), deferred=None,
        )
    dars = overrides.pop("dars", None)
    dars = DARS_DEFAULT if dars is None else bool(dars)  # None: the measured default (toolkit.defaults)
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
        overrides.setdefault("deferred", False)  # NeRF's view-dependent colour at every sample
        cfg = replace(cfg, losses=replace(cfg.losses, **{k: 0.0 for k in ROOM_LOSSES},  # none of our additions
                                          eikonal=EIKONAL["unbounded"][0], eikonal_step=EIKONAL["unbounded"][1]))
    cfg = replace(cfg, sampler=replace(cfg.sampler, dars=dars), render_sampler=replace(cfg.render_sampler, dars=dars))
    if mat_loss is False:
        cfg = replace(cfg, losses=replace(cfg.losses, mat=0.0))
    if "batch_rays" in overrides and "ssim_patches" not in overrides:  # patches take at most half a batch
        s = overrides.get("ssim_patch_size", cfg.ssim_patch_size)
        overrides["ssim_patches"] = min(cfg.ssim_patches, int(overrides["batch_rays"]) // (2 * s * s))
    return replace(cfg, **overrides)


ROOM_LOSSES = {"sparse_depth": 0.1, "opacity": 0.1, "depth_normal": 0.5, "layout_depth": 0.1, "orientation": 1.0,
               "layout_normal": 0.1, "albedo_smooth": 0.2}
"""Loss weights that :func:`resolve_config` gives a room (``unbounded``) where the config leaves them None: the
geometry terms measured on the validation galleries (README, "Geometry of a room", "A room box from the photos" and
"Normals that face the camera"; the albedo prior: "Albedo that does not follow the light"). An object on a transparent background gets :data:`OBJECT_LOSSES`' weight where it
has one, else 0 (the opacity loss would fill its background; the others are not measured there)."""

EIKONAL = {"unbounded": (0.01, 1.0 / 512.0), "object": (0.1, 1.0 / 64.0)}
"""(weight, central-difference step as a fraction of the box's mean edge) of L_eikonal by scene type, where the
config leaves them None. A room keeps Table 1's 0.01 at the step it always had. An object's normals are otherwise
tied to nothing (its photometric loss is met by the per-point light residual whatever the normals), and they came
out one direction across the whole object; 10x the weight on −∇σ taken over 8x the step made them follow the
Ethiopian head's shape (README, "Normals that follow an object")."""

OBJECT_LOSSES = {"orientation": 0.1, "depth_normal": 0.5}
"""Loss weights left None that an object gets (not 0): the orientation loss at Ref-NeRF's weight, as before rooms
had their own, and the depth-normal term at a room's weight since 2026-12-07: on four generated objects the normal
head had stayed 45-70° from the surface while the rendered depth's normals were 13-15° from it; with the term the
mean normal MAE fell from 47° to 23-27° over two seeds (README, "An object's light from its shading")."""

SHELL_FADE = 0.1
"""Fraction of the run over which the (legacy, bounded-only) room prior's layer fades in, after stage (a)."""


def resolve_scene_box(cfg: TrainConfig, scene: Scene, log=None) -> tuple[Scene, TrainConfig]:
    """The scene box of a run: ``cfg.scene_box`` when set (a resumed or loaded run), the file's ``aabb``, or one
    fitted to sparse points (the scene's own, else triangulated from the photos; :mod:`toolkit.bounds`)."""
    from dataclasses import replace as _r

    if cfg.scene_box is not None:
        return _r(scene, aabb=torch.tensor(cfg.scene_box, dtype=torch.float32)), cfg
    if scene.meta.get("aabb_source") == "file":
        box, src = scene.aabb.numpy().astype(np.float64), "file"
    else:
        from ..bounds import scene_box_from_points, triangulate_sparse_points

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


OBJECT_MASK_BORDER = 0.5
"""Masks that keep less than this share of the photos' borders (the median photo) outline an object: the thing
photographed lies inside the frame and the masks cut it out of its surroundings (NeRD, IDR, DTU). Masks that mark
what to leave out (a visitor, a tripod: nerfstudio's use) keep most of the border. Not a tuned constant: the two
kinds sit near 0 and near 1."""


def masks_border_share(scene: Scene, n: int = 5) -> float | None:
    """The share of border pixels that the masks keep, on the median of ``n`` evenly spaced photos with a mask
    (None when no frame has one, or when those masks keep no pixel at all). Reads only the masks."""
    with_mask = [i for i, f in enumerate(scene.frames) if "mask" in f.extras]
    if not with_mask:
        return None
    pick = sorted({with_mask[round(k * (len(with_mask) - 1) / max(n - 1, 1))] for k in range(n)})
    shares, kept = [], 0
    for i in pick:
        m = scene.load_extra(i, "mask")
        border = torch.cat([m[0], m[-1], m[1:-1, 0], m[1:-1, -1]])
        shares.append(float(border.float().mean()))
        kept += int(m.sum())
    return float(np.median(shares)) if kept else None


def resolve_masks(masks: str, scene: Scene, log=None) -> tuple[str, Scene]:
    """What the frames' masks mean (:attr:`TrainConfig.masks`): ``auto`` becomes ``alpha`` when they outline an
    object (:func:`masks_border_share` under :data:`OBJECT_MASK_BORDER`), ``ignore`` when the photos have other
    masks, else ``off``. Returns the mode and ``scene`` reading its masks that way (the priors and the trainer
    both see the photos through it: an object's photos composited on the background)."""
    if masks == "auto":
        has = sum("mask" in f.extras for f in scene.frames)
        share = masks_border_share(scene) if has else None
        outline = share is not None and share < OBJECT_MASK_BORDER
        masks = "alpha" if outline else "ignore" if has else "off"
        if outline and log is not None:
            log(f"[dars] masks: {has} of {len(scene)} photos have a mask_path and the masks outline an object (they "
                f"keep {100 * share:.0f} % of the photos' borders, under {100 * OBJECT_MASK_BORDER:.0f} %): they are "
                "the photos' alpha, an object on a plain background (--masks ignore: only leave their 0 pixels out)")
        elif has and log is not None:
            log(f"[dars] masks: {has} of {len(scene)} photos have a mask_path; its 0 pixels are left out of training "
                "and scoring (--masks alpha: the masks are the photos' alpha; --masks off: not read)")
    if masks in ("alpha", "off") and scene.masks != masks:
        scene = replace(scene, masks=masks)
    return masks, scene


def patch_stride(scene: Scene, eikonal_step: float, patch: int) -> int:
    """Photo pixels between neighbouring pixels of the training patches (:attr:`TrainConfig.patch_stride`):
    L_eikonal's step (``eikonal_step`` x the box's mean edge) in pixels at the median camera distance from the box
    centre, rounded, at least 1, and at most what lets a ``patch`` x ``patch`` patch fit in the smallest photo.

    The depth-normal loss takes its target normals from central differences over ±1 patch pixel, so both of the
    normal head's targets are then measured on the same length of surface whatever the photos' resolution. On the
    Ethiopian head at 1000 px (2 mm pixels, the object's step 2 cm), two renders of the same ±1 pixel normals
    differed by 47-74° (a training render's depth is noisy at the scale of its samples), and a 16 px patch covered
    3 cm of the head. On the generated objects at 128 px and in a room (step 1/512 of the box) the rule gives 1 or 2,
    on NeRF Lego 2 at 200 px and 4 at 400 px (README, "Training patches measured on the object").
    """
    fit = patch_stride_limit(_smallest_side(scene), patch)
    return int(max(1, min(round(eikonal_step_pixels(scene, eikonal_step)), fit)))


def patch_stride_limit(side: int, patch: int) -> int:
    """The widest stride at which a ``patch`` x ``patch`` patch fits in a photo ``side`` pixels across (at least 1):
    its span ``(patch − 1) · stride + 1`` stays under ``side``, as :func:`toolkit.train.step.sample_batch` needs."""
    return max(1, (side - 2) // max(patch - 1, 1))


def _smallest_side(scene: Scene) -> int:
    """The shortest side, in pixels, of the scene's smallest photo."""
    cams = scene.cameras
    return min(int(cams.width.min()), int(cams.height.min()))


def pixel_footprint(scene: Scene) -> float:
    """Metres per pixel at the median camera distance from the box centre, with the median focal length."""
    cams = scene.cameras
    dist = float((cams.origins - scene.aabb.mean(0)).norm(dim=-1).median())
    return dist / float(cams.fx.median())


def eikonal_step_pixels(scene: Scene, eikonal_step: float) -> float:
    """L_eikonal's central-difference step (``eikonal_step`` x the box's mean edge) in pixels at the median camera
    distance from the box centre (:func:`pixel_footprint`)."""
    return float(eikonal_step) * float((scene.aabb[1] - scene.aabb[0]).mean()) / max(pixel_footprint(scene), 1e-12)


def resolve_config(cfg: TrainConfig, scene: Scene, log=None) -> tuple[TrainConfig, Scene]:
    """Fill data-dependent settings; returns the config and the scene with its resolved box.

    * ``masks`` (``auto`` → ``alpha`` when the photos' masks outline an object (:func:`masks_border_share` under
      :data:`OBJECT_MASK_BORDER`), ``ignore`` when they have other masks, else ``off``);
    * ``scene_type`` (``auto`` → ``unbounded`` or ``object``) and with it the field's contraction;
    * ``deferred`` left None: True (shading once per ray) for an unbounded scene, False for an object;
    * the loss weights left None (:data:`ROOM_LOSSES` for a room, :data:`OBJECT_LOSSES` or 0 for an object;
      L_eikonal's weight and step by :data:`EIKONAL`);
    * the scene box (:func:`resolve_scene_box`);
    * ``patch_stride`` left None: :func:`patch_stride` (a stride given that makes a patch wider than the smallest
      photo is an error);
    * with ``auto_resolution`` the hash grid's finest level resolves a quarter of the pixel footprint at the median
      camera distance — ``next_pow2(4 · box extent / footprint)`` (twice that with contraction: the box spans half
      of each grid axis), clamped to [256, 2048].
    """
    masks, scene = resolve_masks(cfg.masks, scene, log)
    cfg = replace(cfg, masks=masks)
    kind = cfg.scene_type
    if kind == "auto":
        kind = "object" if photos_have_transparency(scene) else "unbounded"
    if kind == "room":
        kind = "unbounded"
    if cfg.scene_type != kind or cfg.field.contraction != (kind == "unbounded"):
        cfg = replace(cfg, scene_type=kind, field=replace(cfg.field, contraction=kind == "unbounded", shell=0.0))
    if cfg.deferred is None:  # the fast preset: once per ray in a room, at every sample on an object (README)
        cfg = replace(cfg, deferred=kind == "unbounded")
        if log is not None:
            log("[dars] shading: " + ("once per ray (a room; --shade samples to shade every sample)" if cfg.deferred
                                      else "at every sample (an object; --shade rays to shade once per ray)"))
    auto = {k: (v if kind == "unbounded" else OBJECT_LOSSES.get(k, 0.0)) for k, v in ROOM_LOSSES.items()
            if getattr(cfg.losses, k) is None}
    auto.update({k: v for k, v in zip(("eikonal", "eikonal_step"), EIKONAL[kind]) if getattr(cfg.losses, k) is None})
    if auto:
        cfg = replace(cfg, losses=replace(cfg.losses, **auto))
        if log is not None and kind == "unbounded":
            log("[dars] room geometry losses: " + ", ".join(f"{k} {v:g}" for k, v in auto.items() if k in ROOM_LOSSES))
    if (cfg.losses.depth_normal or 0.0) > 0 and cfg.ssim_patches == 0:
        if "depth_normal" not in auto:
            raise ConfigError(f"depth_normal={cfg.losses.depth_normal:g} is computed on the step's image patches, "
                              "but ssim_patches=0: set ssim_patches > 0 or depth_normal 0")
        cfg = replace(cfg, losses=replace(cfg.losses, depth_normal=0.0))
        if log is not None:
            log("[dars] depth_normal off: it needs image patches and ssim_patches=0")
    scene, cfg = resolve_scene_box(cfg, scene, log)
    if cfg.patch_stride is not None and cfg.ssim_patches > 0:
        side = _smallest_side(scene)
        if cfg.patch_stride > patch_stride_limit(side, cfg.ssim_patch_size):
            span = (cfg.ssim_patch_size - 1) * cfg.patch_stride + 1
            raise ConfigError(f"patch_stride={cfg.patch_stride}: a {cfg.ssim_patch_size} px patch then spans {span} "
                              f"photo pixels, but the smallest photo is {side} px across; give --patch-stride "
                              f"{patch_stride_limit(side, cfg.ssim_patch_size)} or less, or leave it to the data")
    if cfg.patch_stride is None:
        r = patch_stride(scene, cfg.losses.eikonal_step, cfg.ssim_patch_size)
        cfg = replace(cfg, patch_stride=r)
        if log is not None and cfg.ssim_patches > 0:
            log(f"[dars] patches: {cfg.ssim_patch_size} x {cfg.ssim_patch_size} pixels, {r} photo pixel"
                f"{'s' if r > 1 else ''} apart (L_eikonal's step, 1/{1 / cfg.losses.eikonal_step:.0f} of the box, is "
                f"{eikonal_step_pixels(scene, cfg.losses.eikonal_step):.1f} px at the median camera distance; "
                "--patch-stride N sets it)")
    if not cfg.auto_resolution or cfg.field.encoding != "grid":
        return cfg, scene
    footprint = pixel_footprint(scene)
    extent = float((scene.aabb[1] - scene.aabb[0]).max())
    k = 8.0 if cfg.field.contraction else 4.0
    res = 2 ** math.ceil(math.log2(max(k * extent / footprint, 1.0)))
    res = int(min(2048, max(256, res)))
    grid = replace(cfg.field.grid, max_resolution=res, base_resolution=min(cfg.field.grid.base_resolution, res))
    return replace(cfg, field=replace(cfg.field, grid=grid), auto_resolution=False), scene


def format_knots(knots) -> str:
    """``--schedule-knots`` text of ``knots``: ``S:N,S:N``."""
    return ",".join(f"{int(s)}:{int(n)}" for s, n in knots)


def parse_knots(text: str) -> tuple:
    """``S:N,S:N`` (``--schedule-knots``: at step S the run had been planned to N steps) as ``((S, N), ...)``."""
    knots = []
    for part in filter(None, (t.strip() for t in text.split(","))):
        try:
            s, n = part.split(":")
            knots.append((int(s), int(n)))
        except ValueError:
            raise ConfigError(f"--schedule-knots: {part!r} is not STEP:STEPS (e.g. 1200:1780), as a --minutes "
                              "run's timing check logs it") from None
    return check_knots(tuple(knots))


def check_knots(knots: tuple, steps: int | None = None) -> tuple:
    """``knots`` as a tuple of ``(int, int)`` pairs, checked: steps increasing, each plan past its knot, every knot
    before ``steps`` (when given)."""
    knots = tuple((int(s), int(n)) for s, n in knots)
    prev = 0
    for i, (s, n) in enumerate(knots):
        if s <= prev or (n <= s and not (i == 0 and n == 0)):
            raise ConfigError(f"schedule knots {format_knots(knots)}: each is STEP:STEPS with the steps increasing "
                              "and STEPS (the plan at that step) beyond STEP; only the first may be STEP:0 (the "
                              "calibration of a --minutes run)")
        prev = s
    if steps and knots and knots[-1][0] >= steps:
        raise ConfigError(f"schedule knots {format_knots(knots)}: the last knot's step must be below steps={steps}")
    return knots
