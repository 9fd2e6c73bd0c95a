"""Stage 12 — evaluation metrics (paper section III.C, eqs. 30-38), as plain functions on tensors.

Conventions shared by every function here:

* Images are ``float [B, C, H, W]`` (or unbatched ``[C, H, W]``) in [0, 1]; masks are ``bool [B, H, W]``
  (or ``[H, W]``), True = pixel counts. Results are allocated on the input's device and dtype.
* *Per-image* metrics (:func:`psnr`, :func:`ssim`, :func:`flip`, :func:`lpips`) return ``[B]`` for a batch and a
  0-dim tensor for an unbatched image. A data set's figure is the **mean over images of the per-image value**
  (the NeRF convention). For PSNR this is *not* the PSNR of the data set's mean MSE: since ``-log`` is convex,
  the mean of per-image PSNRs is >= the PSNR of the mean MSE (Jensen), equal only when all images' MSEs agree.
* *Pooled* metrics (:func:`albedo_mae`, :func:`roughness_rmse`, :func:`normal_mae_deg`) average over every
  masked pixel of the whole batch (the paper's ``N`` in eqs. 34-35 counts pixels over all exhibits) and
  return a 0-dim tensor.
* A metric that the data or weights cannot support raises :class:`MetricUnavailable` (a
  :class:`~toolkit._checks.DarsError`) with the reason, so a report can print ``null`` and the reason instead of a
  made-up number. Nothing here is ever approximated (e.g. LPIPS never runs without its pretrained weights).

Device limits: :func:`flip` runs the ``flip_evaluator`` C++ code and :func:`chamfer_distance` /
:func:`fscore` use ``scipy.spatial.cKDTree``: both always compute on the CPU (inputs on another device are
copied) and are not differentiable. Everything else runs on the input's device; :func:`psnr`, :func:`ssim`
and :func:`lpips` are differentiable.
"""

from __future__ import annotations

import functools
import math
import os
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ._checks import DarsError, ShapeError, check_shape
from .io import srgb_to_linear
from .scene import SEMANTIC_CLASSES, UNLABELLED, Cameras, project_points
from .segment import mean_iou  # noqa: F401 - re-exported: one mIoU for the whole toolkit (stage 3 owns it)

__all__ = [
    "MetricUnavailable",
    "psnr",
    "ssim",
    "flip",
    "lpips",
    "load_lpips_weights",
    "LPIPS_ENV_VAR",
    "albedo_mae",
    "albedo_mae_aligned",
    "metallic_mae",
    "roughness_rmse",
    "material_mask",
    "env_light_l2",
    "normal_mae_deg",
    "luminance",
    "view_consistency",
    "patch_masks",
    "uniform_view_indices",
    "chamfer_distance",
    "fscore",
    "sample_mesh_surface",
    "mesh_depth_map",
    "mesh_depth_error",
    "mean_iou",
]

LPIPS_ENV_VAR = "DARS_LPIPS_WEIGHTS"
"""Environment variable naming the LPIPS weight file(s) when ``weights_path`` is not given."""

DISPLAY_CLASS = SEMANTIC_CLASSES.index("display")  # 2
"""Semantic id of ``display`` (glass/acrylic case): excluded from material metrics."""

REC709_LUMA = (0.2126, 0.7152, 0.0722)
"""Rec. 709 / sRGB-primaries relative luminance weights for *linear* RGB."""


class MetricUnavailable(DarsError):
    """A metric cannot be computed from what was given (missing weights, empty mask, missing package)."""


# ====================================================================== input checks
def _check_images(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None, fn: str,
                  channels: int | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, bool]:
    """Validate a (pred, target, mask) triple; return batched ``[B, C, H, W]`` views, mask ``[B, H, W]``, batched."""
    for name, x in (("pred", pred), ("target", target)):
        if not isinstance(x, torch.Tensor):
            raise DarsError(f"{fn}: {name} must be a torch.Tensor, got {type(x).__name__}")
        if not x.is_floating_point():
            raise DarsError(f"{fn}: {name} must be a floating-point image in [0, 1], got dtype {x.dtype}")
    if pred.shape != target.shape:
        raise ShapeError(f"{fn}: pred and target must have the same shape, got {list(pred.shape)} and {list(target.shape)}")
    if pred.dim() not in (3, 4):
        raise ShapeError(f"{fn}: images must be [B, C, H, W] or [C, H, W], got {list(pred.shape)}")
    batched = pred.dim() == 4
    p4, t4 = (pred, target) if batched else (pred[None], target[None])
    if channels is not None and p4.shape[1] != channels:
        raise ShapeError(f"{fn}: expected {channels} channels ([B, {channels}, H, W]), got {list(pred.shape)}")
    m3 = None
    if mask is not None:
        b, _, h, w = p4.shape
        expected = [b, h, w] if batched else [h, w]
        if list(mask.shape) != expected:
            raise ShapeError(f"{fn}: mask must have shape {expected} to match images {list(pred.shape)}, got {list(mask.shape)}")
        if mask.dtype != torch.bool:
            raise DarsError(f"{fn}: mask must be a bool tensor (True = pixel counts), got {mask.dtype}; pass e.g. mask > 0.5")
        m3 = (mask if batched else mask[None]).to(pred.device)
    return p4, t4, m3, batched


def _check_mask(mask: torch.Tensor, shape: Sequence[int], fn: str) -> torch.Tensor:
    if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
        got = mask.dtype if isinstance(mask, torch.Tensor) else type(mask).__name__
        raise DarsError(f"{fn}: mask must be a bool tensor (True = pixel counts), got {got}; pass e.g. mask > 0.5")
    if list(mask.shape) != list(shape):
        raise ShapeError(f"{fn}: mask must have shape {list(shape)}, got {list(mask.shape)}")
    return mask


def _require_pixels(count: torch.Tensor | int, fn: str) -> None:
    if int(count) == 0:
        raise MetricUnavailable(f"{fn}: the mask selects no pixels, so there is nothing to measure")


