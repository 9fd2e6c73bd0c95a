"""One training step: the explicit training state (:func:`init_state`), ray batches (:func:`sample_batch`), the field
step (:func:`train_step`, eqs. 21 and 23) and the light step (:func:`light_step`, eq. 22)."""

from __future__ import annotations

from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import Any

import numpy as np
import torch
from torch import nn

from .._checks import DarsError
from ..field import DarsField
from ..io import linear_to_srgb, srgb_to_linear
from ..losses import (albedo_smoothness_loss, compactness_loss, depth_normal_loss, layout_normal_loss, light_residual_loss,
                      material_loss, normal_consistency_loss, orientation_loss, planarity_loss, psnr_loss, rgb_l1,
                      semantic_loss, sparse_depth_loss, ssim_loss)
from ..pipeline import Background, DarsContext, RenderConfig, RenderInputs, render_rays
from ..pixels import PackedViews
from ..sampling import OccupancyGrid, build_ray_sampler, neighbour_views, select_rays
from ..scene import Scene, generate_rays
from .config import SHELL_FADE, TrainConfig, photos_have_transparency
from .config import format_knots
from .data import TrainData

__all__ = ["TrainingDiverged", "TrainState", "Batch", "MAX_BAD_STEPS", "init_state", "progress", "lr_progress",
           "calibrate_steps", "retime_steps", "RETIME_AT", "sample_batch", "train_step", "light_step"]


class TrainingDiverged(DarsError):
    """The loss became NaN or inf; the last good checkpoint is kept."""


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
    grad_sync: Any = None
    """``grad_sync(optimizer)`` after each backward pass (data-parallel runs average gradients over the ranks:
    :meth:`toolkit.distributed.Distributed.average_gradients`); None: a single process."""


MAX_BAD_STEPS = 5
"""A step whose gradients are not finite is skipped (no update); this many in a row stop the run."""


