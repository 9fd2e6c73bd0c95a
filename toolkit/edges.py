"""Stage 6 — distortion weight maps (paper §II.B, eqs. 2-4 and 8).

Per image, three cues of "hard to reconstruct" pixels are fused and smoothed:

* ``G`` (eq. 2): Sobel gradient magnitude of the luminance ``Y = 0.299 R + 0.587 G + 0.114 B`` of the image as
  given (sRGB-encoded photos: gradients are perceptually spaced, so dark edges are not drowned by bright ones),
  divided by its per-image maximum so it lies in [0, 1] (kornia ``sobel``, replicated border).
* ``E`` (eq. 3): ``Canny(Dilate(1[S != wall], 3x3))`` — the boundary of the dilated non-wall region: occlusion
  boundaries where paintings, frames, cases, bases, floor and other objects meet the wall. Unlabelled pixels
  (255) count as non-wall by default (``unlabelled_is_wall=False``): in the SPEC, 255 marks background or
  void (a doorway, the sky), and its boundary with the wall is a depth discontinuity like any other. Set
  ``unlabelled_is_wall=True`` for sparse annotations, where 255 only means "nobody drew here". Eq. 3 cannot
  see "frame-painting" boundaries (both are non-wall) although the paper's text names them;
  ``edge_classes="all"`` takes the union of Canny edges of every dilated class mask instead. No labels: ``E = 0``.
* ``M``: the metal mask (given, e.g. ``Scene.load_extra(i, "metal")``, or derived from predicted metallic);
  absent: 0.

``W0 = minmax(alpha G + beta E + gamma M)`` per image (eq. 4; a constant map gives ``W0 = 0``), then the smoothing
of SPEC stage 6 / eq. 8, solved exactly::

    W = argmin_W ||W - W0||^2 + lambda_reg (||D_x W||^2 + ||D_y W||^2)
    <=>  (I + lambda_reg L) W = W0,      L = D_x^T D_x + D_y^T D_y

with forward differences between horizontally / vertically adjacent pixels only (Neumann boundary), so ``L`` is
the 4-neighbour graph Laplacian. The system is diagonalised by the DCT-II; we solve it with an FFT of the
mirror-extended image (the mirrored periodic Laplacian equals the Neumann one), which is exact to round-off,
``O(HW log HW)``, batched and differentiable. ``(I + lambda L)^-1`` is a non-negative matrix whose rows sum to 1
(a discrete maximum principle), so ``W`` stays within ``[min W0, max W0]`` ⊂ [0, 1]; the final clamp only
removes round-off.

``distortion_loss = lambda_reg (sum (D_x W)^2 + sum (D_y W)^2) / (H W)`` per image: eq. 8 as a mean over pixels
(so it does not grow with resolution). It is the ``L_distortion`` the trainer logs.

Defaults ``alpha, beta, gamma = 0.5, 0.3, 0.2`` (they sum to 1, so ``W0`` is a convex combination and the
min-max rescaling changes little where all cues co-occur): the gradient is the densest and most general cue
(highlights, texture, shadow edges) and carries half the weight; semantic edges are sparse 1-px lines, and
after smoothing a line keeps roughly half its height, so 0.3 lets "edge + strong gradient" cross the sampler's
``tau = 0.7`` while an edge alone does not; the metal mask covers whole regions whose highlights already
score high in ``G``, so it gets the smallest bonus, enough to lift a metal pixel with a highlight above ``tau``.
Measured on the bundled sample (10 train views): mean W 0.44 on metal, 0.38 on semantic edges, 0.025 on flat wall,
0.067 overall — the Fig. 7 ordering (reflective frames and case edges first, plain walls last). Only 0.1 % of pixels
exceed ``tau = 0.7`` (0.7 % with ``renormalise=True``): the sampler should lean on the ratios of W, not on ``tau``
alone. ``(alpha, beta) = (0.4, 0.4)`` would rank edges above metal, ``(0.6, 0.2)`` drops edges to 0.26.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from ._checks import ConfigError, DarsError, ShapeError, check_range, check_shape

__all__ = [
    "WeightMapConfig",
    "WeightMaps",
    "weight_map",
    "gradient_magnitude",
    "semantic_edges",
    "minmax_normalise",
    "quantile_normalise",
    "normalise_weight_map",
    "smooth_weight_map",
    "distortion_loss",
    "weight_overlay",
    "WALL",
]

WALL = 4
"""Class id of ``wall`` in :data:`toolkit.scene.SEMANTIC_CLASSES`."""
_UNLABELLED = 255
_LUMA = (0.299, 0.587, 0.114)


@dataclass(frozen=True)
class WeightMapConfig:
    """Options of :func:`weight_map`.

    Attributes:
        alpha: weight of the gradient map G (eq. 4).
        beta: weight of the semantic edge map E (eq. 4).
        gamma: weight of the metal mask M (eq. 4).
        lambda_reg: smoothness weight of eq. 8 (paper: 0.3); 0 disables the smoothing.
        canny_low: Canny hysteresis low threshold, in units of kornia's unnormalised Sobel magnitude of a 0/1 mask
            (a straight mask step scores 4, a one-pixel corner about 1.4).
        canny_high: Canny high threshold (same units).
        canny_kernel_size: Gaussian blur kernel before Canny (1 = no blur: the input is a clean binary mask).
        canny_sigma: Gaussian blur sigma (ignored with kernel size 1).
        dilate_size: side of the square structuring element of the dilation (paper: 3).
        unlabelled_is_wall: treat label 255 as wall (True) or as non-wall (False, default; see module docstring).
        edge_classes: ``"non_wall"`` (eq. 3: boundary of the non-wall mask) or ``"all"`` (boundaries of every
            class, so frame-painting edges count too).
        gradient_floor: G is divided by ``max(max G, gradient_floor)`` so a flat image's noise is not inflated
            to 1 (luminance units per pixel; 1e-3 is a quarter of an 8-bit step).
        renormalise: min-max W again after the smoothing (default False, as the SPEC: smoothing lowers thin peaks,
            e.g. a 1-px line of W0 = 1 keeps about 1 / sqrt(1 + 4 lambda_reg) = 0.67 < tau, so only broad
            high-W regions pass the sampler's tau = 0.7; True restores max W = 1 per image).
    """

    alpha: float = 0.5
    beta: float = 0.3
    gamma: float = 0.2
    lambda_reg: float = 0.3
    canny_low: float = 0.5
    canny_high: float = 1.0
    canny_kernel_size: int = 1
    canny_sigma: float = 1.0
    dilate_size: int = 3
    unlabelled_is_wall: bool = False
    edge_classes: Literal["non_wall", "all"] = "non_wall"
    gradient_floor: float = 1e-3
    renormalise: bool = False

    def __post_init__(self):
        for name in ("alpha", "beta", "gamma"):
            check_range(getattr(self, name), 0.0, 1e6, name)
        if self.alpha + self.beta + self.gamma <= 0:
            raise ConfigError("alpha + beta + gamma must be positive")
        check_range(self.lambda_reg, 0.0, 1e6, "lambda_reg")
        check_range(self.canny_low, 1e-9, 1e6, "canny_low")
        check_range(self.canny_high, self.canny_low, 1e6, "canny_high")
        if self.canny_kernel_size < 1 or self.canny_kernel_size % 2 == 0:
            raise ConfigError(f"canny_kernel_size={self.canny_kernel_size} must be a positive odd integer")
        if self.dilate_size < 1 or self.dilate_size % 2 == 0:
            raise ConfigError(f"dilate_size={self.dilate_size} must be a positive odd integer")
        if self.edge_classes not in ("non_wall", "all"):
            raise ConfigError(f"edge_classes={self.edge_classes!r} is not valid: choose 'non_wall' or 'all'")
        check_range(self.gradient_floor, 0.0, 1e6, "gradient_floor")


@dataclass(frozen=True)
class WeightMaps:
    """Result of :func:`weight_map`; all maps float [B, H, W] on the images' device and dtype.

    Attributes:
        weights: W, the smoothed weight map in [0, 1] (what the DARS sampler consumes).
        gradient: G, normalised Sobel gradient magnitude in [0, 1].
        edges: E, semantic edges in {0, 1} (zeros without labels).
        metal: M, metal mask in {0, 1} (zeros without a mask).
        raw: W0 = minmax(alpha G + beta E + gamma M), before smoothing.
        distortion_loss: float [B], ``lambda_reg * (sum (D_x W)^2 + sum (D_y W)^2) / (H W)`` (eq. 8, mean over
            pixels).
    """

    weights: torch.Tensor
    gradient: torch.Tensor
    edges: torch.Tensor
    metal: torch.Tensor
    raw: torch.Tensor
    distortion_loss: torch.Tensor

    def __len__(self) -> int:
        return int(self.weights.shape[0])


# ---------------------------------------------------------------------------- pieces
def gradient_magnitude(images: torch.Tensor, floor: float = 1e-3) -> torch.Tensor:
    """Eq. 2: Sobel gradient magnitude of the luminance, divided by its per-image maximum.

    Args:
        images: float [B, 3, H, W] (or [B, 1, H, W] grey) in [0, 1].
        floor: the divisor is ``max(max G, floor)``.

    Returns:
        float [B, H, W] in [0, 1]; the unnormalised Sobel derivative is kornia's ``normalized=True`` one (a ramp of
        slope s per pixel gives s), i.e. OpenCV's ``cv2.Sobel(ksize=3)`` divided by 8.
    """
    import kornia

    if images.ndim != 4 or images.shape[1] not in (1, 3):
        raise ShapeError(f"images: expected shape [B 3 H W] or [B 1 H W], got {list(images.shape)}")
    if images.shape[1] == 3:
        w = torch.tensor(_LUMA, dtype=images.dtype, device=images.device).view(1, 3, 1, 1)
        y = (images * w).sum(1, keepdim=True)
    else:
        y = images
    g = kornia.filters.sobel(y, normalized=True, eps=1e-12)[:, 0]
    peak = g.flatten(1).amax(1).clamp_min(floor).view(-1, 1, 1)
    return g / peak


def semantic_edges(labels: torch.Tensor, cfg: WeightMapConfig = WeightMapConfig(),
                   dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Eq. 3: ``Canny(Dilate(1[S != wall]))`` (or every class boundary with ``cfg.edge_classes="all"``).

    Args:
        labels: int [B, H, W] class ids 0-6, 255 unlabelled.
        cfg: thresholds, dilation size and the 255 / class policy.
        dtype: floating dtype of the result.

    Returns:
        float [B, H, W] in {0, 1}: not differentiable (a function of integer labels).
    """
    import kornia

    check_shape(labels, "B H W", name="labels")
    if labels.is_floating_point():
        raise ShapeError(f"labels: expected an integer tensor of class ids, got {labels.dtype}")
    lab = labels.long()
    B, H, W = lab.shape
    if B == 0:
        return torch.zeros(0, H, W, dtype=dtype, device=labels.device)
    if cfg.edge_classes == "non_wall":
        wall = lab == WALL
        if cfg.unlabelled_is_wall:
            wall = wall | (lab == _UNLABELLED)
        masks = (~wall).to(dtype)[:, None]  # [B, 1, H, W]
    else:
        ids = torch.arange(7, device=labels.device)
        masks = (lab[:, None] == ids.view(1, 7, 1, 1))
        if not cfg.unlabelled_is_wall:
            masks = torch.cat([masks, (lab == _UNLABELLED)[:, None]], 1)
        else:
            masks[:, WALL] |= lab == _UNLABELLED
        masks = masks.to(dtype).reshape(-1, 1, H, W)
    kernel = torch.ones(cfg.dilate_size, cfg.dilate_size, dtype=dtype, device=labels.device)
    dil = kornia.morphology.dilation(masks, kernel, border_type="geodesic") if cfg.dilate_size > 1 else masks
    k = cfg.canny_kernel_size
    _, edges = kornia.filters.canny(dil, low_threshold=cfg.canny_low, high_threshold=cfg.canny_high,
                                    kernel_size=(k, k), sigma=(cfg.canny_sigma, cfg.canny_sigma))
    edges = edges.reshape(B, -1, H, W).amax(1)
    return (edges > 0.5).to(dtype)


