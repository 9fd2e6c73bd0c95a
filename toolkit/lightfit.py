"""An object's light from its shading: the SH light under which the photos' albedo is flattest.

An object on a transparent background gets no light network estimate (the network reads whole photos of rooms), so
``l_env`` starts as a grey ambient light. Left there through stage (a), the albedo takes every shade of the photos
(the side away from the window comes out dark), and the eq. 22 light stage, which moves ``l_env`` with the field
fixed, finds nothing to gain: the albedo already explains the photos under the grey light. On four generated
objects the final light was barely directional (README, "An object's light from its shading").

At the stage switch this module fits the directional bands (l = 1, 2) of ``l_env`` to the photos, with the level
(band 0) kept: render a few training views' depth, take the normals of the rendered depth map
(:func:`toolkit.losses.depth_map_normals`; on an object they follow the surface where the normal head may not yet), and
find the light whose irradiance ``E(n)`` makes ``log(photo / E(n))`` change least between neighbouring pixels of the
object (an L1 total variation: a Lambertian object's colour is albedo × irradiance, albedo is piecewise constant, and
the irradiance of a low-order SH light varies with the normal). Uses the photos and the field's depth only.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from .losses import depth_map_normals
from .sh import SH_BAND_OF_K, SH_IRRADIANCE_BANDS, sh_basis

FIT_VIEWS = 12
"""Training views the fit renders (evenly spaced through the split)."""
FIT_SIDE = 96
"""Their longest side in pixels (rendered and compared at this size)."""
FIT_ITERS = 400
MIN_PIXELS = 400
"""Fewer usable object pixels than this over all views: no fit (the light is kept)."""
MIN_GAIN = 0.005
"""The fitted light is kept only when it lowers the total variation by at least this fraction."""


@dataclass
class LightFit:
    """The result of :func:`fit_light_to_shading`.

    Attributes:
        sh: float [9, 3] the fitted light (band 0 as given), or the given light when ``used`` is False.
        used: whether the fit replaced the light.
        pixels: object pixels the fit saw.
        tv_before / tv_after: the objective under the given light and under the fitted one.
        reason: why the fit was not used ('' when it was).
    """

    sh: torch.Tensor
    used: bool
    pixels: int
    tv_before: float
    tv_after: float
    reason: str = ""

    def describe(self) -> str:
        if not self.used:
            return f"light kept ({self.reason})"
        return (f"directional bands fitted on {self.pixels} object pixels: albedo variation "
                f"{self.tv_before:.4f} -> {self.tv_after:.4f}")


def _irradiance_weights(normals: torch.Tensor) -> torch.Tensor:
    band_w = torch.tensor([SH_IRRADIANCE_BANDS[b] for b in SH_BAND_OF_K], dtype=normals.dtype)
    return sh_basis(normals) * band_w  # [..., 9]: E(n) = weights @ coeffs


def shading_tv(weights: torch.Tensor, log_photo: torch.Tensor, pairs: torch.Tensor, sh: torch.Tensor,
               floor: float) -> torch.Tensor:
    """Mean |Δ log(photo / E(n))| over the neighbour ``pairs`` [K, 2] of pixels with irradiance weights [M, 9]
    and log photo colour [M, 3] under the light ``sh`` [9, 3]; irradiance below ``floor`` counts as ``floor``."""
    log_a = log_photo - torch.log((weights @ sh).clamp_min(floor))
    return (log_a[pairs[:, 0]] - log_a[pairs[:, 1]]).abs().mean()


def fit_sh_to_shading(normals: torch.Tensor, photo_linear: torch.Tensor, mask: torch.Tensor, sh: torch.Tensor,
                      iters: int = FIT_ITERS) -> LightFit:
    """Fit bands 1-2 of ``sh`` to images so that the albedo ``photo / E(n)`` is flattest.

    Args:
        normals: float [V, H, W, 3] unit world normals.
        photo_linear: float [V, H, W, 3] the photos' linear colour.
        mask: bool [V, H, W] pixels of the object to use.
        sh: float [9, 3] the current light; its band 0 is kept.
        iters: Adam iterations.

    Returns:
        :class:`LightFit`.
    """
    sh = sh.detach().double().cpu()
    # a pair counts when both pixels are in the mask
    pairs = []
    idx = torch.arange(mask.numel()).reshape(mask.shape)
    for a, b in ((idx[:, :, 1:], idx[:, :, :-1]), (idx[:, 1:, :], idx[:, :-1, :])):
        flat_a, flat_b = a.reshape(-1), b.reshape(-1)
        ok = mask.reshape(-1)[flat_a] & mask.reshape(-1)[flat_b]
        pairs.append(torch.stack([flat_a[ok], flat_b[ok]], -1))
    pairs = torch.cat(pairs)
    sel = mask.reshape(-1).nonzero().squeeze(-1)
    n_pix = int(sel.numel())
    if n_pix < MIN_PIXELS or len(pairs) < MIN_PIXELS:
        return LightFit(sh.float(), False, n_pix, float("nan"), float("nan"),
                        f"{n_pix} object pixels, fewer than {MIN_PIXELS}")
    remap = torch.full((mask.numel(),), -1, dtype=torch.long)
    remap[sel] = torch.arange(n_pix)
    pairs = remap[pairs]
    weights = _irradiance_weights(normals.reshape(-1, 3)[sel].double())
    log_photo = torch.log(photo_linear.reshape(-1, 3)[sel].double().clamp_min(1e-4))
    level = float(sh[0].abs().mean()) * SH_IRRADIANCE_BANDS[0] * 0.282095  # the grey irradiance of band 0
    floor = 1e-2 * max(level, 1e-6)
    with torch.no_grad():
        tv0 = float(shading_tv(weights, log_photo, pairs, sh, floor))
    directional = torch.zeros(8, 3, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([directional], lr=0.02 * max(float(sh[0].abs().mean()), 1e-3))
    with torch.enable_grad():  # also when called under no_grad (the renders before it need none)
        for _ in range(iters):
            full = torch.cat([sh[:1], sh[1:] + directional])
            loss = shading_tv(weights, log_photo, pairs, full, floor)
            opt.zero_grad()
            loss.backward()
            opt.step()
    fitted = torch.cat([sh[:1], sh[1:] + directional.detach()])
    with torch.no_grad():
        tv1 = float(shading_tv(weights, log_photo, pairs, fitted, floor))
    if not (np.isfinite(tv1) and tv1 < tv0 * (1.0 - MIN_GAIN)):
        return LightFit(sh.float(), False, n_pix, tv0, tv1,
                        f"the fit lowered the albedo variation by less than {MIN_GAIN:.1%} ({tv0:.4f} -> {tv1:.4f})")
    return LightFit(fitted.float(), True, n_pix, tv0, tv1)


def _photo_at(scene, i: int, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Frame ``i`` at ``width`` x ``height``: linear colour [H, W, 3] and the pixels that are the object's and may be
    used (alpha and any ``ignore`` mask) [H, W]."""
    import cv2

    from .io import srgb_to_linear

    img = scene.load_image(i, with_alpha=True).permute(1, 2, 0).numpy()
    keep = img[..., 3] > 0.95
    valid = scene.valid_mask(i)
    if valid is not None:
        keep &= valid.numpy().astype(bool)
    h0, w0 = keep.shape
    if (w0, h0) != (width, height):
        img = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
        keep = cv2.resize(keep.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST).astype(bool)
    rgb = torch.from_numpy(np.ascontiguousarray(img[..., :3])).float()
    if scene.srgb:
        rgb = srgb_to_linear(rgb)
    return rgb, torch.from_numpy(keep)