# ====================================================================== image fidelity
def psnr(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None, max_val: float = 1.0) -> torch.Tensor:
    """Peak signal-to-noise ratio per image (eqs. 30-31), in dB.

    ``PSNR = 10 log10(max_val^2 / MSE)`` with the MSE averaged over the image's (masked) pixels **and channels**,
    as NeRF, scikit-image and every NeRF table do. (Eq. 31 read literally sums the squared RGB norm and divides
    by H·W only, i.e. 3x this MSE and 4.77 dB lower; we follow the field's convention, which is what the
    paper's numbers mean.) Report a data set as the mean over images of this per-image PSNR.

    Args:
        pred: float [B, C, H, W] or [C, H, W] rendered image, values in [0, max_val].
        target: float, same shape, ground truth.
        mask: optional bool [B, H, W] (or [H, W]); only True pixels count.
        max_val: peak value ``MAX_I`` (1.0 for images in [0, 1]).

    Returns:
        float [B] (0-dim if unbatched) PSNR in dB; ``inf`` where the images are identical on the mask and NaN
        where an image's mask selects no pixel. Differentiable.

    Raises:
        ShapeError: shapes of pred/target/mask disagree.
        DarsError: non-float images or a non-bool mask.

    Example:
        >>> x = torch.zeros(1, 3, 4, 4)
        >>> psnr(x + 0.1, x)  # MSE 0.01 -> 20 dB
        tensor([20.])
    """
    p, t, m, batched = _check_images(pred, target, mask, "psnr")
    sq = (p - t) ** 2
    if m is None:
        mse = sq.mean(dim=(1, 2, 3))
    else:
        w = m[:, None].to(sq.dtype)
        mse = (sq * w).sum(dim=(1, 2, 3)) / (w.sum(dim=(1, 2, 3)) * p.shape[1])
    out = 10.0 * torch.log10(torch.as_tensor(max_val, dtype=p.dtype, device=p.device) ** 2 / mse)
    return out if batched else out[0]


def _gaussian_kernel(window: int, sigma: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    x = torch.arange(window, dtype=torch.float64) - (window - 1) / 2
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return (g / g.sum()).to(dtype=dtype, device=device)


def gaussian_blur(img: torch.Tensor, sigma: float, truncate: float = 2.5) -> torch.Tensor:
    """Separable Gaussian blur of a float [C, H, W] image, replicated borders, radius ``max(1, ceil(truncate·σ))``
    (:func:`toolkit.regions.textureless_regions`; the segmenter keeps its own copy: metrics imports segment)."""
    r = max(1, math.ceil(truncate * sigma))
    c = img.shape[0]
    k = _gaussian_kernel(2 * r + 1, sigma, img.dtype, img.device).view(1, 1, 1, -1).expand(c, 1, 1, -1)
    x = F.conv2d(F.pad(img[None], (r, r, 0, 0), mode="replicate"), k, groups=c)
    return F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), k.transpose(-1, -2), groups=c)[0]


def ssim(
    pred: torch.Tensor,
    target: torch.Tensor,
    window: int = 11,
    sigma: float = 1.5,
    mask: torch.Tensor | None = None,
    padding: Literal["valid", "reflect"] = "valid",
    data_range: float = 1.0,
) -> torch.Tensor:
    """Structural similarity per image (eq. 32) with a Gaussian window, per channel then averaged.

    Local statistics use a separable, normalised ``window x window`` Gaussian (default 11x11, sigma 1.5), population
    (co)variances and ``c1 = (0.01 R)^2, c2 = (0.03 R)^2`` with ``R = data_range`` (Wang et al. 2004).

    Padding:
        ``"valid"`` (default, the metric): the SSIM map is computed only where the window fits inside the image
        (``[H - window + 1, W - window + 1]`` centres) and averaged there. This equals scikit-image's
        ``structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
        data_range=1, channel_axis=...)``, which filters with reflection and then crops ``(window - 1) / 2``
        pixels from each side before averaging. Needs ``H, W >= window``.
        ``"reflect"`` (for losses on small patches, e.g. 16x16 with ``1 - ssim``): the images are mirrored
        without repeating the edge pixel (``torch.nn.functional.pad(mode="reflect")``, scipy's ``"mirror"``)
        and every pixel gets an SSIM value. Needs ``H, W > window // 2``.

    Args:
        pred: float [B, C, H, W] or [C, H, W], values in [0, data_range].
        target: float, same shape.
        window: odd Gaussian window size in pixels.
        sigma: Gaussian standard deviation in pixels.
        mask: optional bool [B, H, W] (or [H, W]); the SSIM map is averaged over pixels whose *window centre* is
            True (windows still see their unmasked neighbours).
        padding: ``"valid"`` or ``"reflect"``, see above.
        data_range: dynamic range ``R`` of the images (1 for [0, 1]).

    Returns:
        float [B] (0-dim if unbatched) mean SSIM in [-1, 1] (1 = identical); NaN where the mask selects no
        centre. Differentiable (use ``1 - ssim(...)`` as a loss).

    Raises:
        ShapeError: shapes disagree, or the image is too small for the window and padding.
        DarsError: bad ``window``/``padding``/dtype.
    """
    p, t, m, batched = _check_images(pred, target, mask, "ssim")
    if not (isinstance(window, int) and window >= 1 and window % 2 == 1):
        raise DarsError(f"ssim: window={window!r} must be a positive odd integer (11 for the standard SSIM)")
    if not sigma > 0:
        raise DarsError(f"ssim: sigma={sigma!r} must be positive")
    if padding not in ("valid", "reflect"):
        raise DarsError(f"ssim: padding={padding!r} is not valid: choose 'valid' or 'reflect'")
    b, c, h, w = p.shape
    r = window // 2
    if padding == "valid" and (h < window or w < window):
        raise ShapeError(f"ssim: images of {h}x{w} are smaller than the {window}x{window} window; "
                         "use padding='reflect' for small patches or a smaller window")
    if padding == "reflect" and (h <= r or w <= r):
        raise ShapeError(f"ssim: images of {h}x{w} are too small to reflect-pad by {r}; need H, W > {r}")
    g = _gaussian_kernel(window, sigma, p.dtype, p.device)
    stats = torch.cat([p, t, p * p, t * t, p * t], dim=1)  # [B, 5C, H, W]
    if padding == "reflect":
        stats = F.pad(stats, (r, r, r, r), mode="reflect")
    n = stats.shape[1]
    stats = F.conv2d(stats, g.view(1, 1, 1, window).expand(n, 1, 1, window), groups=n)
    stats = F.conv2d(stats, g.view(1, 1, window, 1).expand(n, 1, window, 1), groups=n)
    mu_x, mu_y, e_xx, e_yy, e_xy = stats.split(c, dim=1)
    var_x = e_xx - mu_x * mu_x
    var_y = e_yy - mu_y * mu_y
    cov = e_xy - mu_x * mu_y
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    smap = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2))
    smap = smap.mean(dim=1)  # average over channels: [B, H', W']
    if m is None:
        out = smap.mean(dim=(1, 2))
    else:
        if padding == "valid":
            m = m[:, r:h - r, r:w - r]
        wt = m.to(smap.dtype)
        out = (smap * wt).sum(dim=(1, 2)) / wt.sum(dim=(1, 2))
    return out if batched else out[0]