def minmax_normalise(x: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Per-image min-max normalisation of float [B, H, W] to [0, 1]; a constant image maps to 0."""
    flat = x.flatten(1)
    lo = flat.amin(1).view(-1, 1, 1)
    hi = flat.amax(1).view(-1, 1, 1)
    return (x - lo) / (hi - lo).clamp_min(eps)


def quantile_normalise(x: torch.Tensor) -> torch.Tensor:
    """Per-image rank normalisation of float [B, H, W]: each value becomes the fraction of the image's pixels below
    it (ties share their mean rank), so the result is uniform on [0, 1] in every image.

    The sampler reads W this way (SPEC stage 6): a threshold τ = 0.7 then selects the top 30 % of *this photo's*
    distortion rather than an absolute level that few pixels of a smooth W reach, and per-ray budgets spread over
    their whole range. A constant image maps to 0.5 everywhere.
    """
    B = x.shape[0]
    flat = x.reshape(B, -1)
    n = flat.shape[1]
    srt, _ = flat.sort(dim=1)
    lo = torch.searchsorted(srt, flat.contiguous(), right=False)
    hi = torch.searchsorted(srt, flat.contiguous(), right=True)
    return ((lo + hi).to(x.dtype) / (2.0 * n)).reshape_as(x)


def normalise_weight_map(weights: torch.Tensor, mode: Literal["quantile", "none"] = "quantile") -> torch.Tensor:
    """One W map as the DARS sampler reads it (:attr:`toolkit.sampling.SamplerConfig.normalise`): clamped to [0, 1],
    then rank-normalised per image (:func:`quantile_normalise`) for ``quantile``, as is for ``none``.

    Apply it to the full-precision map, before it is stored at 8 bits (the trainer's W buffer): ranking an already
    quantised map would merge pixels that share a 1/255 level into ties.

    Args:
        weights: float [H, W] W in [0, 1].
        mode: ``quantile`` or ``none``.

    Returns:
        float [H, W] in [0, 1].

    Raises:
        ShapeError: ``weights`` is not [H, W].
        ConfigError: an unknown ``mode``.
    """
    check_shape(weights, "H W", name="weights")
    if mode not in ("quantile", "none"):
        raise ConfigError(f"W normalisation {mode!r}: choose 'quantile' or 'none'")
    w = weights.float().clamp(0.0, 1.0)
    return quantile_normalise(w[None])[0] if mode == "quantile" else w


def _laplacian_eigenvalues(n: int, dtype, device) -> torch.Tensor:
    # eigenvalues of the 1-D Neumann path Laplacian on the 2n-periodic mirror extension: 2 - 2 cos(2 pi k / 2n)
    k = torch.arange(2 * n, dtype=dtype, device=device)
    return 2.0 - 2.0 * torch.cos(torch.pi * k / n)


def smooth_weight_map(raw: torch.Tensor, lambda_reg: float = 0.3) -> torch.Tensor:
    """Exact minimiser of ``||W - raw||^2 + lambda_reg (||D_x W||^2 + ||D_y W||^2)`` per image.

    Solves ``(I + lambda_reg L) W = raw`` (L: 4-neighbour Laplacian, Neumann boundary) with an FFT of the
    mirror-extended image. Differentiable; batched; runs on the input's device (``torch.fft``).

    Args:
        raw: float [B, H, W].
        lambda_reg: smoothness weight (>= 0).

    Returns:
        float [B, H, W].
    """
    check_shape(raw, "B H W", name="raw")
    if lambda_reg < 0:
        raise ConfigError(f"lambda_reg={lambda_reg} must be >= 0")
    if lambda_reg == 0 or raw.numel() == 0:
        return raw
    B, H, W = raw.shape
    ext = torch.cat([raw, raw.flip(-1)], -1)
    ext = torch.cat([ext, ext.flip(-2)], -2)  # [B, 2H, 2W], even about the image borders
    real = raw.dtype if raw.dtype in (torch.float32, torch.float64) else torch.float32
    ey = _laplacian_eigenvalues(H, real, raw.device)  # [2H]
    ex = _laplacian_eigenvalues(W, real, raw.device)[: W + 1]  # rfft keeps W + 1 columns of 2W
    denom = 1.0 + lambda_reg * (ey[:, None] + ex[None, :])
    spec = torch.fft.rfft2(ext.to(real))
    out = torch.fft.irfft2(spec / denom, s=(2 * H, 2 * W))
    return out[:, :H, :W].to(raw.dtype)


def distortion_loss(weights: torch.Tensor, lambda_reg: float = 0.3) -> torch.Tensor:
    """Eq. 8 per image: ``lambda_reg * (sum (D_x W)^2 + sum (D_y W)^2) / (H W)``.

    Args:
        weights: float [B, H, W].

    Returns:
        float [B] (differentiable).
    """
    check_shape(weights, "B H W", name="weights")
    dx = weights[:, :, 1:] - weights[:, :, :-1]
    dy = weights[:, 1:, :] - weights[:, :-1, :]
    hw = weights.shape[1] * weights.shape[2]
    return lambda_reg * (dx.square().flatten(1).sum(1) + dy.square().flatten(1).sum(1)) / max(hw, 1)


# ---------------------------------------------------------------------------- the stage
def weight_map(
    images: torch.Tensor,
    labels: torch.Tensor | None = None,
    metal: torch.Tensor | None = None,
    cfg: WeightMapConfig = WeightMapConfig(),
) -> WeightMaps:
    """Distortion-sensitive weight maps W (eqs. 2-4, smoothed by eq. 8) for a batch of images.

    Differentiable with respect to ``images`` (through G, the min-max and the smoothing); E and M are constants.

    Args:
        images: float [B, 3, H, W] in [0, 1] (sRGB-encoded photos as loaded, or linear: G uses what is given).
        labels: int [B, H, W] class ids (0-6, 255 unlabelled) or ``None`` (then E = 0).
        metal: bool/float [B, H, W] metal mask (non-zero = metal) or ``None`` (then M = 0).
        cfg: weights and options (:class:`WeightMapConfig`).

    Returns:
        :class:`WeightMaps` with ``weights``, ``gradient``, ``edges``, ``metal``, ``raw`` [B, H, W] and
        ``distortion_loss`` [B].

    Raises:
        ShapeError: shapes disagree or labels are not integers.
        DarsError: images contain NaN/inf or labels hold ids other than 0-6 and 255.

    Example:
        >>> wm = weight_map(torch.rand(2, 3, 32, 32))
        >>> wm.weights.shape, bool((wm.weights >= 0).all() and (wm.weights <= 1).all())
        (torch.Size([2, 32, 32]), True)
    """
    dims = check_shape(images, "B 3 H W", name="images")
    if not images.is_floating_point():
        raise ShapeError(f"images: expected a floating tensor in [0, 1], got {images.dtype}")
    if not bool(torch.isfinite(images).all()):
        raise DarsError("images contain NaN or inf values")
    B, H, W = dims["B"], dims["H"], dims["W"]
    dtype, device = images.dtype, images.device

    G = gradient_magnitude(images, floor=cfg.gradient_floor)
    if labels is not None:
        check_shape(labels, f"{B} {H} {W}", name="labels")
        labels = labels.to(device)
        if labels.numel():
            ok = ((labels >= 0) & (labels <= 6)) | (labels == _UNLABELLED)
            if not bool(ok.all()):
                bad = torch.unique(labels[~ok])[:8].tolist()
                raise DarsError(f"labels contain unknown class ids {bad}: valid ids are 0-6 and 255 (unlabelled)")
        E = semantic_edges(labels, cfg, dtype=dtype)
    else:
        E = torch.zeros(B, H, W, dtype=dtype, device=device)
    if metal is not None:
        check_shape(metal, f"{B} {H} {W}", name="metal")
        M = (metal.to(device) != 0).to(dtype)
    else:
        M = torch.zeros(B, H, W, dtype=dtype, device=device)

    raw = minmax_normalise(cfg.alpha * G + cfg.beta * E + cfg.gamma * M)
    Wm = smooth_weight_map(raw, cfg.lambda_reg).clamp(0.0, 1.0)
    if cfg.renormalise:
        Wm = minmax_normalise(Wm)
    loss = distortion_loss(Wm, cfg.lambda_reg)
    return WeightMaps(weights=Wm, gradient=G, edges=E, metal=M, raw=raw, distortion_loss=loss)


# ---------------------------------------------------------------------------- preview
def weight_overlay(image: torch.Tensor | np.ndarray, weights: torch.Tensor | np.ndarray,
                   darken: float = 0.45, opacity: float = 0.75, cmap: str = "turbo") -> np.ndarray:
    """Heat-map overlay in the look of the paper's Fig. 7: a colour-mapped W over a darkened grey image.

    Args:
        image: float [3, H, W] (or H-W-3) in [0, 1].
        weights: float [H, W] in [0, 1].
        darken: brightness factor of the grey background.
        opacity: blend of the colour map at W = 1 (it falls to 30 % of this at W = 0, so flat areas stay
            readable).
        cmap: matplotlib colour map (``turbo`` or ``jet``).

    Returns:
        float H-W-3 in [0, 1].
    """
    from .visualise import colourise_scalar

    img = np.asarray(image.detach().cpu() if isinstance(image, torch.Tensor) else image, dtype=np.float32)
    if img.ndim == 3 and img.shape[0] == 3 and img.shape[-1] != 3:
        img = img.transpose(1, 2, 0)
    w = np.asarray(weights.detach().cpu() if isinstance(weights, torch.Tensor) else weights, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[:2] != w.shape:
        raise ShapeError(f"weight_overlay: image {list(img.shape)} and weights {list(w.shape)} do not match "
                         "(expected [3, H, W] or H-W-3 and [H, W])")
    grey = (img @ np.asarray(_LUMA, np.float32))[..., None] * darken
    heat = colourise_scalar(np.clip(w, 0, 1), 0.0, 1.0, cmap)
    a = (opacity * (0.3 + 0.7 * np.clip(w, 0, 1)))[..., None]
    return np.clip((1 - a) * grey + a * heat, 0.0, 1.0).astype(np.float32)