def _pad(x: torch.Tensor, h: int, w: int, value) -> torch.Tensor:
    out = x.new_full((h, w, *x.shape[2:]), value)
    out[:x.shape[0], :x.shape[1]] = x
    return out


@torch.no_grad()
def fit_light_to_shading(field, occupancy, background, l_env: torch.Tensor, scene, sampler, shading: str,
                         deferred: bool, views: int = FIT_VIEWS, side: int = FIT_SIDE) -> LightFit:
    """:func:`fit_sh_to_shading` on ``views`` training views of ``scene`` rendered by the field at ``side`` px.

    Args:
        field, occupancy, background: the trainer's state.
        l_env: float [9, 3] the current light (band 0 kept; also the light the depth renders use).
        scene: the training split (photos, cameras, box).
        sampler: :class:`~toolkit.sampling.SamplerConfig` for the renders (its perturbation and DARS are turned off).
        shading, deferred: the run's.
    """
    from .pipeline import RenderConfig, RenderInputs, render_image

    n = len(scene)
    picks = sorted(set(np.linspace(0, n - 1, min(views, n)).round().astype(int).tolist()))
    dev = l_env.device
    cfg = RenderConfig(sampler=replace(sampler, perturb=False, dars=False), shading=shading, deferred=deferred,
                       near=scene.near, far=scene.far)
    inputs = RenderInputs(occupancy, l_env.detach(), background, scene.aabb.to(dev), None)
    normals, photos, masks = [], [], []
    was_training = field.training
    field.eval()
    try:
        for i in picks:
            h0, w0 = int(scene.cameras.height[i]), int(scene.cameras.width[i])
            s = min(1.0, side / max(h0, w0))
            w, h = max(8, round(w0 * s)), max(8, round(h0 * s))
            cams = scene.cameras[[i]].resized(w, h).to(dev)
            r = render_image(field, cams, 0, cfg, inputs)
            nd = torch.zeros(h, w, 3, device=dev)
            nd[1:-1, 1:-1], d = depth_map_normals(cams, 0, r.depth)
            facing = -(nd * d).sum(-1)  # a depth step (an occluding edge) gives a normal at right angles to the ray
            photo, keep = _photo_at(scene, i, w, h)
            m = keep & (r.opacity.cpu() > 0.95) & (facing.cpu() > 0.15)
            # the object's inside only: all four neighbours are the object's too
            inner = m.clone()
            inner[1:, :] &= m[:-1, :]
            inner[:-1, :] &= m[1:, :]
            inner[:, 1:] &= m[:, :-1]
            inner[:, :-1] &= m[:, 1:]
            normals.append(nd.cpu())
            photos.append(photo)
            masks.append(inner)
    finally:
        field.train(was_training)
    hmax, wmax = max(x.shape[0] for x in masks), max(x.shape[1] for x in masks)
    normals = [_pad(x, hmax, wmax, 0.0) for x in normals]  # views of different sizes: one padded stack
    photos = [_pad(x, hmax, wmax, 1.0) for x in photos]
    masks = [_pad(x, hmax, wmax, False) for x in masks]
    res = fit_sh_to_shading(torch.stack(normals), torch.stack(photos), torch.stack(masks), l_env.detach().cpu())
    res.sh = res.sh.to(dev)
    return res