def flip(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None,
         pixels_per_degree: float | None = None) -> torch.Tensor:
    """LDR-ꟻLIP error per image (Andersson et al. 2020), via NVIDIA's ``flip_evaluator`` package.

    Both images are **sRGB-encoded** LDR images in [0, 1] (what you would write to a PNG); ``target`` is the
    reference. No learned weights are involved. Always computed on the CPU, not differentiable.

    Args:
        pred: float [B, 3, H, W] or [3, H, W] test image(s), sRGB in [0, 1].
        target: float, same shape, reference image(s), sRGB in [0, 1].
        mask: optional bool [B, H, W] (or [H, W]); the FLIP error map is averaged over True pixels only
            (the error at a pixel still depends on its neighbours).
        pixels_per_degree: observer model; None = the package default (67.02, a 0.7 m wide 4K display at 0.7 m),
            the same default as the ``flip`` command line.

    Returns:
        float [B] (0-dim if unbatched) mean ꟻLIP error in [0, 1] (0 = identical), on the input's device.

    Raises:
        DarsError: values outside [0, 1] (tone-map / clamp HDR renders first) or bad shapes.
        MetricUnavailable: ``flip_evaluator`` is not installed, or a mask selects no pixel.
    """
    p, t, m, batched = _check_images(pred, target, mask, "flip", channels=3)
    for name, x in (("pred", p), ("target", t)):
        lo, hi = float(x.min()), float(x.max())
        if not (math.isfinite(lo) and math.isfinite(hi)) or lo < -1e-6 or hi > 1 + 1e-6:
            raise DarsError(f"flip: {name} has values in [{lo:.4g}, {hi:.4g}]; LDR-FLIP needs sRGB values in [0, 1] "
                            "(clamp or tone-map the image first)")
    try:
        import flip_evaluator
    except ImportError as e:  # pragma: no cover - it is a core dependency
        raise MetricUnavailable("flip: the flip_evaluator package is not installed (pip install flip-evaluator)") from e
    params = {} if pixels_per_degree is None else {"ppd": float(pixels_per_degree)}
    p_np = p.detach().to("cpu", torch.float32).clamp(0, 1).permute(0, 2, 3, 1).contiguous().numpy()
    t_np = t.detach().to("cpu", torch.float32).clamp(0, 1).permute(0, 2, 3, 1).contiguous().numpy()
    values = []
    for i in range(p_np.shape[0]):
        err_map, mean, _ = flip_evaluator.evaluate(t_np[i], p_np[i], "LDR", inputsRGB=True, applyMagma=False,
                                                    computeMeanError=True, parameters=dict(params))
        if m is None:
            values.append(float(mean))
        else:
            mi = m[i].cpu().numpy()
            _require_pixels(mi.sum(), "flip")
            values.append(float(np.asarray(err_map, dtype=np.float64)[..., 0][mi].mean()))
    out = torch.tensor(values, dtype=pred.dtype, device=pred.device)
    return out if batched else out[0]


# ---------------------------------------------------------------------- LPIPS
_LPIPS_SHIFT = (-0.030, -0.088, -0.188)
_LPIPS_SCALE = (0.458, 0.448, 0.450)
# torchvision AlexNet ``features`` convs that LPIPS taps: (index, out, in, kernel, stride, padding), each followed
# by a ReLU whose output is one LPIPS layer; max-pools (3, stride 2) follow conv 0 and conv 3.
_ALEX_CONVS = ((0, 64, 3, 11, 4, 2), (3, 192, 64, 5, 1, 2), (6, 384, 192, 3, 1, 1), (8, 256, 384, 3, 1, 1),
               (10, 256, 256, 3, 1, 1))
_LPIPS_MIN_SIZE = 31  # smallest H, W for which AlexNet's conv5 output is non-empty


def _lpips_expected() -> dict[str, tuple[int, ...]]:
    exp: dict[str, tuple[int, ...]] = {}
    for k, (idx, cout, cin, ks, _, _) in enumerate(_ALEX_CONVS):
        exp[f"features.{idx}.weight"] = (cout, cin, ks, ks)
        exp[f"features.{idx}.bias"] = (cout,)
        exp[f"lin{k}.weight"] = (1, cout, 1, 1)
    return exp


def _canonical_lpips_key(key: str) -> str | None:
    """Map the key spellings of torchvision / lpips checkpoints to ``features.N.*`` and ``linK.weight``."""
    parts = key.split(".")
    while parts and parts[0] == "module":
        parts = parts[1:]
    if len(parts) == 3 and parts[0] == "features":  # torchvision alexnet: features.N.weight
        return ".".join(parts)
    if len(parts) == 4 and parts[0] == "net" and parts[1].startswith("slice"):  # lpips.LPIPS(): net.sliceK.N.weight
        return f"features.{parts[2]}.{parts[3]}"
    if len(parts) == 4 and parts[0].startswith("lin") and parts[1] == "model" and parts[3] == "weight":
        return f"{parts[0]}.weight"  # lpips weights/v0.1/alex.pth: linK.model.1.weight (0 without dropout)
    return None


def _lpips_paths(weights_path: str | os.PathLike | Sequence[str | os.PathLike] | None) -> list[Path]:
    if weights_path is None:
        env = os.environ.get(LPIPS_ENV_VAR, "").strip()
        if not env:
            raise MetricUnavailable(
                "lpips: no pretrained weights given; LPIPS is only computed with the real AlexNet + LPIPS v0.1 "
                f"weights. Pass weights_path=... or set the environment variable {LPIPS_ENV_VAR} to the file(s) "
                "(see toolkit.metrics.load_lpips_weights)")
        items: list = [s for s in env.split(os.pathsep) if s]
    elif isinstance(weights_path, (str, os.PathLike)):
        items = [weights_path]
    else:
        items = list(weights_path)
    paths: list[Path] = []
    for item in items:
        path = Path(item).expanduser()
        if path.is_dir():
            found = sorted(q for q in path.iterdir() if q.suffix in (".pth", ".pt") and q.is_file())
            if not found:
                raise MetricUnavailable(f"lpips: weights directory {path} holds no .pth/.pt files")
            paths.extend(found)
        elif path.is_file():
            paths.append(path)
        else:
            raise MetricUnavailable(f"lpips: weights file not found: {path} (from weights_path or {LPIPS_ENV_VAR})")
    return paths


@functools.lru_cache(maxsize=4)
def _load_lpips_cached(key: tuple[tuple[str, float], ...]) -> dict[str, torch.Tensor]:
    merged: dict[str, torch.Tensor] = {}
    for file, _ in key:
        try:
            sd = torch.load(file, map_location="cpu", weights_only=True)
        except Exception as e:  # noqa: BLE001 - any unreadable file is reported the same way
            raise MetricUnavailable(f"lpips: cannot read weights file {file}: {e}") from e
        if isinstance(sd, dict) and "state_dict" in sd and isinstance(sd["state_dict"], dict):
            sd = sd["state_dict"]
        if not isinstance(sd, dict):
            raise MetricUnavailable(f"lpips: {file} does not hold a state dict (got {type(sd).__name__})")
        for k, v in sd.items():
            ck = _canonical_lpips_key(str(k))
            if ck is not None and isinstance(v, torch.Tensor):
                merged[ck] = v.detach().float()
    expected = _lpips_expected()
    files = ", ".join(f for f, _ in key)
    missing = [k for k in expected if k not in merged]
    if missing:
        raise MetricUnavailable(f"lpips: weights in [{files}] lack {missing}; expected torchvision AlexNet "
                                "'features.N.*' and LPIPS v0.1 'linK.model.1.weight' tensors")
    for k, shape in expected.items():
        if tuple(merged[k].shape) != shape:
            raise MetricUnavailable(f"lpips: weight {k} in [{files}] has shape {list(merged[k].shape)}, "
                                    f"expected {list(shape)} (AlexNet/LPIPS v0.1 'alex')")
    return {k: merged[k] for k in expected}


