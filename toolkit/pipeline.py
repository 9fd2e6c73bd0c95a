"""The rendering pipeline: rays -> samples (sampling) -> field -> shading -> volume rendering.

:func:`render_rays` is the one place that composes the stages; training, ``dars render``, evaluation, the
ablations and the ONNX parity check all go through it. What to render with is split in two:

* :class:`RenderConfig` (frozen) — how: sampler, shading, deferred or per-sample heads, chunk size, near/far;
* :class:`RenderInputs` — the run's state a render reads: occupancy grid, global light, background, scene box and
  the DARS context.

:func:`render_image` renders every output of one camera into a :class:`RenderedImage`;
:meth:`toolkit.train.run.Run.render` does so with a trained run's own settings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from dataclasses import field as dc_field
from typing import Callable, Literal

import torch
from torch import nn

from ._checks import ConfigError, check_choice
from .field import DarsField, FieldOutputs
from .pixels import PackedViews
from .render import accumulate_along_rays, render_weights
from .sampling import (OccupancyGrid, SamplerConfig, average_other_view_weights, coarse_samples, merge_samples,
                       proposal_weights, ray_budgets, sample_fine, stratified_edges)
from .scene import Cameras, RayBundle, generate_rays
from .sh import lookup_latlong
from .shading import ShadingConfig, shade_pbr

__all__ = ["Background", "DarsContext", "RenderConfig", "RenderInputs", "RenderOutputs", "RenderedImage", "render_rays",
           "render_image", "render_dars_context", "RENDER_KEYS"]

RENDER_KEYS = ("rgb", "depth", "opacity", "normal", "albedo", "roughness", "metallic", "semantic_logits",
               "diffuse", "specular")


class Background(nn.Module):
    """What a ray sees after leaving the scene box.

    Modes: ``constant`` (a fixed colour, e.g. the white of Blender RGBA renders), ``learned`` (one learnable
    colour) and ``env`` (a learnable low-resolution lat-long radiance map in the SPEC convention, sampled
    bilinearly by ray direction with gathers — exportable). Values are linear radiance.
    """

    def __init__(self, mode: Literal["constant", "learned", "env"] = "env", colour=(1.0, 1.0, 1.0),
                 resolution: tuple[int, int] = (16, 32)):
        super().__init__()
        self.mode = mode
        c = torch.as_tensor(colour, dtype=torch.float32).reshape(3)
        if mode == "constant":
            self.register_buffer("colour", c)
        elif mode == "learned":
            self.raw = nn.Parameter(torch.logit(c.clamp(0.02, 0.98)))
        elif mode == "env":
            h, w = resolution
            inv = torch.log(torch.expm1(c.clamp_min(1e-4)))  # softplus^-1: the map starts at ``colour``
            self.raw = nn.Parameter(inv.reshape(1, 1, 3).repeat(h, w, 1))
        else:
            raise ValueError(f"background mode {mode!r}: choose constant, learned or env")

    def dark_raw(self) -> torch.Tensor:
        """Raw parameter value of a (nearly) black background of this mode (``learned``/``env``)."""
        if self.mode == "learned":
            return torch.full_like(self.raw, math.log(0.02 / 0.98))
        if self.mode == "env":
            return torch.full_like(self.raw, math.log(math.expm1(1e-4)))
        raise ValueError("a constant background has no parameters")

    def env_map(self) -> torch.Tensor:
        """float [h, w, 3] linear radiance lat-long map (``env`` mode)."""
        return nn.functional.softplus(self.raw)

    def forward(self, directions: torch.Tensor) -> torch.Tensor:
        """float [R, 3] background radiance for unit directions [R, 3]."""
        if self.mode == "constant":
            return self.colour.to(directions).expand(directions.shape[0], 3)
        if self.mode == "learned":
            return torch.sigmoid(self.raw).to(directions).expand(directions.shape[0], 3)
        return lookup_latlong(self.env_map(), directions)

    def radiance_map(self) -> torch.Tensor:
        """float [h, w, 3] the background as a lat-long linear radiance map in any mode (1×1 for ``constant`` and
        ``learned``), sampled as :meth:`forward` does (:func:`toolkit.sh.lookup_latlong`)."""
        if self.mode == "env":
            return self.env_map()
        return (self.colour if self.mode == "constant" else torch.sigmoid(self.raw)).reshape(1, 1, 3)


@dataclass
class DarsContext:
    """What DARS needs at render time (part 3): the training cameras, their weight maps and neighbours."""

    cameras: Cameras
    weight_maps: PackedViews | torch.Tensor  # W of the training views: packed (views of any sizes) or [V, H, W]
    neighbours: torch.Tensor  # [V, k]
    view_of_ray: torch.Tensor | None = None  # [R] training view index of each ray (None: nearest view)


@dataclass(frozen=True)
class RenderConfig:
    """How to render: what a run fixes (:meth:`toolkit.train.run.Run.render_config` builds the run's own)."""

    sampler: SamplerConfig = dc_field(default_factory=SamplerConfig)
    """Sample counts and DARS switches (a run renders test views with its ``render_sampler``)."""
    shading: Literal["pbr", "radiance"] = "pbr"
    """``pbr``: decomposed (material + SH light); ``radiance``: the plain NeRF colour head."""
    deferred: bool = False
    """True: only density and the shared feature h per sample, the heads and the PBR shading once per ray on
    h̄ = Σ w h / Σ w (cheaper); False (default, as :attr:`toolkit.train.TrainConfig.deferred`): heads and shading
    at every sample, shaded colours composited. A run's renders use the run's setting."""
    shading_cfg: ShadingConfig = dc_field(default_factory=ShadingConfig)
    """Options of :func:`toolkit.shading.shade_pbr`."""
    chunk: int = 8192
    """Rays per batch in :func:`render_image` (memory bound; results do not depend on it)."""
    near: float | None = None
    """Scene near bound along the rays, metres (``None``: from the box only); :func:`render_image`."""
    far: float | None = None
    """Scene far bound, metres (``None``: from the box only); :func:`render_image`."""

    def __post_init__(self):
        check_choice(self.shading, ("pbr", "radiance"), "shading")
        if self.chunk < 1:
            raise ConfigError(f"chunk={self.chunk} must be >= 1")


@dataclass
class RenderInputs:
    """The state a render reads (a trained run's, or the trainer's).

    Attributes:
        occupancy: empty-space grid (None: no skipping).
        l_env: float [9, 3] global SH light (``pbr``), or None.
        background: what rays see after leaving the box.
        aabb: float [2, 3] scene box, metres (ray bounds of :func:`render_image`; None: ``near``/``far`` only).
        dars: DARS context (W maps of the training views) for the along-ray part when ``sampler.dars``, or None.
    """

    occupancy: OccupancyGrid | None
    l_env: torch.Tensor | None
    background: Background
    aabb: torch.Tensor | None = None
    dars: DarsContext | None = None


@dataclass
class RenderOutputs:
    """Per-ray results (R rays) and a few per-sample values for losses.

    ``rgb``, ``diffuse``, ``specular`` are linear radiance (background composited into ``rgb``; diffuse and
    specular are premultiplied by opacity); ``depth`` is metres along the camera axis; ``normal`` is unit;
    ``semantic_logits`` per ray (Σ w l / Σ w); material maps are per ray (deferred) or opacity-normalised
    accumulations.
    """

    rgb: torch.Tensor
    opacity: torch.Tensor
    depth: torch.Tensor
    normal: torch.Tensor
    semantic_logits: torch.Tensor
    albedo: torch.Tensor | None
    roughness: torch.Tensor | None
    metallic: torch.Tensor | None
    diffuse: torch.Tensor | None
    specular: torch.Tensor | None
    light_residual: torch.Tensor | None
    """float [R, 9, 3] (deferred) or [S, 9, 3] (per-sample) local light residual."""
    samples_per_ray: torch.Tensor
    weights: torch.Tensor
    """float [S] compositing weights of the packed samples."""
    sample_points: torch.Tensor
    sample_ray_indices: torch.Tensor
    sample_density: torch.Tensor
    sample_features: torch.Tensor
    """float [S, D] shared field features of the packed samples."""
    fine_counts: torch.Tensor
    deferred: bool
    sample_normals: torch.Tensor | None = None
    """float [S, 3] per-sample normal-head outputs (``deferred=False``; None when deferred)."""
    sample_s: tuple[torch.Tensor, torch.Tensor] | None = None
    """(start, end) float [S] of each sample's interval in normalised ray coordinates s ∈ [0, 1] (uniform in the
    strata: contracted arc length, or metres when bounded), for :func:`toolkit.losses.compactness_loss`."""


def render_dars_context(train_cameras: Cameras, weight_maps: PackedViews | torch.Tensor, c2w: torch.Tensor, k: int) -> DarsContext:
    """DARS context for rendering a camera with pose ``c2w`` [4, 4]: its ``k`` nearest training views."""
    o = train_cameras.origins
    f = -train_cameras.c2w[:, :3, 2]
    scale = (o - o.mean(0)).norm(dim=-1).mean().clamp_min(1e-6)
    d = (o - c2w[:3, 3].to(o)).norm(dim=-1) / scale + (1.0 - f @ (-c2w[:3, 2].to(o)))
    nb = torch.topk(d, min(k, len(train_cameras)), largest=False).indices
    return DarsContext(train_cameras, weight_maps, nb[None])


class _Permute(torch.autograd.Function):
    """``x[order]`` for a permutation ``order`` whose gradient is a gather by the inverse permutation. Autograd's
    own backward of ``x[order]`` scatters with accumulation (``index_put_``), which runs on one thread on the CPU:
    for the [S, 9, 3] light of a 4096-ray batch that was 6x slower than this (the values are the same: every row
    of a permutation gets exactly one gradient)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, order: torch.Tensor, inverse: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(inverse)
        return x.index_select(0, order)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        (inverse,) = ctx.saved_tensors
        return grad.index_select(0, inverse), None, None


def _permute(a: torch.Tensor, b: torch.Tensor, order: torch.Tensor, inverse: torch.Tensor) -> torch.Tensor:
    """``cat([a, b])[order]`` for the permutation ``order`` of :func:`toolkit.sampling.merge_samples`
    (``inverse[order] = arange``)."""
    return _Permute.apply(torch.cat([a, b]), order, inverse)


def _cat_outputs(a: FieldOutputs, b: FieldOutputs, order: torch.Tensor, inverse: torch.Tensor) -> FieldOutputs:
    out = FieldOutputs(density=_permute(a.density, b.density, order, inverse))
    for k in ("normal", "albedo", "roughness", "metallic", "semantic_logits", "light", "light_residual", "radiance"):
        va, vb = getattr(a, k), getattr(b, k)
        if va is not None and vb is not None:
            setattr(out, k, _permute(va, vb, order, inverse))
    return out


def _query(field: DarsField, points, dirs, l_env, mode, deferred: bool, hook=None):
    if deferred:
        sig, h = field.geometry_features(points)
        return sig, h, None
    out = field(points, dirs, l_env, mode)
    if hook is not None:
        out = hook(out)
    return out.density, None, out


def render_rays(
    field: DarsField,
    rays: RayBundle,
    cfg: RenderConfig,
    inputs: RenderInputs,
    ray_weights: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
    outputs_hook: Callable[[FieldOutputs], FieldOutputs] | None = None,
    fine_budgets: torch.Tensor | None = None,
) -> RenderOutputs:
    """Render a batch of rays (differentiable w.r.t. the field, ``l_env`` and the background).

    Two passes: the field's density at the occupied stratified samples gives the hierarchical proposal; fine
    samples (DARS budgets and along-ray density when enabled) are drawn from it; the union is rendered.

    ``cfg.deferred``: only density and the shared feature h are evaluated per sample; the heads run once per ray on
    h̄ = Σ w h / Σ w and the PBR shading uses the ray's material, normal and local light (for opaque surfaces this
    equals querying the heads at the surface point). Otherwise the heads and the shading run at every sample and
    the shaded colours are composited.

    Args:
        field: the field.
        rays: R rays (near/far already set; ``cfg.chunk``, ``cfg.near`` and ``cfg.far`` are not used here).
        cfg: sampler, shading, deferred.
        inputs: occupancy grid, l_env [9, 3], background; ``inputs.dars`` for the along-ray part when
            ``cfg.sampler.dars`` (``inputs.aabb`` is not used here).
        ray_weights: float [R] W at each ray's pixel (training), for the per-ray budgets; None: uniform budget.
        generator: RNG for stratified jitter.
        outputs_hook: optional callable ``FieldOutputs -> FieldOutputs`` applied to every field query before
            shading (relighting and material edits, :mod:`toolkit.relight`); when deferred it sees the per-ray
            head outputs.
        fine_budgets: int64 [R] fine samples per ray, computed by the caller (``ray_weights`` is then not used):
            lets one image be rendered in chunks with the DARS budgets shared over the whole image
            (:func:`toolkit.evaluate.training_sample_counts`). Rays without an occupied coarse sample get none.
    """
    sampler, shading, shading_cfg, deferred = cfg.sampler, cfg.shading, cfg.shading_cfg, cfg.deferred
    occupancy, l_env, background, dars = inputs.occupancy, inputs.l_env, inputs.background, inputs.dars
    R = len(rays)
    n = sampler.n_coarse
    dev = rays.origins.device
    mode = "radiance" if shading == "radiance" else "pbr"
    space = field.space
    edges = stratified_edges(rays, n, sampler.perturb, generator, space)
    coarse, stratum = coarse_samples(rays, edges, occupancy)
    pts_c = coarse.points(rays.origins, rays.directions)
    sig_c, h_c, out_c = _query(field, pts_c, rays.directions[coarse.ray_indices], l_env, mode, deferred, outputs_hook)
    has = torch.zeros(R, dtype=torch.bool, device=dev)
    has[coarse.ray_indices] = True
    # ---- fine samples: hierarchical proposal, mixed with W̄ (DARS part 3)
    counts = torch.zeros(R, dtype=torch.long, device=dev)
    if sampler.n_fine > 0:
        pdf = proposal_weights(coarse, stratum, sig_c, n)
        if sampler.dars and dars is not None and sampler.mix > 0 and coarse.ray_indices.numel():
            views = dars.view_of_ray if dars.view_of_ray is not None else rays.camera_indices
            with torch.no_grad():
                wb = average_other_view_weights(pts_c.detach(), views[coarse.ray_indices].to(dev),
                                                dars.neighbours, dars.cameras, dars.weight_maps)
            wbar = torch.zeros(R, n, dtype=pdf.dtype, device=dev)
            wbar[coarse.ray_indices, stratum] = wb.to(pdf.dtype) + 1e-4  # p0: the occupied strata
            ps = pdf.sum(-1, keepdim=True)
            pw = wbar.sum(-1, keepdim=True)
            pdf = (1 - sampler.mix) * pdf / ps.clamp_min(1e-12) + sampler.mix * wbar / pw.clamp_min(1e-12)
        idx = torch.nonzero(has).squeeze(-1)
        if idx.numel():
            if fine_budgets is not None:
                counts[idx] = fine_budgets.to(dev)[idx]
            elif sampler.dars and ray_weights is not None:
                counts[idx] = ray_budgets(ray_weights[idx], sampler.n_fine, sampler.tau, sampler.budget_min,
                                          sampler.budget_max)
            else:
                counts[idx] = sampler.n_fine
        t_f, ray_f, k_f = sample_fine(edges, pdf, counts, sampler.perturb, generator, return_strata=True)
    else:
        t_f = edges.new_zeros(0)
        ray_f = k_f = torch.zeros(0, dtype=torch.long, device=dev)
    pts_f = rays.origins[ray_f] + t_f[:, None] * rays.directions[ray_f]
    sig_f, h_f, out_f = _query(field, pts_f, rays.directions[ray_f], l_env, mode, deferred, outputs_hook)
    max_delta = (torch.maximum(rays.far, rays.near) - rays.near) / n
    sample_delta = None
    if space.contraction:  # strata of unequal length: each sample spans at most its own stratum
        sample_delta = torch.cat([coarse.deltas, edges[ray_f, k_f + 1] - edges[ray_f, k_f]])
    samples, order = merge_samples(coarse.t_mids, coarse.ray_indices, t_f, ray_f, R, max_delta, rays.near, rays.far,
                                   sample_delta)
    inverse = torch.empty_like(order)
    inverse[order] = torch.arange(order.numel(), device=order.device)
    density = _permute(sig_c, sig_f, order, inverse)
    rows = edges[samples.ray_indices].contiguous()  # [S, n+1]: s = k / n at edge k

    def _s_of(t: torch.Tensor) -> torch.Tensor:
        k = torch.searchsorted(rows, t[:, None].contiguous(), right=True).squeeze(-1).clamp(1, n) - 1
        e0, e1 = rows.gather(1, k[:, None])[:, 0], rows.gather(1, (k + 1)[:, None])[:, 0]
        return (k.to(t.dtype) + ((t - e0) / (e1 - e0).clamp_min(1e-12)).clamp(0.0, 1.0)) / n

    sample_s = (_s_of(samples.t_starts), _s_of(samples.t_ends)) if samples.t_starts.numel() else None
    points = _permute(pts_c, pts_f, order, inverse)
    ri = samples.ray_indices
    weights, _, _ = render_weights(density, samples.deltas, ri, R)
    opacity = accumulate_along_rays(weights, None, ri, R)
    safe = opacity.clamp_min(1e-6)
    depth = (accumulate_along_rays(weights, samples.t_mids[:, None], ri, R)[:, 0] / safe[:, 0]) * rays.z_scale
    bg = background(rays.directions)
    diffuse = specular = albedo = rough = metal = light_res = sample_normals = None
    if deferred:
        feats = _permute(h_c, h_f, order, inverse)
        hbar = accumulate_along_rays(weights, feats, ri, R) / safe
        heads = field.heads(hbar, rays.directions, l_env, mode)
        if outputs_hook is not None:
            heads = outputs_hook(heads)
        normal, logits = heads.normal, heads.semantic_logits
        if mode == "pbr":
            sh = heads.light if heads.light is not None else l_env.reshape(1, 9, 3).expand(R, 9, 3)
            sh_out = shade_pbr(heads.albedo, heads.roughness, heads.metallic, normal, -rays.directions, sh,
                               shading_cfg)
            colour = sh_out.colour
            diffuse, specular = opacity * sh_out.diffuse, opacity * sh_out.specular
            albedo, rough, metal, light_res = heads.albedo, heads.roughness, heads.metallic, heads.light_residual
        else:
            colour = heads.radiance
        rgb = opacity * colour + (1.0 - opacity) * bg
    else:
        feats = points.new_zeros(points.shape[0], 0)
        out = _cat_outputs(out_c, out_f, order, inverse)
        dirs = rays.directions[ri]
        if mode == "pbr":
            sh = out.light if out.light is not None else l_env.reshape(1, 9, 3).expand(ri.shape[0], 9, 3)
            sh_out = shade_pbr(out.albedo, out.roughness, out.metallic, out.normal, -dirs, sh, shading_cfg)
            colour = sh_out.colour
            diffuse = accumulate_along_rays(weights, sh_out.diffuse, ri, R)
            specular = accumulate_along_rays(weights, sh_out.specular, ri, R)
            albedo = accumulate_along_rays(weights, out.albedo, ri, R) / safe
            rough = (accumulate_along_rays(weights, out.roughness[:, None], ri, R) / safe)[:, 0]
            metal = (accumulate_along_rays(weights, out.metallic[:, None], ri, R) / safe)[:, 0]
            light_res = out.light_residual
        else:
            colour = out.radiance
        rgb = accumulate_along_rays(weights, colour, ri, R) + (1.0 - opacity) * bg
        sample_normals = out.normal
        normal = nn.functional.normalize(accumulate_along_rays(weights, out.normal, ri, R), dim=-1, eps=1e-6)
        # normalised by opacity: a ray that is still mostly transparent carries its surface's class, not ~0 logits
        logits = accumulate_along_rays(weights, out.semantic_logits, ri, R) / safe
    return RenderOutputs(rgb=rgb, opacity=opacity[:, 0], depth=depth, normal=normal, semantic_logits=logits,
                         albedo=albedo, roughness=rough, metallic=metal, diffuse=diffuse, specular=specular,
                         light_residual=light_res, samples_per_ray=samples.counts(), weights=weights,
                         sample_points=points, sample_ray_indices=ri, sample_density=density, sample_features=feats,
                         fine_counts=counts, deferred=deferred, sample_normals=sample_normals, sample_s=sample_s)


@dataclass
class RenderedImage:
    """Every output of one camera as images (H x W pixels), from :func:`render_image`.

    ``rgb``, ``diffuse`` and ``specular`` are linear radiance (background composited into ``rgb``); ``depth`` is
    metres along the camera axis; ``normal`` is unit (world); material maps and ``semantic_logits`` as in
    :class:`RenderOutputs`; ``samples`` is the number of samples each ray took. The material, diffuse and specular
    maps are None for a ``radiance`` run.

    Attributes:
        rgb: float [H, W, 3].
        depth: float [H, W].
        opacity: float [H, W].
        normal: float [H, W, 3].
        semantic_logits: float [H, W, C].
        samples: float [H, W].
        albedo: float [H, W, 3] or None.
        roughness: float [H, W] or None.
        metallic: float [H, W] or None.
        diffuse: float [H, W, 3] or None.
        specular: float [H, W, 3] or None.
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    opacity: torch.Tensor
    normal: torch.Tensor
    semantic_logits: torch.Tensor
    samples: torch.Tensor
    albedo: torch.Tensor | None = None
    roughness: torch.Tensor | None = None
    metallic: torch.Tensor | None = None
    diffuse: torch.Tensor | None = None
    specular: torch.Tensor | None = None

    def as_dict(self) -> dict[str, torch.Tensor]:
        """The outputs that exist, by name (:data:`RENDER_KEYS` order, then ``samples``)."""
        out = {k: getattr(self, k) for k in RENDER_KEYS if getattr(self, k) is not None}
        out["samples"] = self.samples
        return out