def resolve_device(name: str) -> torch.device:
    """A ``--device`` value as a torch device: ``auto`` is CUDA when present, else the CPU (the one place that rule
    lives: training, ``dars eval`` and the other commands that load a run use it)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


OBJECT_OCCUPANCY_STEPS = 1024
"""Instant-NGP's marching steps per box diagonal: an object's occupancy grid counts a cell empty when one step of
diagonal / this adds under 1 % opacity (a room's grid uses the coarse sample spacing; :func:`init_state`)."""


def train_device(cfg: TrainConfig) -> torch.device:
    """Where a run with ``cfg`` trains: ``cfg.device`` (:func:`resolve_device`)."""
    return resolve_device(cfg.device)


def _border_colour(images: PackedViews, srgb: bool, valid: PackedViews | None = None) -> tuple[float, float, float]:
    """Median colour (linear) of the outermost pixel ring of all training images (of its pixels ``valid`` keeps, the
    photos' masks): the background a learned background model starts from (starting it wrong lets the optimiser
    hide it behind a shell of density)."""
    rings = []
    for i in range(len(images)):
        x = images.raw(i)  # [H, W, 3] as stored
        ring = [x[0], x[-1], x[:, 0], x[:, -1]]
        if valid is not None:
            m = valid.raw(i)
            ring = [r[k] for r, k in zip(ring, (m[0], m[-1], m[:, 0], m[:, -1]))]
        rings += ring
    ring = torch.cat(rings).float()
    if ring.numel() == 0:  # every border pixel masked out: the median of all the images
        ring = images.data.float().reshape(-1, 3)
    med = ring.median(0).values / (255.0 if images.quantised else 1.0)
    lin = srgb_to_linear(med) if srgb else med
    return tuple(float(c) for c in lin.clamp(0.0, 1.0))


def _background_for(scene: Scene, cfg: TrainConfig, images: PackedViews | None = None,
                    valid: PackedViews | None = None) -> Background:
    mode = cfg.background
    if mode == "auto":
        mode = "constant" if cfg.scene_type == "object" and photos_have_transparency(scene) else "env"
    start = cfg.background_start
    if start == "auto":  # measured on unseen galleries and the sample: dark gave fog and 3-5 dB less (issue 16)
        start = "border"
    if mode == "constant" or images is None:
        colour = tuple(float(c) for c in srgb_to_linear(np.asarray(scene.background, np.float64)))
    elif start == "dark":
        colour = (1e-4, 1e-4, 1e-4)
    else:
        colour = _border_colour(images, scene.srgb, valid)
    return Background(mode, colour)


def init_state(cfg: TrainConfig, data: TrainData) -> TrainState:
    """Fresh training state for ``data`` (seeded)."""
    dev = train_device(cfg)
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    scene = data.scene
    fld = DarsField(cfg.field, scene.aabb).to(dev)
    bg = _background_for(scene, cfg, data.images, data.valid).to(dev)
    l_env = nn.Parameter(data.l_env_init.clone().to(dev))
    colour = None
    if cfg.colour_correction == "on" or (cfg.colour_correction == "auto" and data.colour_init is not None):
        from ..colour import ColourCorrection

        colour = ColourCorrection(len(scene), data.colour_init).to(dev)
    grid_params = [p for n, p in fld.named_parameters() if n.startswith("grid.")]
    net_params = [p for n, p in fld.named_parameters() if not n.startswith("grid.")]
    groups = [{"params": net_params, "lr": cfg.lr_net, "weight_decay": cfg.weight_decay, "name": "net"}]
    if grid_params:
        groups.append({"params": grid_params, "lr": cfg.lr_grid, "weight_decay": 0.0, "name": "grid"})
    if list(bg.parameters()):
        groups.append({"params": list(bg.parameters()), "lr": cfg.lr_background or cfg.lr_grid, "weight_decay": 0.0,
                       "name": "background"})
    if colour is not None:
        groups.append({"params": list(colour.parameters()), "lr": cfg.lr_colour, "weight_decay": 0.0, "name": "colour"})
    opt = torch.optim.AdamW(groups, betas=(0.9, 0.99), eps=1e-15)
    for g in opt.param_groups:
        g["initial_lr"] = g["lr"]
    light_opt = torch.optim.Adam([l_env], lr=cfg.lr_light, betas=(0.9, 0.99))
    for g in light_opt.param_groups:
        g["initial_lr"] = g["lr"]
    extent = float((scene.aabb[1] - scene.aabb[0]).norm())
    # A cell is skipped when a sample in it would add less than the grid's threshold opacity; the step that turns
    # its density into that opacity depends on what empty space is:
    # * a room (contracted space): the spacing our coarse samples actually have, the box diagonal over the coarse
    #   samples per ray. Against Instant-NGP's fine marching step (diagonal / 1024), thin density the renders still
    #   rely on (σ·Δ ≈ 0.2 per coarse sample) counted as empty and pruning it wrecked the fit (a gallery fell from
    #   18 to 14 dB).
    # * an object in its box (on a known background): Instant-NGP's diagonal / 1024. Everything around the object
    #   is empty, and the coarse step kept a fog that filled 96 % of the grid on NeRF Lego: 19.2 dB and 0.40 s a
    #   step at 600 steps, against 22.2 dB and 0.22 s with the fine step (README, "NeRF Lego").
    occ_step = extent / (cfg.sampler.n_coarse if cfg.field.contraction else OBJECT_OCCUPANCY_STEPS)
    occ = OccupancyGrid(scene.aabb, cfg.occupancy_resolution, step=occ_step,
                        contraction=cfg.field.contraction, far_radius=cfg.field.far_radius).to(dev)
    occ.explore = cfg.occupancy_explore
    ray_sampler = build_ray_sampler(data.weights if cfg.sampler.dars else None, data.weights, cfg.sampler.rho,
                                    valid=data.valid)
    nb = neighbour_views(scene.cameras, cfg.sampler.n_neighbours)
    dars = DarsContext(scene.cameras.to(dev), data.weights.to(dev), nb.to(dev))
    return TrainState(cfg=cfg, field=fld, background=bg, l_env=l_env, colour=colour, optimizer=opt,
                      light_optimizer=light_opt, occupancy=occ, generator=gen, ray_sampler=ray_sampler, dars=dars,
                      device=dev)


def progress(state: TrainState) -> float:
    """Fraction of the run done, in [0, 1], by steps (a ``minutes`` budget is turned into steps by
    :func:`calibrate_steps`; until then the run is in its first, length-independent steps: 0)."""
    return _progress_at(state.cfg, state.step)


def _progress_at(cfg, step: int) -> float:
    """:func:`progress` of step ``step`` of a run with config ``cfg``: ``step / cfg.steps``, or, where a ``minutes``
    budget was re-timed mid-run (:attr:`TrainConfig.schedule_knots`), piecewise linear: each stretch runs on to the
    step count planned in it, so the schedule stays continuous and a replay computes the same numbers."""
    return _piecewise(step, 0, cfg) if cfg.steps else 0.0


def _piecewise(step: int, start: int, cfg) -> float:
    """0 at ``start``, 1 at ``cfg.steps``; linear in between, bent at each knot ``(s, n)`` of
    :attr:`TrainConfig.schedule_knots` (up to step ``s`` the run was planned to end at step ``n``). Without knots this
    is exactly ``(step - start) / (cfg.steps - start)``. A knot ``(c, 0)`` is a ``minutes`` budget's calibration at
    step ``c``: before it the run had no step count (0), and it bends nothing after it."""
    s0, p0 = start, 0.0
    for s1, n in cfg.schedule_knots:
        if n == 0:
            if step < s1:
                return 0.0
            continue
        if s1 <= s0:
            continue
        if step <= s1:
            return min(1.0, p0 + (step - s0) / max(1, n - s0) * (1.0 - p0))
        p0, s0 = p0 + (s1 - s0) / max(1, n - s0) * (1.0 - p0), s1
    return min(1.0, p0 + (step - s0) / max(1, cfg.steps - s0) * (1.0 - p0))


def is_light_step(cfg, step: int) -> bool:
    """Whether training step ``step`` (0-based) of a run with config ``cfg`` is an eq. 22 l_env step rather than a
    field step: in stage b (``step / cfg.steps >= cfg.pretrain_fraction``), the first ``cfg.light_steps`` of every
    ``cfg.light_period`` steps, unless the run has fixed lighting or radiance shading. A ``minutes`` budget has no step
    count until it is calibrated (progress 0 until then), as :func:`progress` reads it."""
    if cfg.fixed_light or cfg.shading != "pbr":
        return False
    return _progress_at(cfg, step) >= cfg.pretrain_fraction and step % cfg.light_period < cfg.light_steps


def wants_light_fit(cfg, l_env_source: str) -> bool:
    """Whether a run fits l_env's directional bands to the photos' shading when stage (b) starts
    (:attr:`TrainConfig.light_fit`, :mod:`toolkit.lightfit`): never with a fixed light or radiance shading; ``auto``
    only for an object whose light starts as a grey ambient (``l_env_source`` as :func:`prepare_data` names it)."""
    if cfg.fixed_light or cfg.shading != "pbr" or cfg.light_fit == "off":
        return False
    return cfg.light_fit == "on" or (cfg.scene_type == "object" and l_env_source.startswith("grey ambient"))


def stage_b_starts(cfg, step: int) -> bool:
    """Whether step ``step`` (0-based) is the first of stage (b): none when stage (a) has no steps."""
    return step >= 1 and _progress_at(cfg, step) >= cfg.pretrain_fraction > _progress_at(cfg, step - 1)


def field_steps(cfg, steps: int | None = None) -> int:
    """How many of the first ``steps`` (default ``cfg.steps``) training steps optimise the field: the rest are eq. 22
    l_env steps (:func:`is_light_step`). At a fixed step count the lighting stage takes its steps from the field's
    (600 steps with the defaults: 560 field steps)."""
    n = int(cfg.steps if steps is None else steps)
    return n - sum(1 for k in range(n) if is_light_step(cfg, k))


def lr_progress(state: TrainState) -> float:
    """Fraction of the learning-rate decay done: none during the first :attr:`TrainConfig.calibration_steps`
    steps (their schedule must not depend on the run's length), then exponential decay to the end."""
    cfg = state.cfg
    k = min(cfg.calibration_steps, max(0, cfg.steps - 1)) if cfg.steps else cfg.calibration_steps
    if not cfg.steps or state.step <= k:
        return 0.0
    return _piecewise(state.step, k, cfg)  # bent where a minutes budget was re-timed, as the progress is


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
    knot = ""
    if steps > state.step:  # the steps so far ran with no step count (progress 0): a replay must know where
        rec["schedule_knots"] = [[int(state.step), 0]]
        knot = f" --schedule-knots {state.step}:0"
    log(f"[dars] timing calibration: {per_step:.3f} s/step on this machine -> {steps} steps for {budget_minutes:g} min "
        f"(reproduce exactly with --steps {steps}{knot})")
    return rec


RETIME_AT = (0.25, 0.5, 0.75)
"""Progress at which a calibrated ``minutes`` budget checks its clock again (:func:`retime_steps`)."""
RETIME_TOLERANCE = 0.08
"""A re-timing changes the step count only when the projected run time misses the budget by more than this share."""


def retime_steps(cfg, step: int, elapsed: float, mark: tuple[int, float], log=print) -> tuple[int, tuple] | None:
    """Check a calibrated ``minutes`` budget against the clock at step ``step`` (``elapsed`` seconds): the seconds per
    step since ``mark`` (``(step, elapsed)`` of the calibration or the last check) project the run's end. When that
    misses the budget by more than :data:`RETIME_TOLERANCE` (a step's cost grew as the occupancy grid filled, or the
    machine got busier), the remaining steps are rescaled (at most halved or doubled per check) and a knot
    ``(step, steps planned until then)`` keeps the schedule continuous (:func:`progress`). Returns
    ``(steps, knots)``, or None when the run is on time. ``--steps N --schedule-knots S:N,...`` (logged) replays it."""
    n_done = step - mark[0]
    if n_done <= 0 or step >= cfg.steps:
        return None
    per_step = (elapsed - mark[1]) / n_done
    budget = 60.0 * cfg.minutes
    projected = elapsed + (cfg.steps - step) * per_step
    if abs(projected - budget) <= RETIME_TOLERANCE * budget:
        log(f"[dars] timing check at step {step}: {per_step:.3f} s/step, on schedule ({projected / 60:.3g} of "
            f"{cfg.minutes:g} min)")
        return None
    rest = cfg.steps - step
    new_rest = int(max(0.0, budget - elapsed) / max(per_step, 1e-9))
    new_rest = int(min(2 * rest, max((rest + 1) // 2, new_rest, 1)))
    knots = tuple(cfg.schedule_knots) + ((int(step), int(cfg.steps)),)
    steps = step + new_rest
    log(f"[dars] timing check at step {step}: {per_step:.3f} s/step, the run would take {projected / 60:.3g} of "
        f"{cfg.minutes:g} min -> {steps} steps (reproduce exactly with --steps {steps} --schedule-knots "
        f"{format_knots(knots)})")
    return steps, knots


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
    pixels: torch.Tensor | None = None  # [R] int64 packed pixel indices (CPU) of the rays


def sample_batch(state: TrainState, data: TrainData) -> Batch:
    """A batch of training rays: ``batch_rays`` pixels drawn by the ray sampler (the last ``ssim_patches`` x s x s
    of them as s x s patches around drawn pixels, ``patch_stride`` photo pixels apart), their targets converted from
    the packed buffers to float here."""
    cfg = state.cfg
    gen = state.generator
    lay = data.weights  # the views' sizes
    s, r = cfg.ssim_patch_size, cfg.patch_stride or 1
    span = (s - 1) * r + 1  # a patch's extent in photo pixels
    fits = int(lay.heights.min()) > span and int(lay.widths.min()) > span
    patches_used = cfg.losses.ssim > 0 or (cfg.losses.depth_normal or 0.0) > 0 or (cfg.losses.albedo_smooth or 0.0) > 0
    P = cfg.ssim_patches if (patches_used and fits) else 0
    n_rand = cfg.batch_rays - P * s * s
    idx, iw = select_rays(state.ray_sampler, n_rand, gen)
    views, rows, cols = lay.locate(idx)
    patch_iw = None
    if P:
        pidx, patch_iw = select_rays(state.ray_sampler, P, gen)
        pv, prow, pcol = lay.locate(pidx)
        pr = torch.minimum((prow - span // 2).clamp_min(0), lay.heights[pv] - span)
        pc = torch.minimum((pcol - span // 2).clamp_min(0), lay.widths[pv] - span)
        dr, dc = torch.meshgrid(torch.arange(s) * r, torch.arange(s) * r, indexing="ij")
        views = torch.cat([views, pv.repeat_interleave(s * s)])
        rows = torch.cat([rows, (pr[:, None] + dr.reshape(1, -1)).reshape(-1)])
        cols = torch.cat([cols, (pc[:, None] + dc.reshape(1, -1)).reshape(-1)])
        iw = torch.cat([iw, patch_iw.repeat_interleave(s * s)])
    flat = lay.flat_index(views, rows, cols)
    if P and data.valid is not None:  # a patch's masked pixels weigh nothing; SSIM drops a patch that has any
        ok = data.valid.gather(flat).to(iw.dtype)
        iw = iw * ok
        patch_iw = patch_iw * ok[n_rand:].reshape(P, -1).amin(1)
    dev = state.device
    rays = _training_rays(state, data, views, rows, cols)
    target = data.images.gather(flat).to(dev)
    labels = data.labels.gather(flat).long().to(dev) if data.labels is not None else None
    metal = data.metal.gather(flat).to(dev) if data.metal is not None else None
    albedo_gt = data.albedo_gt.gather(flat).to(dev) if data.albedo_gt is not None else None
    wray = data.weights.gather(flat).to(dev)
    return Batch(rays, target, iw.to(dev), views.to(dev), labels, metal, wray, albedo_gt, n_rand,
                 None if patch_iw is None else patch_iw.to(dev), flat)


SPARSE_DEPTH_RAYS = 256
"""Rays per step through pixels with a depth target, on top of ``batch_rays``: for each of ``losses.sparse_depth``
(triangulated points) and ``losses.layout_depth`` (the room's box) that is on."""


def _training_rays(state: TrainState, data: TrainData, views: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor):
    """Rays of training pixels (views, rows, cols: int64 [R]) on the training device, bounded as the field is."""
    dev, scene = state.device, data.scene
    bounds = state.field.space if state.cfg.field.contraction else scene.aabb.to(dev)
    return generate_rays(state.dars.cameras, views.to(dev), pixels=torch.stack([cols, rows], -1).to(dev),
                         aabb=bounds, near=scene.near, far=scene.far)


def _render_pixels(state: TrainState, data: TrainData, views: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor):
    """Rays of training pixels and their deferred render (the extra rays of the geometry terms: they use weights,
    depth and opacity, not the shaded colour). Returns (rays, outputs)."""
    rays = _training_rays(state, data, views, rows, cols)
    wray = data.weights.gather(data.weights.flat_index(views, rows, cols)).to(state.device)
    return rays, _render(state, rays, wray, state.l_env.detach(), deferred=True)


def _sparse_depth_term(state: TrainState, data: TrainData, sd: dict,
                       normals: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`toolkit.losses.sparse_depth_loss` on ``SPARSE_DEPTH_RAYS`` rays drawn from ``sd`` (pixels with a
    depth target: ``data.sparse_depth`` or ``data.layout_depth``), and with ``normals`` the
    :func:`toolkit.losses.layout_normal_loss` of the same rays against ``sd["normal"]`` (``data.layout_depth``'s face
    normals); None without."""
    dev = state.device
    k = len(sd["depth"])
    pick = torch.randint(0, k, (min(k, SPARSE_DEPTH_RAYS),), generator=state.generator)
    rays, out = _render_pixels(state, data, sd["views"][pick], sd["rows"][pick], sd["cols"][pick])
    ri = out.sample_ray_indices
    t = ((out.sample_points - rays.origins[ri]) * rays.directions[ri]).sum(-1)
    t_target = sd["depth"][pick].to(dev) / rays.z_scale.reshape(-1)  # camera-axis depth -> distance along the ray
    depth = sparse_depth_loss(out.weights, t, ri, t_target, len(pick))
    return depth, (layout_normal_loss(out.normal, sd["normal"][pick].to(dev), out.opacity) if normals else None)


PLANAR_REGIONS = 8
"""Textureless regions drawn per step for ``losses.planar``."""
PLANAR_RAYS = 32
"""Rays drawn from each of them (the plane is fitted to these)."""


def _planar_term(state: TrainState, data: TrainData) -> torch.Tensor:
    """:func:`toolkit.losses.planarity_loss` on ``PLANAR_RAYS`` rays of each of ``PLANAR_REGIONS`` regions drawn
    from ``data.planar``."""
    pl = data.planar
    off = pl["offsets"]
    K = len(off) - 1
    reg = torch.randint(0, K, (PLANAR_REGIONS,), generator=state.generator)
    size = (off[reg + 1] - off[reg]).double()
    u = torch.rand(PLANAR_REGIONS, PLANAR_RAYS, generator=state.generator, dtype=torch.float64)
    pick = (off[reg][:, None] + (u * size[:, None]).long().clamp_max(size.long()[:, None] - 1)).reshape(-1)
    rays, out = _render_pixels(state, data, pl["views"][pick], pl["rows"][pick], pl["cols"][pick])
    t = out.depth / rays.z_scale.reshape(-1)  # camera-axis depth -> distance along the ray
    pts = (rays.origins + rays.directions * t[:, None]).reshape(PLANAR_REGIONS, PLANAR_RAYS, 3)
    a = out.opacity.reshape(PLANAR_REGIONS, PLANAR_RAYS)
    scale = (t.detach().reshape(PLANAR_REGIONS, PLANAR_RAYS) * a).sum(1) / a.sum(1).clamp_min(1e-6)
    return planarity_loss(pts, a, scale)


def _depth_normal_term(out, batch: Batch, s: int) -> torch.Tensor:
    """:func:`toolkit.losses.depth_normal_loss` on the batch's s x s SSIM patches (the last rays of the batch; its
    ±1 pixel stencil spans ``patch_stride`` photo pixels)."""
    n0, P = batch.n_random, batch.patch_iw.shape[0]
    rays = batch.rays
    o, d = rays.origins[n0:], rays.directions[n0:]
    t = out.depth[n0:] / rays.z_scale.reshape(-1)[n0:]  # camera-axis depth -> distance along the ray
    pts = (o + d * t[:, None]).reshape(P, s, s, 3)
    w = (out.opacity[n0:] * batch.iw[n0:]).reshape(P, s, s)
    return depth_normal_loss(pts, out.normal[n0:].reshape(P, s, s, 3), d.reshape(P, s, s, 3), w)


def _to_target_space(state: TrainState, data: TrainData, rgb_linear: torch.Tensor, views: torch.Tensor) -> torch.Tensor:
    if state.colour is not None:
        rgb_linear = state.colour(rgb_linear, views)
    # clamp forward, pass the gradient straight through: a hard clamp has zero gradient where the shaded colour
    # overshoots (e.g. a bright initial light on a white-background scene) and the run would stay saturated
    rgb_linear = rgb_linear - (rgb_linear - rgb_linear.clamp(0.0, 1.0)).detach()
    return linear_to_srgb(rgb_linear) if data.scene.srgb else rgb_linear


def _render(state: TrainState, rays, wray: torch.Tensor, l_env: torch.Tensor, deferred: bool | None = None):
    """Render training rays (``wray``: W at each ray's pixel); ``deferred`` None = the run's setting."""
    cfg = state.cfg
    rcfg = RenderConfig(sampler=cfg.sampler, shading=cfg.shading,
                        deferred=cfg.deferred if deferred is None else deferred)
    inputs = RenderInputs(state.occupancy, l_env, state.background, dars=state.dars if cfg.sampler.dars else None)
    return render_rays(state.field, rays, rcfg, inputs, wray if cfg.sampler.dars else None, state.generator)


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
    out = _render(state, batch.rays, batch.wray, state.l_env.detach())
    pred = _to_target_space(state, data, out.rgb, batch.views)
    terms: dict[str, torch.Tensor] = {}
    terms["rgb"] = rgb_l1(pred, batch.target, batch.iw)
    if batch.patch_iw is not None:
        s, P = cfg.ssim_patch_size, batch.patch_iw.shape[0]
        pp = pred[batch.n_random:].reshape(P, s, s, 3).permute(0, 3, 1, 2)
        tp = batch.target[batch.n_random:].reshape(P, s, s, 3).permute(0, 3, 1, 2)
        if lw.ssim > 0:
            terms["ssim"] = ssim_loss(pp, tp, batch.patch_iw)
        if (lw.depth_normal or 0.0) > 0:
            terms["depth_normal"] = _depth_normal_term(out, batch, s)
        if (lw.albedo_smooth or 0.0) > 0 and out.albedo is not None:
            n0 = batch.n_random
            photo = batch.target[n0:]
            photo = srgb_to_linear(photo) if data.scene.srgb else photo
            terms["albedo_smooth"] = albedo_smoothness_loss(
                out.albedo[n0:].reshape(P, s, s, 3), photo.reshape(P, s, s, 3),
                (out.opacity[n0:] * batch.iw[n0:]).reshape(P, s, s))
    if cfg.shading == "pbr" and lw.mat > 0:
        terms["mat"] = material_loss(out.albedo, out.roughness, out.metallic,
                                     batch.labels if cfg.mat_labels else None, batch.metal,
                                     batch.albedo_gt, batch.iw)
    if stage_b:
        terms["psnr_loss"] = psnr_loss(pred, batch.target, batch.iw)
        if lw.eikonal > 0 and state.step >= lw.eikonal_start and out.weights.numel():
            m = min(2048, out.weights.numel())
            sel = torch.multinomial(out.weights.detach().float() + 1e-8, m, replacement=False, generator=state.generator
                                    if out.weights.device.type == "cpu" else None)
            ext = float((data.scene.aabb[1] - data.scene.aabb[0]).mean())
            grad = _density_gradient(state.field, out.sample_points[sel].detach(), ext * lw.eikonal_step)
            if out.deferred:
                n_pred = nn.functional.normalize(state.field.normal_head(out.sample_features[sel]), dim=-1, eps=1e-6)
            else:
                n_pred = state.field(out.sample_points[sel].detach(), shading="none").normal
            terms["eikonal"] = normal_consistency_loss(n_pred, grad, out.weights[sel])
    if cfg.shading == "pbr" and (lw.orientation or 0.0) > 0 and out.weights.numel():
        if out.sample_normals is not None:
            terms["orientation"] = orientation_loss(out.sample_normals, batch.rays.directions[out.sample_ray_indices],
                                                    out.weights)
        else:
            terms["orientation"] = orientation_loss(out.normal, batch.rays.directions, out.opacity)
    if (lw.sparse_depth or 0.0) > 0 and data.sparse_depth is not None:
        terms["sparse_depth"], _ = _sparse_depth_term(state, data, data.sparse_depth)
    if lw.uses_room_layout and data.layout_depth is not None:
        depth_term, normal_term = _sparse_depth_term(state, data, data.layout_depth,
                                                     normals=(lw.layout_normal or 0.0) > 0)
        if (lw.layout_depth or 0.0) > 0:
            terms["layout_depth"] = depth_term
        if normal_term is not None:
            terms["layout_normal"] = normal_term
    if lw.planar > 0 and data.planar is not None:
        terms["planar"] = _planar_term(state, data)
    if cfg.semantics and batch.labels is not None and lw.semantic > 0:
        terms["semantic"] = semantic_loss(out.semantic_logits, batch.labels, batch.iw)
    if out.light_residual is not None and lw.light_reg > 0 and out.weights.numel():
        lw_w = out.opacity if out.deferred else out.weights
        terms["light_reg"] = light_residual_loss(out.light_residual, state.l_env, lw_w)
    if (lw.opacity or 0.0) > 0:
        terms["opacity"] = ((1.0 - out.opacity) * batch.iw).sum() / batch.iw.sum().clamp_min(1e-12)
    if lw.compactness > 0 and out.sample_s is not None:
        terms["compactness"] = compactness_loss(out.weights, out.sample_s[0], out.sample_s[1],
                                                out.sample_ray_indices, len(batch.rays))
    if state.colour is not None and lw.colour_reg > 0:
        terms["colour_reg"] = state.colour.regulariser()
    weight = {"rgb": lw.rgb, "ssim": lw.ssim, "mat": lw.mat, "psnr_loss": lw.psnr, "eikonal": lw.eikonal,
              "orientation": lw.orientation, "semantic": lw.semantic, "light_reg": lw.light_reg, "colour_reg": lw.colour_reg,
              "compactness": lw.compactness, "opacity": lw.opacity, "sparse_depth": lw.sparse_depth,
              "depth_normal": lw.depth_normal, "planar": lw.planar, "layout_depth": lw.layout_depth,
              "layout_normal": lw.layout_normal, "albedo_smooth": lw.albedo_smooth}
    loss = sum(weight[k] * v for k, v in terms.items())
    if not torch.isfinite(loss):
        bad = [k for k, v in terms.items() if not torch.isfinite(v)]
        raise TrainingDiverged(f"loss is {loss.item()} at step {state.step} (non-finite terms: {bad or 'sum'}); "
                               "training stopped, the last good checkpoint is kept — lower the learning rate "
                               "(--lr-scale) or check the input images")
    state.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    if state.grad_sync is not None:
        state.grad_sync(state.optimizer)
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
        out = _render(state, batch.rays, batch.wray, state.l_env)
        pred = _to_target_space(state, data, out.rgb, batch.views)
        loss = rgb_l1(pred, batch.target, batch.iw)
        if not torch.isfinite(loss):
            raise TrainingDiverged(f"light step loss is {loss.item()} at step {state.step}; training stopped")
        state.light_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if state.grad_sync is not None:
            state.grad_sync(state.light_optimizer)
        state.light_optimizer.step()
    finally:
        for p, r in zip(state.field.parameters(), req):
            p.requires_grad_(r)
    return {"reproj": loss.item()}