def load_lpips_weights(weights_path: str | os.PathLike | Sequence[str | os.PathLike] | None = None
                       ) -> dict[str, torch.Tensor]:
    """Load and check LPIPS-AlexNet weights from local files (never downloads).

    Expected files (the layouts of the ``lpips`` package v0.1, net ``'alex'``), either given together or merged
    into one state dict:

    * torchvision's ImageNet AlexNet, ``alexnet-owt-7be5be79.pth``: keys ``features.{0,3,6,8,10}.{weight,bias}``
      (``classifier.*`` is ignored); an ``lpips.LPIPS`` module state dict (``net.sliceK.N.*``) also works;
    * LPIPS' linear calibration, ``lpips/weights/v0.1/alex.pth``: keys ``lin{0..4}.model.1.weight``,
      shapes ``[1, C, 1, 1]`` with C = 64, 192, 384, 256, 256.

    Args:
        weights_path: a file, a directory (every ``.pth``/``.pt`` in it is read), or a sequence of those. None
            reads :data:`LPIPS_ENV_VAR` (``DARS_LPIPS_WEIGHTS``: paths separated by ``os.pathsep``).

    Returns:
        dict with keys ``features.N.weight``/``features.N.bias`` and ``linK.weight`` (float32, CPU).

    Raises:
        MetricUnavailable: no path given and the env var unset, a file missing/unreadable, or a key missing or
            of the wrong shape (named in the message).
    """
    paths = _lpips_paths(weights_path)
    key = tuple((str(p.resolve()), p.stat().st_mtime) for p in paths)
    return dict(_load_lpips_cached(key))


def lpips(pred: torch.Tensor, target: torch.Tensor,
          weights_path: str | os.PathLike | Sequence[str | os.PathLike] | None = None) -> torch.Tensor:
    """LPIPS distance per image (eq. 33), the ``lpips`` package v0.1 ``net='alex'`` definition, in plain torch.

    Inputs in [0, 1] are mapped to [-1, 1] (``normalize=True`` in the package), then through the scaling layer
    ``(x - shift) / scale`` (shift = (-0.030, -0.088, -0.188), scale = (0.458, 0.448, 0.450)); AlexNet's five
    ReLU outputs (after conv1..conv5) are unit-normalised over channels (``f / (||f|| + 1e-10)``), their squared
    difference is weighted by the learned non-negative 1x1 linear layers, averaged over space and summed over
    the five layers.

    Weights come only from local files (:func:`load_lpips_weights`); without them this raises
    :class:`MetricUnavailable` — it is never approximated with random or untrained weights.

    Args:
        pred: float [B, 3, H, W] or [3, H, W] in [0, 1] (sRGB, as displayed); H, W >= 31.
        target: float, same shape.
        weights_path: see :func:`load_lpips_weights`; None reads ``DARS_LPIPS_WEIGHTS``.

    Returns:
        float [B] (0-dim if unbatched) LPIPS distance (>= 0, 0 = identical; about 0-0.8 in practice).
        Differentiable with respect to the images; runs on the input's device.

    Raises:
        MetricUnavailable: no weights, or weights of the wrong layout (the message names the env var/file/key).
        ShapeError: shapes disagree or the image is smaller than 31x31.
    """
    p, t, _, batched = _check_images(pred, target, None, "lpips", channels=3)
    if p.shape[-1] < _LPIPS_MIN_SIZE or p.shape[-2] < _LPIPS_MIN_SIZE:
        raise ShapeError(f"lpips: images must be at least {_LPIPS_MIN_SIZE}x{_LPIPS_MIN_SIZE} for AlexNet, "
                         f"got {p.shape[-2]}x{p.shape[-1]}")
    wts = {k: v.to(device=p.device, dtype=p.dtype) for k, v in load_lpips_weights(weights_path).items()}
    shift = torch.tensor(_LPIPS_SHIFT, dtype=p.dtype, device=p.device).view(1, 3, 1, 1)
    scale = torch.tensor(_LPIPS_SCALE, dtype=p.dtype, device=p.device).view(1, 3, 1, 1)
    x = (torch.cat([p, t], dim=0) * 2 - 1 - shift) / scale
    total = torch.zeros(p.shape[0], dtype=p.dtype, device=p.device)
    for k, (idx, _, _, _, stride, pad) in enumerate(_ALEX_CONVS):
        if idx in (3, 6):
            x = F.max_pool2d(x, kernel_size=3, stride=2)
        x = F.relu(F.conv2d(x, wts[f"features.{idx}.weight"], wts[f"features.{idx}.bias"], stride=stride, padding=pad))
        f = x / (torch.sqrt((x * x).sum(dim=1, keepdim=True)) + 1e-10)
        f0, f1 = f.split(p.shape[0], dim=0)
        total = total + F.conv2d((f0 - f1) ** 2, wts[f"lin{k}.weight"]).mean(dim=(1, 2, 3))
    return total if batched else total[0]


# ====================================================================== materials and light
def material_mask(labels: torch.Tensor, depth: torch.Tensor | None = None,
                  surface: torch.Tensor | None = None) -> torch.Tensor:
    """Default mask for material metrics: labelled surface pixels that are not glass.

    Keeps pixels whose label is a material class (0 painting, 1 frame, 3 base, 4 wall, 5 floor, 6 other) and
    drops ``display`` (2, glass/acrylic: its "albedo" is not a surface property) and unlabelled/background
    (255). When ground-truth ``depth`` (SPEC: 0 = no hit) or a ``surface`` mask is given, pixels where the
    ground truth has no surface are dropped too.

    Args:
        labels: uint8/int [B, H, W] or [H, W] semantic ids (0-6, 255).
        depth: optional float, same shape, ground-truth depth in metres; ``<= 0`` or non-finite = no surface.
        surface: optional bool, same shape, True where the ground truth has a surface (e.g. alpha > 0).

    Returns:
        bool, same shape as ``labels``.

    Raises:
        DarsError: labels outside {0..6, 255}, float labels, or shape mismatch.
    """
    if not isinstance(labels, torch.Tensor) or labels.is_floating_point() or labels.dtype == torch.bool:
        raise DarsError(f"material_mask: labels must be an integer tensor of class ids, got "
                        f"{labels.dtype if isinstance(labels, torch.Tensor) else type(labels).__name__}")
    bad = ~(((labels >= 0) & (labels <= 6)) | (labels == UNLABELLED))
    if bool(bad.any()):
        raise DarsError(f"material_mask: labels contain ids outside 0-6 and 255, e.g. {int(labels[bad][0])}")
    keep = (labels != UNLABELLED) & (labels != DISPLAY_CLASS)
    if depth is not None:
        if depth.shape != labels.shape:
            raise ShapeError(f"material_mask: depth shape {list(depth.shape)} != labels shape {list(labels.shape)}")
        keep = keep & torch.isfinite(depth) & (depth > 0)
    if surface is not None:
        _check_mask(surface, labels.shape, "material_mask (surface)")
        keep = keep & surface
    return keep