@torch.no_grad()
def render_image(
    field: DarsField,
    cameras: Cameras,
    index: int,
    cfg: RenderConfig,
    inputs: RenderInputs,
    outputs_hook: Callable[[FieldOutputs], FieldOutputs] | None = None,
) -> RenderedImage:
    """Render every output of camera ``index``.

    Args:
        field: the field.
        cameras: the cameras.
        index: which camera.
        cfg: sampler, shading, deferred, chunk and the scene's near/far.
        inputs: the run's state; ``inputs.aabb`` bounds the rays; ``inputs.dars`` is a context whose first
            ``neighbours`` row lists the training views nearest this camera (:func:`render_dars_context`).
        outputs_hook: see :func:`render_rays`.

    Returns:
        :class:`RenderedImage`.
    """
    h, w = int(cameras.height[index]), int(cameras.width[index])
    rays = generate_rays(cameras, [index], aabb=field.space if field.cfg.contraction else inputs.aabb, near=cfg.near,
                         far=cfg.far)
    dars = inputs.dars
    outs: dict[str, list[torch.Tensor]] = {}
    for i in range(0, len(rays), cfg.chunk):
        sub = rays[i:i + cfg.chunk]
        ctx = None
        if dars is not None:  # every ray of this image belongs to the one view whose neighbours are row 0
            ctx = DarsContext(dars.cameras, dars.weight_maps, dars.neighbours[:1],
                              torch.zeros(len(sub), dtype=torch.long, device=sub.origins.device))
        r = render_rays(field, sub, cfg, replace(inputs, dars=ctx), outputs_hook=outputs_hook)
        for k in RENDER_KEYS:
            v = getattr(r, k)
            if v is not None:
                outs.setdefault(k, []).append(v)
        outs.setdefault("samples", []).append(r.samples_per_ray.float())
    result = {}
    for k, vs in outs.items():
        v = torch.cat(vs)
        result[k] = v.reshape(h, w, -1) if v.dim() == 2 else v.reshape(h, w)
    return RenderedImage(**result)
