"""Training configuration: :class:`TrainConfig`, the named presets (:func:`make_config`) and the data-dependent
settings filled from the scene (:func:`resolve_config`: scene type and room prior, hash-grid resolution)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, replace
from dataclasses import field as dc_field
from typing import Any, Literal

import torch

from .._checks import ConfigError, check_choice
from ..encoding import HashGridConfig
from ..field import FieldConfig
from ..losses import LossWeights
from ..sampling import SamplerConfig
from ..scene import Scene

__all__ = ["TrainConfig", "PRESETS", "make_config", "resolve_config", "ROOM_SHELL", "SHELL_FADE",
           "photos_have_alpha"]


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
    scene_type: Literal["auto", "room", "object"] = "auto"
    """``room``: photos taken inside an enclosed room — the density starts with an opaque layer on the box faces
    (:attr:`FieldConfig.shell`) away from the cameras; ``object``: a transparent start everywhere. ``auto``: room
    when most training cameras are inside the scene box and the photos are not RGBA (:func:`resolve_config`)."""
    seed: int = 0
    checkpoint_every: int = 500
    log_every: int = 25
    snapshot_minutes: tuple[float, ...] = ()
    """Save the field at these elapsed training minutes (benchmarks evaluate them)."""
    device: str = "auto"

    def __post_init__(self):
        check_choice(self.shading, ("pbr", "radiance"), "shading")
        check_choice(self.colour_correction, ("auto", "on", "off"), "colour_correction")
        check_choice(self.background, ("auto", "constant", "learned", "env"), "background")
        check_choice(self.scene_type, ("auto", "room", "object"), "scene_type")
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
        return cls(field=FieldConfig(**fd), sampler=SamplerConfig(**d.pop("sampler")),
                   render_sampler=SamplerConfig(**d.pop("render_sampler")), losses=LossWeights(**d.pop("losses")),
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


ROOM_SHELL = 0.03
"""Thickness of the room prior's layer: 3 % of the box diagonal (25 cm on the gallery sample, about 1.3 coarse
steps of the ``fast`` preset, so every ray that reaches a face puts a sample in the layer)."""


SHELL_FADE = 0.1
"""Fraction of the run over which the room prior's layer fades in, after stage (a)."""


def _resolve_scene_type(cfg: TrainConfig, scene: Scene) -> TrainConfig:
    """``scene_type`` → the field's room prior: on for a room (most cameras inside the box, opaque photos), on the
    faces no camera comes within 1.5 layer thicknesses of (a camera inside the layer would see nothing)."""
    kind = cfg.scene_type
    lo, hi = scene.aabb[0], scene.aabb[1]
    cams = scene.cameras.origins.to(lo)
    if kind == "auto":
        inside = ((cams >= lo) & (cams <= hi)).all(-1).float().mean()
        kind = "room" if float(inside) > 0.5 and not photos_have_alpha(scene) else "object"
    if kind == "object":
        return replace(cfg, scene_type="object", field=replace(cfg.field, shell=0.0))
    eps = ROOM_SHELL * float((hi - lo).norm())
    clearance = torch.cat([cams - lo, hi - cams], -1).amin(0)  # [6] closest camera to each face
    faces = tuple(bool(c > 1.5 * eps) for c in clearance)
    return replace(cfg, scene_type="room", field=replace(cfg.field, shell=ROOM_SHELL if any(faces) else 0.0,
                                                         shell_faces=faces))


def resolve_config(cfg: TrainConfig, scene: Scene) -> TrainConfig:
    """Fill data-dependent settings:

    * ``scene_type`` (``auto`` → ``room`` or ``object``) and with it the field's room prior (:data:`ROOM_SHELL`);
    * with ``auto_resolution`` the hash grid's finest level resolves a quarter of the pixel footprint at the median
      camera distance — ``next_pow2(4 · box extent / footprint)``, clamped to [256, 2048] (tiny Lego 100 px: 512;
      Lego 400 px: 2048; the gallery sample: 1024).
    """
    if cfg.scene_type == "auto" or (cfg.scene_type == "room" and cfg.field.shell == 0.0):
        cfg = _resolve_scene_type(cfg, scene)
    if not cfg.auto_resolution or cfg.field.encoding != "grid":
        return cfg
    cams = scene.cameras
    centre = scene.aabb.mean(0)
    dist = float((cams.origins - centre).norm(dim=-1).median())
    footprint = dist / float(cams.fx.median())
    extent = float((scene.aabb[1] - scene.aabb[0]).max())
    res = 2 ** math.ceil(math.log2(max(4.0 * extent / footprint, 1.0)))
    res = int(min(2048, max(256, res)))
    grid = replace(cfg.field.grid, max_resolution=res, base_resolution=min(cfg.field.grid.base_resolution, res))
    return replace(cfg, field=replace(cfg.field, grid=grid), auto_resolution=False)


def photos_have_alpha(scene: Scene) -> bool:
    """Whether the photos are RGBA (objects on a known background colour, as Blender renders): the first frame."""
    f0 = scene.frames[0]
    if f0.image_path is None or f0.image_path.suffix.lower() != ".png":
        return False
    from PIL import Image

    with Image.open(f0.image_path) as im:
        return im.mode in ("RGBA", "LA")