def _pooled_pixels(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, fn: str,
                   channels: int | None) -> tuple[torch.Tensor, torch.Tensor]:
    """Return the masked values of pred and target as ``[N, C]`` (C channels)."""
    if not isinstance(pred, torch.Tensor) or not isinstance(target, torch.Tensor):
        raise DarsError(f"{fn}: pred and target must be torch tensors")
    if pred.shape != target.shape:
        raise ShapeError(f"{fn}: pred and target must have the same shape, got {list(pred.shape)} and {list(target.shape)}")
    if channels == 1 and pred.dim() in (2, 3) and list(mask.shape) == list(pred.shape):
        pred, target = pred.unsqueeze(-3), target.unsqueeze(-3)  # [B, H, W] / [H, W] single-channel maps
    if pred.dim() == 3:
        pred, target, mask = pred[None], target[None], mask[None] if isinstance(mask, torch.Tensor) else mask
    if pred.dim() != 4 or (channels is not None and pred.shape[1] != channels):
        c = "C" if channels is None else str(channels)
        raise ShapeError(f"{fn}: pred must be [B, {c}, H, W] or [{c}, H, W], got {list(pred.shape)}")
    b, c, h, w = pred.shape
    _check_mask(mask, [b, h, w], fn)
    mask = mask.to(pred.device)
    _require_pixels(mask.sum(), fn)
    return pred.permute(0, 2, 3, 1)[mask], target.permute(0, 2, 3, 1)[mask]


def albedo_mae(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Albedo mean absolute error (eq. 34) over masked pixels and channels, linear albedo.

    ``mean |a_pred - a_gt|`` over the N masked pixels of the whole batch *and* the 3 channels, i.e. eq. 34's
    per-pixel L1 norm divided by 3 (so the value is in [0, 1] like the albedo itself).

    Args:
        pred: float [B, 3, H, W] or [3, H, W] predicted linear albedo in [0, 1].
        target: float, same shape, ground-truth linear albedo.
        mask: bool [B, H, W] (or [H, W]); e.g. :func:`material_mask`.

    Returns:
        float 0-dim tensor.

    Raises:
        MetricUnavailable: the mask selects no pixels. ShapeError: shape mismatch.
    """
    a, b = _pooled_pixels(pred, target, mask, "albedo_mae", 3)
    return (a - b).abs().mean()


def albedo_mae_aligned(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """Albedo MAE after a per-channel least-squares scale: the part of the albedo error that light cannot explain.

    From photos alone, albedo and light are known only up to a common scale per colour channel (a twice brighter
    light and a half as bright albedo render the same photo), so papers on inverse rendering (NeRFactor, InvRender,
    TensoIR) also score albedo after aligning its scale to the ground truth. ``s_c = Σ p_c g_c / Σ p_c²`` over the
    masked pixels, then ``mean |s_c p_c - g_c|`` as in :func:`albedo_mae`. Report it *beside* ``albedo_mae``, never
    instead of it: a user's asset carries the unaligned albedo.

    Args:
        pred, target, mask: as :func:`albedo_mae`.

    Returns:
        (MAE, float 0-dim tensor; scale, float [3] tensor — above 1: the prediction is too dark).

    Raises:
        MetricUnavailable: the mask selects no pixels. ShapeError: shape mismatch.
    """
    a, b = _pooled_pixels(pred, target, mask, "albedo_mae_aligned", 3)
    a64, b64 = a.double(), b.double()
    scale = (a64 * b64).sum(0) / (a64 * a64).sum(0).clamp_min(1e-12)
    return (a64 * scale - b64).abs().mean().to(pred.dtype), scale.to(pred.dtype)


def metallic_mae(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Metallic mean absolute error over masked pixels of the whole batch (shapes as :func:`roughness_rmse`)."""
    a, b = _pooled_pixels(pred, target, mask, "metallic_mae", 1)
    return (a - b).abs().mean()


def roughness_rmse(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Roughness root-mean-square error (eq. 35) over masked pixels of the whole batch.

    Args:
        pred: float [B, 1, H, W], [B, H, W] or [1, H, W] predicted roughness in [0, 1] (perceptual roughness,
            the glTF/principled-BSDF parameter, not alpha = roughness^2).
        target: float, same shape, ground truth.
        mask: bool [B, H, W] (or [H, W] when unbatched).

    Returns:
        float 0-dim tensor.

    Raises:
        MetricUnavailable: the mask selects no pixels. ShapeError: shape mismatch.
    """
    a, b = _pooled_pixels(pred, target, mask, "roughness_rmse", 1)
    return torch.sqrt(((a - b) ** 2).mean())


def env_light_l2(pred_sh: torch.Tensor, gt_sh: torch.Tensor) -> torch.Tensor:
    """Environment-light L2 (eq. 36): Euclidean norm of the difference of the 27 SH coefficients.

    Args:
        pred_sh: float [..., 9, 3] predicted SH radiance coefficients (SPEC order and basis).
        gt_sh: float, same shape, ground truth (e.g. fitted to the HDR probe with ``toolkit.sh``).

    Returns:
        float [...] (0-dim for a single [9, 3]) ``||pred - gt||_2`` over the 27 values.
    """
    check_shape(pred_sh, "... 9 3", "pred_sh")
    check_shape(gt_sh, "... 9 3", "gt_sh")
    if pred_sh.shape != gt_sh.shape:
        raise ShapeError(f"env_light_l2: pred_sh and gt_sh must have the same shape, got {list(pred_sh.shape)} and {list(gt_sh.shape)}")
    return torch.linalg.vector_norm(pred_sh - gt_sh.to(pred_sh), dim=(-2, -1))


def normal_mae_deg(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean angular error between normal maps, in degrees, pooled over masked pixels of the batch.

    Both maps are normalised per pixel; the angle is ``acos(clamp(<n_pred, n_gt>, -1, 1))``. A zero-length
    predicted normal counts as 90 degrees.

    Args:
        pred: float [B, 3, H, W] or [3, H, W] predicted normals (world space, need not be unit length).
        target: float, same shape, ground-truth normals.
        mask: optional bool [B, H, W] (or [H, W]). None = pixels whose ground-truth normal is non-zero and
            finite (the SPEC's "no surface" is a zero normal).

    Returns:
        float 0-dim tensor, degrees in [0, 180].

    Raises:
        MetricUnavailable: no pixel to measure. ShapeError: shape mismatch.
    """
    if mask is None:
        if not isinstance(target, torch.Tensor) or target.dim() not in (3, 4):
            raise ShapeError(f"normal_mae_deg: target must be [B, 3, H, W] or [3, H, W]")
        cdim = target.dim() - 3
        mask = torch.isfinite(target).all(dim=cdim) & (target.abs().sum(dim=cdim) > 0)
    a, b = _pooled_pixels(pred, target, mask, "normal_mae_deg", 3)
    a = a / a.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    b = b / b.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    cos = (a * b).sum(-1).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.acos(cos)).mean()


# ====================================================================== view consistency
def luminance(images: torch.Tensor, space: Literal["linear", "srgb"] = "linear") -> torch.Tensor:
    """Rec. 709 relative luminance ``Y = 0.2126 R + 0.7152 G + 0.0722 B`` of linear RGB.

    Args:
        images: float [..., 3, H, W]; linear RGB, or sRGB-encoded when ``space="srgb"`` (decoded first).
        space: ``"linear"`` or ``"srgb"``.

    Returns:
        float [..., H, W] luminance in the images' linear units.
    """
    check_shape(images, "... 3 H W", "images")
    if space not in ("linear", "srgb"):
        raise DarsError(f"luminance: space={space!r} is not valid: choose 'linear' or 'srgb'")
    lin = srgb_to_linear(images) if space == "srgb" else images
    wts = torch.tensor(REC709_LUMA, dtype=lin.dtype, device=lin.device).view(3, 1, 1)
    return (lin * wts).sum(dim=-3)


def view_consistency(
    images: torch.Tensor,
    masks: torch.Tensor,
    space: Literal["linear", "srgb"] = "linear",
    lux_factor: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cross-view brightness consistency (eqs. 37-38): sample std of a region's mean luminance over K views.

    ``I_k`` = mean Rec. 709 luminance (of linear RGB) over the True pixels of ``masks[k]``;
    result = ``sqrt(sum_k (I_k - mean(I))^2 / (K - 1))``. The region is usually a 3D surface patch seen in K
    uniformly spaced views (:func:`patch_masks`, :func:`uniform_view_indices`; K = 10 in the paper).

    Args:
        images: float [K, 3, H, W] rendered views, linear RGB (``space="linear"``) or sRGB (``space="srgb"``,
            decoded to linear first).
        masks: bool [K, H, W] region per view.
        space: colour encoding of ``images``.
        lux_factor: optional calibration, lux per unit of linear luminance; when given both outputs are in lux
            (``lux = lux_factor * luminance``), otherwise in relative luminance units.

    Returns:
        (std, per_view_means): float 0-dim sample standard deviation (K - 1 in the denominator) and float [K]
        the ``I_k``.

    Raises:
        MetricUnavailable: K < 2 or a view's mask is empty (the message names the view).
        ShapeError: shape mismatch.
    """
    dims = check_shape(images, "K 3 H W", "images")
    _check_mask(masks, [dims["K"], dims["H"], dims["W"]], "view_consistency")
    if dims["K"] < 2:
        raise MetricUnavailable("view_consistency: needs at least 2 views (K - 1 in the denominator)")
    masks = masks.to(images.device)
    counts = masks.sum(dim=(1, 2))
    empty = (counts == 0).nonzero().flatten().tolist()
    if empty:
        raise MetricUnavailable(f"view_consistency: the region is not visible in view(s) {empty} (empty mask)")
    y = luminance(images, space)
    means = (y * masks.to(y.dtype)).sum(dim=(1, 2)) / counts.to(y.dtype)
    if lux_factor is not None:
        if not (isinstance(lux_factor, (int, float)) and math.isfinite(lux_factor) and lux_factor > 0):
            raise DarsError(f"view_consistency: lux_factor={lux_factor!r} must be a positive number")
        means = means * lux_factor
    return means.std(unbiased=True), means


def uniform_view_indices(n: int, k: int = 10) -> list[int]:
    """``k`` uniformly spaced view indices in ``range(n)``, first and last included (``round(linspace(0, n-1, k))``).

    Raises:
        DarsError: ``k < 1`` or ``k > n`` (ask for at most ``n`` views).

    Example:
        >>> uniform_view_indices(100, 10)
        [0, 11, 22, 33, 44, 55, 66, 77, 88, 99]
    """
    if not (isinstance(n, int) and isinstance(k, int)) or k < 1 or n < 1:
        raise DarsError(f"uniform_view_indices: need positive integers, got n={n!r}, k={k!r}")
    if k > n:
        raise DarsError(f"uniform_view_indices: cannot pick k={k} distinct views out of n={n}; ask for at most {n}")
    if k == 1:
        return [0]
    return [int(math.floor(i * (n - 1) / (k - 1) + 0.5)) for i in range(k)]


def _patch_frame(centre: torch.Tensor, normal: torch.Tensor, up: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    n = normal / normal.norm()
    u = torch.linalg.cross(up, n)
    if float(u.norm()) < 1e-6:  # normal parallel to up (floor/ceiling patch): use +y as the in-plane reference
        u = torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0], dtype=n.dtype, device=n.device), n)
    u = u / u.norm()
    v = torch.linalg.cross(n, u)
    return n, u, v


def patch_masks(
    cameras: Cameras,
    indices: Sequence[int],
    centre: torch.Tensor | Sequence[float],
    normal: torch.Tensor | Sequence[float],
    size: float,
    up: Sequence[float] = (0.0, 0.0, 1.0),
    depths: torch.Tensor | None = None,
    depth_tol: float = 0.05,
    cull_backfacing: bool = True,
) -> torch.Tensor:
    """Masks of a square 3D surface patch seen in K views (the "same pixel area" of eqs. 37-38).

    The patch is the square of side ``size`` centred at ``centre`` in the plane with normal ``normal``; its
    edges run along ``up x normal`` and the in-plane "up" (``normal x (up x normal)``), or +y-based axes when
    ``normal`` is parallel to ``up``. Its 4 corners are projected with :func:`toolkit.scene.project_points` and the
    quadrilateral is rasterised exactly: a pixel is in the mask iff its centre ``(u + 0.5, v + 0.5)`` lies
    inside the projected quad. (We do not use ``cv2.fillPoly``: it fills pixels touched by the edges, so a
    20-pixel square becomes 21x21, +10% area; the test checks agreement with it up to that one-pixel band.)

    A view gets an empty mask when a corner is behind the camera, or (``cull_backfacing``) when the camera sees
    the back of the patch. With ``depths``, pixels where the depth map is nearer than the patch plane by more
    than ``depth_tol`` are dropped as occluded; pixels with no depth (0 or non-finite, SPEC "no hit") carry no
    evidence of occlusion and are kept.

    Args:
        cameras: the scene's cameras (pinhole, OpenGL convention).
        indices: K camera indices (e.g. :func:`uniform_view_indices`); all views must share one image size.
        centre: float [3] patch centre, world space, metres.
        normal: float [3] patch normal (pointing toward the side it is seen from), world space.
        size: side length of the square, metres.
        up: world up used to orient the square's edges (SPEC: +z).
        depths: optional float [K, H, W] depth maps of those views, metres along the camera axis.
        depth_tol: occlusion tolerance in metres.
        cull_backfacing: give an empty mask to views that see the patch from behind.

    Returns:
        bool [K, H, W] on the cameras' device.

    Raises:
        ShapeError: bad centre/normal/depths shape, or views of different image sizes.
        DarsError: non-positive size or zero normal.
    """
    idx = [int(i) for i in indices]
    if not idx:
        raise DarsError("patch_masks: indices is empty")
    device = cameras.c2w.device
    dtype = cameras.c2w.dtype if cameras.c2w.is_floating_point() else torch.float32
    centre = torch.as_tensor(centre, dtype=dtype, device=device)
    normal = torch.as_tensor(normal, dtype=dtype, device=device)
    check_shape(centre, "3", "centre")
    check_shape(normal, "3", "normal")
    if not (math.isfinite(size) and size > 0):
        raise DarsError(f"patch_masks: size={size!r} must be a positive side length in metres")
    if float(normal.norm()) < 1e-12:
        raise DarsError("patch_masks: normal must be non-zero")
    hs = {int(cameras.height[i]) for i in idx}
    ws = {int(cameras.width[i]) for i in idx}
    if len(hs) != 1 or len(ws) != 1:
        raise ShapeError(f"patch_masks: views {idx} have different image sizes (heights {sorted(hs)}, widths {sorted(ws)})")
    h, w = hs.pop(), ws.pop()
    if depths is not None:
        check_shape(depths, f"{len(idx)} {h} {w}", "depths")
        depths = depths.to(device=device, dtype=dtype)
    n, eu, ev = _patch_frame(centre, normal, torch.as_tensor(up, dtype=dtype, device=device))
    half = 0.5 * size
    corners = torch.stack([centre - half * eu - half * ev, centre + half * eu - half * ev,
                           centre + half * eu + half * ev, centre - half * eu + half * ev])  # counter-clockwise seen from +n
    ys, xs = torch.meshgrid(torch.arange(h, dtype=dtype, device=device) + 0.5,
                            torch.arange(w, dtype=dtype, device=device) + 0.5, indexing="ij")
    out = torch.zeros(len(idx), h, w, dtype=torch.bool, device=device)
    for k, i in enumerate(idx):
        origin = cameras.c2w[i, :3, 3].to(dtype)
        if cull_backfacing and float(torch.dot(n, origin - centre)) <= 0:
            continue
        uv, z = project_points(cameras, i, corners)
        if bool((z <= 1e-6).any()):
            continue
        inside = torch.ones(h, w, dtype=torch.bool, device=device)
        # sign of the quad's orientation in the image, so the half-plane tests work for either winding
        area = sum(uv[j, 0] * uv[(j + 1) % 4, 1] - uv[(j + 1) % 4, 0] * uv[j, 1] for j in range(4))
        sgn = 1.0 if float(area) >= 0 else -1.0
        for j in range(4):
            a, b = uv[j], uv[(j + 1) % 4]
            cross = (b[0] - a[0]) * (ys - a[1]) - (b[1] - a[1]) * (xs - a[0])
            inside &= sgn * cross >= 0
        if depths is not None:
            # depth of the patch plane at each pixel centre: ray d = ((x - cx)/fx, -(y - cy)/fy, -1) in camera space
            rot = cameras.c2w[i, :3, :3].to(dtype)
            n_cam = rot.T @ n
            c_cam = rot.T @ (centre - origin)
            dx = (xs - cameras.cx[i].to(dtype)) / cameras.fx[i].to(dtype)
            dy = -(ys - cameras.cy[i].to(dtype)) / cameras.fy[i].to(dtype)
            denom = n_cam[0] * dx + n_cam[1] * dy - n_cam[2]
            plane_depth = torch.dot(n_cam, c_cam) / torch.where(denom.abs() < 1e-12, torch.full_like(denom, 1e-12), denom)
            d = depths[k]
            occluded = torch.isfinite(d) & (d > 0) & (d < plane_depth - depth_tol)
            inside &= ~occluded
        out[k] = inside
    return out


# ====================================================================== geometry
def _points_np(x, name: str) -> np.ndarray:
    arr = x.detach().cpu().double().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ShapeError(f"{name}: expected shape [N, 3], got {list(arr.shape)}")
    if arr.shape[0] == 0:
        raise MetricUnavailable(f"{name} is empty: no points to compare")
    if not np.isfinite(arr).all():
        raise DarsError(f"{name} contains NaN or inf values")
    return arr


def _nn_distances(points_a, points_b) -> tuple[np.ndarray, np.ndarray]:
    from scipy.spatial import cKDTree

    a, b = _points_np(points_a, "points_a"), _points_np(points_b, "points_b")
    d_ab = cKDTree(b).query(a, k=1)[0]
    d_ba = cKDTree(a).query(b, k=1)[0]
    return d_ab, d_ba


def chamfer_distance(points_a: torch.Tensor | np.ndarray, points_b: torch.Tensor | np.ndarray) -> dict[str, float]:
    """Symmetric Chamfer distance with *unsquared* Euclidean nearest-neighbour distances, in the points' units.

    ``a_to_b`` = mean over a of ``min_b ||a - b||_2``; ``b_to_a`` likewise; ``chamfer = (a_to_b + b_to_a) / 2``.
    (Some papers sum the two terms or use squared distances; this one is in metres, not metres².)
    Uses ``scipy.spatial.cKDTree``: always computed on the CPU in float64, not differentiable.

    Args:
        points_a: float [N, 3] e.g. points sampled on the reconstructed mesh (:func:`sample_mesh_surface`).
        points_b: float [M, 3] e.g. points sampled on the reference mesh.

    Returns:
        dict with floats ``chamfer``, ``a_to_b``, ``b_to_a``.

    Raises:
        MetricUnavailable: an empty point set. ShapeError: not [N, 3].
    """
    d_ab, d_ba = _nn_distances(points_a, points_b)
    a_to_b, b_to_a = float(d_ab.mean()), float(d_ba.mean())
    return {"chamfer": 0.5 * (a_to_b + b_to_a), "a_to_b": a_to_b, "b_to_a": b_to_a}


def fscore(points_a: torch.Tensor | np.ndarray, points_b: torch.Tensor | np.ndarray, threshold: float) -> dict[str, float]:
    """Precision, recall and F-score at distance ``threshold`` (Tanks and Temples / Knapitsch et al. 2017).

    ``points_a`` is the reconstruction and ``points_b`` the reference: precision = fraction of a closer than
    ``threshold`` to b (strictly ``<``), recall = fraction of b closer than ``threshold`` to a,
    ``F = 2PR / (P + R)`` (0 when both are 0). CPU only (cKDTree).

    Args:
        points_a: float [N, 3] reconstruction samples.
        points_b: float [M, 3] reference samples.
        threshold: tau, in the points' units (metres).

    Returns:
        dict with floats ``precision``, ``recall``, ``fscore`` in [0, 1].
    """
    if not (isinstance(threshold, (int, float)) and math.isfinite(threshold) and threshold > 0):
        raise DarsError(f"fscore: threshold={threshold!r} must be a positive distance")
    d_ab, d_ba = _nn_distances(points_a, points_b)
    precision = float((d_ab < threshold).mean())
    recall = float((d_ba < threshold).mean())
    f = 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)
    return {"precision": precision, "recall": recall, "fscore": f}


def sample_mesh_surface(vertices: torch.Tensor | np.ndarray, faces: torch.Tensor | np.ndarray, n: int,
                        seed: int = 0) -> torch.Tensor:
    """``n`` points uniformly distributed over a triangle mesh's surface (area-weighted, seeded).

    Faces are drawn with probability proportional to their area, then a uniform point in the triangle with
    ``(1 - sqrt(r1)) A + sqrt(r1)(1 - r2) B + sqrt(r1) r2 C`` (Osada et al. 2002). Random numbers come from
    ``numpy.random.default_rng(seed)`` on the CPU, so results do not depend on the device.

    Args:
        vertices: float [V, 3] vertex positions.
        faces: int [F, 3] vertex indices.
        n: number of points.
        seed: random seed.

    Returns:
        float [n, 3] (the vertices' dtype and device; float64 for numpy input).

    Raises:
        ShapeError: bad shapes. DarsError: face indices out of range, or the mesh has zero area.
    """
    v = vertices.detach().cpu().double().numpy() if isinstance(vertices, torch.Tensor) else np.asarray(vertices, np.float64)
    f = faces.detach().cpu().numpy() if isinstance(faces, torch.Tensor) else np.asarray(faces)
    check_shape(v, "V 3", "vertices")
    check_shape(f, "F 3", "faces")
    if not (isinstance(n, int) and n >= 1):
        raise DarsError(f"sample_mesh_surface: n={n!r} must be a positive integer")
    f = f.astype(np.int64)
    if f.size == 0 or f.min() < 0 or f.max() >= len(v):
        raise DarsError(f"sample_mesh_surface: face indices must lie in [0, {len(v) - 1}]")
    tri = v[f]  # [F, 3, 3]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    total = area.sum()
    if not (np.isfinite(total) and total > 0):
        raise DarsError("sample_mesh_surface: the mesh has zero (or non-finite) surface area")
    rng = np.random.default_rng(seed)
    fid = rng.choice(len(f), size=n, p=area / total)
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    pts = ((1 - s)[:, None] * tri[fid, 0] + (s * (1 - r2))[:, None] * tri[fid, 1] + (s * r2)[:, None] * tri[fid, 2])
    if isinstance(vertices, torch.Tensor):
        dtype = vertices.dtype if vertices.is_floating_point() else torch.float32
        return torch.as_tensor(pts, dtype=dtype, device=vertices.device)
    return torch.from_numpy(pts)


def mesh_depth_map(vertices: torch.Tensor | np.ndarray, faces: torch.Tensor | np.ndarray, cameras,
                   index: int) -> np.ndarray:
    """Depth of a triangle mesh seen from a camera: every pixel's ray cast against it (Open3D's CPU ray caster).

    Args:
        vertices: float [V, 3] world positions (metres, the scene's frame).
        faces: int [F, 3].
        cameras: :class:`toolkit.scene.Cameras`.
        index: which camera.

    Returns:
        float [H, W] metres along the optical axis; inf where the ray misses the mesh.
    """
    import open3d as o3d

    from .cameras import generate_rays

    v = vertices.detach().cpu().numpy() if isinstance(vertices, torch.Tensor) else np.asarray(vertices)
    f = faces.detach().cpu().numpy() if isinstance(faces, torch.Tensor) else np.asarray(faces)
    check_shape(v, "V 3", "vertices")
    check_shape(f, "F 3", "faces")
    h, w = int(cameras.height[index]), int(cameras.width[index])
    rays = generate_rays(cameras, [index])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    q = np.concatenate([rays.origins.cpu().numpy(), rays.directions.cpu().numpy()], -1).astype(np.float32)
    t_hit = scene.cast_rays(o3d.core.Tensor(q))["t_hit"].numpy()
    return (t_hit * rays.z_scale.cpu().numpy()).reshape(h, w)


def mesh_depth_error(vertices: torch.Tensor | np.ndarray, faces: torch.Tensor | np.ndarray, cameras, index: int,
                     gt_depth: torch.Tensor, mask: torch.Tensor | None = None) -> dict[str, float]:
    """Depth error of a triangle mesh seen from a camera against a ground-truth depth map.

    Every pixel's ray is cast against the mesh (Open3D's CPU ray caster); its depth along the optical axis is
    compared with ``gt_depth`` where both exist. Meant for exported assets (GLB) against a scene's test views.

    Args:
        vertices: float [V, 3] world positions (metres, the scene's frame).
        faces: int [F, 3].
        cameras: :class:`toolkit.scene.Cameras`.
        index: which camera.
        gt_depth: float [H, W] metres along the optical axis (0 = no surface).
        mask: optional bool [H, W] pixels to score.

    Returns:
        ``{"median": m, "mean": m, "p90": m, "coverage": fraction of scored GT pixels the mesh covers,
        "pixels": n}`` (errors in metres; NaN when the mesh covers no scored pixel).
    """
    h, w = int(cameras.height[index]), int(cameras.width[index])
    check_shape(gt_depth, f"{h} {w}", "gt_depth")
    depth = mesh_depth_map(vertices, faces, cameras, index).reshape(-1)
    gt = gt_depth.detach().cpu().numpy().reshape(-1)
    valid = gt > 0
    if mask is not None:
        valid &= mask.detach().cpu().numpy().reshape(-1).astype(bool)
    hit = np.isfinite(depth)
    both = valid & hit
    err = np.abs(depth[both] - gt[both])
    if err.size == 0:
        return {"median": float("nan"), "mean": float("nan"), "p90": float("nan"), "coverage": 0.0,
                "pixels": int(valid.sum())}
    return {"median": float(np.median(err)), "mean": float(err.mean()), "p90": float(np.quantile(err, 0.9)),
            "coverage": float(both.sum() / max(1, valid.sum())), "pixels": int(valid.sum())}
