"""Stage 3 — 7-class semantic segmentation of the photos (SPEC classes, 255 = unlabelled).

One function, three backends (:class:`SegmentConfig.backend`):

* ``"provided"``: the scene's own label images (``semantic_path``), validated and passed through.
* ``"builtin"``: :class:`Segmenter`, a compact U-Net (plain torch, GroupNorm so train and eval behave the same and
  ONNX export is trivial, 0.35 M parameters) trained by :func:`train_segmenter` on a few labelled views and
  applied to the rest. On the bundled sample (trained on every 4th of the 80 train views, 500 steps, ~1.5 min on
  one core) it reaches mIoU 0.88 on the 20 test views.
* ``"onnx"``: any ONNX segmenter, run with ONNX Runtime under this contract:

  - **input**: one tensor, float32 (float16 accepted) NCHW, RGB, sRGB-encoded values in [0, 1]. Static spatial
    sizes are honoured by resizing the images bilinearly (with antialiasing when shrinking); dynamic ones get the
    images as they are; a static batch of 1 is run image by image. If the model's ``metadata_props`` has
    ``dars.normalize = imagenet``, inputs are ``(x - mean) / std`` with the ImageNet mean (0.485, 0.456, 0.406)
    and std (0.229, 0.224, 0.225) (e.g. an exported Mask2Former/SegFormer); ``none`` (default) passes [0, 1].
  - **output** (the first one): either float logits ``N x 7 x h x w`` (any h, w: resized bilinearly to H x W,
    then softmax and argmax) or int labels ``N x h x w`` (resized nearest to H x W; values 0-6 or 255).
  - Anything else fails with a :class:`SegmentationError` saying what the model has and what is expected.

:func:`mean_iou` is the mIoU used everywhere (the evaluation stage imports it from here).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ._checks import ConfigError, DarsError, ShapeError, check_shape
from .io import save_torch

__all__ = [
    "NUM_CLASSES",
    "METAL_THRESHOLD",
    "IGNORE_INDEX",
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "SegmentationError",
    "SegmentConfig",
    "Segmentation",
    "SegmenterConfig",
    "Segmenter",
    "TrainSegmenterConfig",
    "SegmenterTraining",
    "segment_images",
    "train_segmenter",
    "mean_iou",
    "metal_iou",
    "validate_labels",
    "save_segmenter",
    "SCENE_PRIOR_FLOOR",
    "SCENE_PRIOR_CEILING",
    "train_class_prior",
    "segmenter_train_prior",
    "estimate_scene_prior",
    "apply_scene_prior",
    "load_segmenter",
    "DEFAULT_SEGMENTER",
    "SegmenterExport",
    "work_resolution",
]

NUM_CLASSES = 7
IGNORE_INDEX = 255
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
_FORMAT = "dars-segmenter"
DEFAULT_SEGMENTER = Path(__file__).resolve().parent / "weights" / "segmenter_small.pt"
"""The shipped segmenter: 7 classes + metal mask, trained on procedural galleries (card: ``segmenter_small.json``,
reproduced by ``bench/bench_segmenter.py``)."""


class SegmentationError(DarsError):
    """Bad labels, a missing or unusable model, or an ONNX model that does not fit the contract."""


# ============================================================================ configs and results
@dataclass(frozen=True)
class SegmentConfig:
    """Options of :func:`segment_images`.

    Attributes:
        backend: ``"provided"`` (scene labels), ``"builtin"`` (:class:`Segmenter`) or ``"onnx"`` (a file).
        batch_size: images per forward pass (memory bound).
        onnx_path: ONNX file for the ``onnx`` backend when ``model`` is not given.
    """

    backend: Literal["provided", "builtin", "onnx"] = "provided"
    batch_size: int = 8
    onnx_path: str | None = None

    def __post_init__(self):
        if self.backend not in ("provided", "builtin", "onnx"):
            raise ConfigError(f"backend={self.backend!r} is not valid: choose 'provided', 'builtin' or 'onnx'")
        if self.batch_size < 1:
            raise ConfigError(f"batch_size={self.batch_size} must be >= 1")


@dataclass(frozen=True)
class Segmentation:
    """Result of :func:`segment_images`.

    Attributes:
        labels: int64 [B, H, W] class ids 0-6 (255 only where the ``provided`` labels are unlabelled).
        probabilities: float [B, 7, H, W] class probabilities (one-hot for provided labels, all zero where they are
            255; a softmax for the networks).
        backend: which backend produced them.
        metal: float [B, H, W] probability that a pixel is metal (networks with a metal channel), else None.
    """

    labels: torch.Tensor
    probabilities: torch.Tensor
    backend: str
    metal: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.labels.shape[0])


@dataclass(frozen=True)
class SegmenterConfig:
    """Architecture of :class:`Segmenter`.

    Attributes:
        widths: channels of the encoder levels (each level halves the resolution after the first); the last is the
            bottleneck.
        groups: GroupNorm groups (must divide every width).
        num_classes: output classes (7 in the SPEC).
        metal: one more output channel, the logit of the metal mask (eq. 4's and eq. 20's I_metal: metal frames,
            bases and other objects).
        work_size: the short side (pixels) photos are resized to before the network sees them, and the logits
            resized back (the scale it was trained at; 0: as given). The shipped network uses 160.
    """

    widths: tuple[int, ...] = (16, 32, 64, 128)
    groups: int = 8
    num_classes: int = NUM_CLASSES
    metal: bool = False
    work_size: int = 0

    def __post_init__(self):
        if len(self.widths) < 2 or any(w < 1 for w in self.widths):
            raise ConfigError(f"widths={self.widths}: need at least two positive widths")
        if any(w % self.groups for w in self.widths):
            raise ConfigError(f"groups={self.groups} must divide every width in {self.widths}")
        if self.work_size < 0:
            raise ConfigError(f"work_size={self.work_size} must be >= 0 (0: the photos' own size)")


@dataclass(frozen=True)
class TrainSegmenterConfig:
    """Options of :func:`train_segmenter` (defaults: 1.5-2.5 minutes on one CPU core for 20 views of 128 px).

    Attributes:
        arch: network architecture.
        steps: optimiser steps.
        batch_size: crops per step.
        crop: side of the square training crops in pixels (``0``: whole images); crops are taken after a random
            rescale in ``scale_range``, so the network sees objects at several distances.
        scale_range: random rescale factors of a training image before cropping.
        lr: peak AdamW learning rate (one-cycle schedule).
        weight_decay: AdamW weight decay.
        hflip: random horizontal flips (no vertical flips: floors are below walls in every photo).
        colour_jitter: strength of the random brightness / contrast / per-channel gain / saturation jitter (0 = off).
        class_balance: weight the cross-entropy by inverse square-root class frequency (small classes such as
            frames and bases count more).
        exposure_stops: random exposure change of up to this many stops (applied in linear light; 0 = off).
        noise: largest standard deviation of the Gaussian sensor noise added (sRGB units; 0 = off).
        blur: largest Gaussian blur sigma in pixels, applied to a third of the crops (0 = off).
        jpeg: lowest JPEG quality a third of the crops are re-encoded at (0 = off; qualities up to 95).
        metal_weight: weight of the metal mask's binary cross-entropy (networks with a metal channel, given masks).
        seed: seed of initialisation, sampling and augmentation.
        progress: show a tqdm bar on stderr.
    """

    arch: SegmenterConfig = field(default_factory=SegmenterConfig)
    steps: int = 500
    batch_size: int = 8
    crop: int = 96
    scale_range: tuple[float, float] = (0.75, 1.25)
    lr: float = 4e-3
    weight_decay: float = 1e-4
    hflip: bool = True
    colour_jitter: float = 0.2
    class_balance: bool = True
    exposure_stops: float = 0.0
    noise: float = 0.0
    blur: float = 0.0
    jpeg: int = 0
    metal_weight: float = 1.0
    seed: int = 0
    progress: bool = False

    def __post_init__(self):
        if self.steps < 0 or self.batch_size < 1:
            raise ConfigError(f"steps={self.steps} must be >= 0 and batch_size={self.batch_size} >= 1")
        if self.crop < 0:
            raise ConfigError(f"crop={self.crop} must be >= 0 (0 = whole images)")
        lo, hi = self.scale_range
        if not 0 < lo <= hi:
            raise ConfigError(f"scale_range={self.scale_range} must satisfy 0 < low <= high")


# ============================================================================ the network
def _block(cin: int, cout: int, groups: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.GroupNorm(groups, cout), nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.GroupNorm(groups, cout), nn.ReLU(inplace=True),
    )


class Segmenter(nn.Module):
    """A compact U-Net: images float [B, 3, H, W] in [0, 1] (sRGB) -> logits float [B, 7, H, W] (``[B, 8, H, W]``
    with a metal channel: the 7 class logits, then the metal-mask logit; :meth:`split` separates them).

    Encoder: per level two 3x3 conv + GroupNorm + ReLU, 2x2 max-pooling between levels (rounding up, so any H, W
    works). Decoder (light, FPN-like, to keep CPU training to about a minute): a 1x1 projection of the coarser
    features, bilinear upsampling to the skip's size, addition of the skip, one 3x3 conv + GroupNorm + ReLU.
    GroupNorm instead of BatchNorm, so eval equals training behaviour and the ONNX graph has no running buffers.

    Example:
        >>> net = Segmenter()
        >>> net(torch.rand(2, 3, 37, 50)).shape
        torch.Size([2, 7, 37, 50])
    """

    def __init__(self, cfg: SegmenterConfig = SegmenterConfig()):
        super().__init__()
        self.cfg = cfg
        w, g = cfg.widths, cfg.groups
        self.encoders = nn.ModuleList([_block(3 if i == 0 else w[i - 1], w[i], g) for i in range(len(w))])
        self.laterals = nn.ModuleList([nn.Conv2d(w[i + 1], w[i], 1) for i in reversed(range(len(w) - 1))])
        self.decoders = nn.ModuleList([
            nn.Sequential(nn.Conv2d(w[i], w[i], 3, padding=1, bias=False), nn.GroupNorm(g, w[i]), nn.ReLU(inplace=True))
            for i in reversed(range(len(w) - 1))])
        self.head = nn.Conv2d(w[0], cfg.num_classes + int(cfg.metal), 1)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = images * 2.0 - 1.0
        skips = []
        for i, enc in enumerate(self.encoders):
            if i > 0:
                x = F.max_pool2d(x, 2, ceil_mode=True)
            x = enc(x)
            skips.append(x)
        skips.pop()
        for lateral, dec in zip(self.laterals, self.decoders):
            skip = skips.pop()
            x = F.interpolate(lateral(x), size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = dec(x + skip)
        return self.head(x)

    def split(self, logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(class logits [B, 7, H, W], metal logit [B, H, W] or None) of :meth:`forward`'s output."""
        C = self.cfg.num_classes
        return logits[:, :C], (logits[:, C] if self.cfg.metal else None)

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())


def work_resolution(H: int, W: int, work_size: int) -> tuple[int, int]:
    """(h, w) a photo of H x W is resized to so its short side is ``work_size`` (aspect kept; 0: unchanged)."""
    if work_size <= 0 or min(H, W) == work_size:
        return H, W
    s = work_size / min(H, W)
    return max(1, round(H * s)), max(1, round(W * s))


class SegmenterExport(nn.Module):
    """The ONNX face of a :class:`Segmenter`: images -> (``logits`` [B, 7, H, W], ``metal`` [B, 1, H, W] probability
    of metal); without a metal channel only ``logits``."""

    def __init__(self, net: Segmenter):
        super().__init__()
        self.net = net

    def forward(self, images: torch.Tensor):
        logits, metal = self.net.split(self.net(images))
        return logits if metal is None else (logits, torch.sigmoid(metal)[:, None])


# ============================================================================ metrics and validation
def mean_iou(pred, target, num_classes: int = NUM_CLASSES, ignore: int = IGNORE_INDEX) -> tuple[float, list[float]]:
    """Mean intersection-over-union over classes.

    Pixels whose target is ``ignore`` are skipped; a predicted ``ignore`` (or any id outside 0..C-1) on a labelled
    pixel counts as a miss of the target class. A class absent from both prediction and target (over all pixels
    given) has IoU ``nan`` and is left out of the mean.

    Args:
        pred: int array/tensor of predicted ids, any shape (e.g. [B, H, W]).
        target: int array/tensor of the same shape.
        num_classes: C.
        ignore: label of pixels to skip.

    Returns:
        (mIoU, per-class IoU list of length C); mIoU is ``nan`` if no class occurs at all.

    Example:
        >>> mean_iou(torch.tensor([0, 0, 1, 1]), torch.tensor([0, 1, 1, 255]), num_classes=2)
        (0.5, [0.5, 0.5])
    """
    p = np.asarray(pred.detach().cpu() if isinstance(pred, torch.Tensor) else pred).astype(np.int64).ravel()
    t = np.asarray(target.detach().cpu() if isinstance(target, torch.Tensor) else target).astype(np.int64).ravel()
    if p.shape != t.shape:
        raise ShapeError(f"mean_iou: prediction has {p.size} pixels, target {t.size}")
    keep = t != ignore
    p, t = p[keep], t[keep]
    valid_t = (t >= 0) & (t < num_classes)
    p, t = p[valid_t], t[valid_t]
    p = np.where((p >= 0) & (p < num_classes), p, num_classes)  # an extra "none" column
    conf = np.bincount(t * (num_classes + 1) + p, minlength=num_classes * (num_classes + 1)).reshape(
        num_classes, num_classes + 1)
    tp = np.diag(conf[:, :num_classes]).astype(np.float64)
    fn = conf.sum(1) - tp
    fp = conf[:, :num_classes].sum(0) - tp
    denom = tp + fp + fn
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(denom > 0, tp / np.maximum(denom, 1), np.nan)
    miou = float(np.nanmean(iou)) if np.isfinite(iou).any() else float("nan")
    return miou, [float(v) for v in iou]


def metal_iou(pred, target, labels=None, ignore: int = IGNORE_INDEX) -> float | None:
    """IoU of a predicted metal mask against the true one (bool, any equal shapes), skipping pixels whose ``labels``
    are ``ignore`` when given; None when neither mask has a metal pixel."""
    p = torch.as_tensor(pred).bool().flatten()
    t = torch.as_tensor(target).bool().flatten()
    if p.shape != t.shape:
        raise ShapeError(f"metal_iou: prediction has {p.numel()} pixels, target {t.numel()}")
    if labels is not None:
        keep = torch.as_tensor(labels).flatten() != ignore
        p, t = p[keep], t[keep]
    union = int((p | t).sum())
    return None if union == 0 else int((p & t).sum()) / union


def validate_labels(labels: torch.Tensor, shape: tuple[int, int, int] | None = None, name: str = "labels") -> torch.Tensor:
    """Check int [B, H, W] labels hold only 0-6 and 255; returns them as int64.

    Raises:
        SegmentationError: wrong shape or dtype, or unknown ids (listed).
    """
    if not isinstance(labels, torch.Tensor):
        labels = torch.as_tensor(np.asarray(labels))
    if labels.ndim != 3 or (shape is not None and tuple(labels.shape) != tuple(shape)):
        raise SegmentationError(f"{name}: expected shape {list(shape) if shape else '[B, H, W]'}, got {list(labels.shape)}")
    if labels.is_floating_point() or labels.dtype == torch.bool:
        raise SegmentationError(f"{name}: expected integer class ids, got {labels.dtype}")
    labels = labels.long()
    ok = ((labels >= 0) & (labels < NUM_CLASSES)) | (labels == IGNORE_INDEX)
    if labels.numel() and not bool(ok.all()):
        bad = torch.unique(labels[~ok])[:10].tolist()
        raise SegmentationError(f"{name} contain unknown class ids {bad}: valid ids are 0-6 and 255 (unlabelled)")
    return labels


def _one_hot(labels: torch.Tensor, dtype) -> torch.Tensor:
    valid = labels != IGNORE_INDEX
    oh = F.one_hot(labels.clamp(0, NUM_CLASSES - 1), NUM_CLASSES).permute(0, 3, 1, 2).to(dtype)
    return oh * valid[:, None].to(dtype)


# ============================================================================ training
def _gaussian_blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    r = max(1, int(math.ceil(2.5 * sigma)))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=img.dtype) / sigma) ** 2)
    k = (k / k.sum()).view(1, 1, 1, -1).expand(3, 1, 1, -1)
    x = F.pad(img[None], (r, r, 0, 0), mode="replicate")
    x = F.conv2d(x, k, groups=3)
    x = F.pad(x, (0, 0, r, r), mode="replicate")
    return F.conv2d(x, k.transpose(-1, -2), groups=3)[0]


def _jpeg(img: torch.Tensor, quality: int) -> torch.Tensor:
    import cv2

    u8 = (img.permute(1, 2, 0).clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()[..., ::-1]
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(u8), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        return img
    dec = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]
    return torch.from_numpy(np.ascontiguousarray(dec)).permute(2, 0, 1).to(img.dtype) / 255.0


def _photometric(img: torch.Tensor, cfg: TrainSegmenterConfig, g: torch.Generator) -> torch.Tensor:
    """Camera effects a user's photos have and renders lack: exposure, blur, sensor noise, JPEG."""
    from .io import linear_to_srgb, srgb_to_linear

    u = lambda: float(torch.rand(1, generator=g))  # noqa: E731
    if cfg.exposure_stops > 0:
        k = 2.0 ** ((2 * u() - 1) * cfg.exposure_stops)
        img = linear_to_srgb((srgb_to_linear(img) * k).clamp(0, 1))
    if cfg.blur > 0 and u() < 1 / 3:
        img = _gaussian_blur(img, 0.3 + u() * max(cfg.blur - 0.3, 0.0))
    if cfg.noise > 0:
        sd = u() * cfg.noise
        img = img + sd * torch.randn(img.shape, generator=g, dtype=img.dtype)
    img = img.clamp(0, 1)
    if cfg.jpeg > 0 and u() < 1 / 3:
        img = _jpeg(img, cfg.jpeg + int(u() * max(95 - cfg.jpeg, 0)))
    return img


def _augment(img: torch.Tensor, lab: torch.Tensor, cfg: TrainSegmenterConfig, g: torch.Generator,
             metal: torch.Tensor | None = None):
    """One augmented crop: img float [3, H, W], lab int64 [H, W] (metal int64 [H, W], 255 unlabelled, or None)
    -> the same at crop size."""
    _, H, W = img.shape
    maps = lab[None] if metal is None else torch.stack([lab, metal])
    lo, hi = cfg.scale_range
    s = math.exp(float(torch.empty(1).uniform_(math.log(lo), math.log(hi), generator=g)))
    if abs(s - 1.0) > 1e-3:
        nh, nw = max(8, round(H * s)), max(8, round(W * s))
        img = F.interpolate(img[None], size=(nh, nw), mode="bilinear", align_corners=False, antialias=s < 1)[0]
        maps = F.interpolate(maps[None].float(), size=(nh, nw), mode="nearest")[0].long()
        H, W = nh, nw
    if cfg.crop:
        c = cfg.crop
        if H < c or W < c:  # pad with ignore so every crop has the same size
            ph, pw = max(0, c - H), max(0, c - W)
            img = F.pad(img, (0, pw, 0, ph), value=0.0)
            maps = F.pad(maps, (0, pw, 0, ph), value=IGNORE_INDEX)
            H, W = img.shape[-2:]
        y = int(torch.randint(0, H - c + 1, (1,), generator=g))
        x = int(torch.randint(0, W - c + 1, (1,), generator=g))
        img, maps = img[:, y:y + c, x:x + c], maps[:, y:y + c, x:x + c]
    if cfg.hflip and float(torch.rand(1, generator=g)) < 0.5:
        img, maps = img.flip(-1), maps.flip(-1)
    j = cfg.colour_jitter
    if j > 0:
        r = lambda: 1.0 + j * (2 * float(torch.rand(1, generator=g)) - 1)  # noqa: E731
        gains = torch.tensor([r() * 0.5 + 0.5 for _ in range(3)], dtype=img.dtype).view(3, 1, 1)
        img = img * r() * gains  # brightness and white balance
        mean = img.mean()
        img = (img - mean) * r() + mean  # contrast
        grey = img.mean(0, keepdim=True)
        img = (img - grey) * r() + grey  # saturation
        img = img.clamp(0, 1)
    img = _photometric(img, cfg, g)
    return img, maps[0], (maps[1] if metal is not None else None)


def train_segmenter(
    images: torch.Tensor,
    labels: torch.Tensor,
    cfg: TrainSegmenterConfig = TrainSegmenterConfig(),
    model: Segmenter | None = None,
    metal: torch.Tensor | None = None,
) -> "SegmenterTraining":
    """Train :class:`Segmenter` on labelled views with cross-entropy (``ignore_index=255``), plus the binary
    cross-entropy of the metal mask (weight ``cfg.metal_weight``) when the network has a metal channel and ``metal``
    is given.

    Seeded and CPU-friendly: random rescaled crops, horizontal flips and colour jitter; AdamW with a one-cycle
    learning rate. Runs on ``images.device``.

    Args:
        images: float [N, 3, H, W] in [0, 1] (sRGB photos as loaded).
        labels: int [N, H, W] class ids 0-6, 255 unlabelled (skipped by the loss).
        cfg: :class:`TrainSegmenterConfig`.
        model: continue training this network instead of a fresh one (fine-tuning, e.g. the shipped network).
        metal: bool [N, H, W] metal masks (ground truth of the training views), or None.

    Returns:
        :class:`SegmenterTraining` with the model (in eval mode), the loss per step and the training mIoU.

    Raises:
        ShapeError / SegmentationError: shapes disagree, labels hold unknown ids or no pixel is labelled.
    """
    dims = check_shape(images, "N 3 H W", name="images")
    labels = validate_labels(labels.to(images.device), (dims["N"], dims["H"], dims["W"]))
    if dims["N"] == 0 or not bool((labels != IGNORE_INDEX).any()):
        raise SegmentationError("train_segmenter needs at least one labelled pixel (labels are all 255 or empty)")
    torch.manual_seed(cfg.seed)
    g = torch.Generator().manual_seed(cfg.seed)
    device = images.device
    net = (model or Segmenter(cfg.arch)).to(device).train()
    counts = torch.bincount(labels[labels != IGNORE_INDEX].flatten(), minlength=NUM_CLASSES).double()
    if cfg.class_balance:
        freq = counts / counts.sum()
        w = torch.where(counts > 0, 1.0 / freq.clamp_min(1e-8).sqrt(), torch.zeros_like(freq))
        w = w / (w * freq).sum()  # mean weight over pixels = 1
        weight = w.float().to(device)
    else:
        weight = None
    if net.cfg.work_size > 0 and cfg.crop:  # train at the scale photos are segmented at (work_size on the short side)
        k = net.cfg.work_size / min(dims["H"], dims["W"])
        cfg = replace(cfg, scale_range=(cfg.scale_range[0] * k, cfg.scale_range[1] * k))
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=cfg.lr, total_steps=max(cfg.steps, 1), pct_start=0.15)
    imgs_cpu, labs_cpu = images.detach().float().cpu(), labels.cpu()
    use_metal = metal is not None and net.cfg.metal and cfg.metal_weight > 0
    if use_metal:
        check_shape(metal, f"{dims['N']} {dims['H']} {dims['W']}", name="metal")
        metal_cpu = torch.where(labs_cpu == IGNORE_INDEX, torch.full_like(labs_cpu, IGNORE_INDEX),
                                metal.cpu().long().clamp(0, 1))
        # metal is rare (a few % of pixels): weight positives by sqrt(negatives / positives), as the classes
        pos = float((metal_cpu == 1).sum())
        neg = float((metal_cpu == 0).sum())
        pos_weight = torch.tensor(math.sqrt(neg / pos) if pos > 0 and neg > 0 else 1.0, device=device)
    losses: list[float] = []
    t0 = time.time()
    steps = range(cfg.steps)
    if cfg.progress:
        import sys

        from tqdm import tqdm

        steps = tqdm(steps, desc="train segmenter", file=sys.stderr, leave=False)
    for _ in steps:
        idx = torch.randint(0, dims["N"], (cfg.batch_size,), generator=g)
        pairs = [_augment(imgs_cpu[i], labs_cpu[i], cfg, g, metal_cpu[i] if use_metal else None)
                 for i in idx.tolist()]
        x = torch.stack([p[0] for p in pairs]).to(device)
        y = torch.stack([p[1] for p in pairs]).to(device)
        if not bool((y != IGNORE_INDEX).any()):
            continue
        logits, metal_logit = net.split(net(x))
        loss = F.cross_entropy(logits, y, weight=weight, ignore_index=IGNORE_INDEX)
        if use_metal:
            m = torch.stack([p[2] for p in pairs]).to(device)
            keep = m != IGNORE_INDEX
            if bool(keep.any()):
                loss = loss + cfg.metal_weight * F.binary_cross_entropy_with_logits(metal_logit[keep], m[keep].float(),
                                                                                    pos_weight=pos_weight)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
        if cfg.progress:
            steps.set_postfix(loss=f"{losses[-1]:.3f}")
    net.eval()
    with torch.no_grad():
        pred = _predict_builtin(net, images, 8)[0]
    miou, _ = mean_iou(pred, labels)
    return SegmenterTraining(model=net, losses=losses, train_miou=miou, seconds=time.time() - t0,
                             class_pixels=counts.long().tolist())


@dataclass(frozen=True)
class SegmenterTraining:
    """Result of :func:`train_segmenter`.

    Attributes:
        model: the trained :class:`Segmenter` (eval mode).
        losses: cross-entropy per step.
        train_miou: mIoU of its predictions on the training views.
        seconds: wall-clock training time.
        class_pixels: labelled training pixels per class.
    """

    model: Segmenter
    losses: list[float]
    train_miou: float
    seconds: float
    class_pixels: list[int]


# ============================================================================ inference backends
def _to_work_size(x: torch.Tensor, work_size: int) -> torch.Tensor:
    H, W = x.shape[-2:]
    h, w = work_resolution(H, W, work_size)
    if (h, w) == (H, W):
        return x
    return F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=h < H)


def _predict_builtin(model: nn.Module, images: torch.Tensor, batch_size: int
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """(labels int64 [B, H, W], probabilities [B, 7, H, W], metal probability [B, H, W] or None)."""
    was = model.training
    model.eval()
    labs, probs, metals = [], [], []
    H, W = images.shape[-2:]
    cfg = getattr(model, "cfg", None)
    work = int(getattr(cfg, "work_size", 0) or 0)
    has_metal = bool(getattr(cfg, "metal", False))
    try:
        p = next(iter(model.parameters()), None)
        device = p.device if p is not None else images.device
        with torch.no_grad():
            for s in range(0, images.shape[0], batch_size):
                x = _to_work_size(images[s:s + batch_size].to(device).float(), work)
                out = model(x)
                want = NUM_CLASSES + int(has_metal)
                if out.ndim != 4 or out.shape[1] != want or out.shape[-2:] != x.shape[-2:]:
                    raise SegmentationError(f"the builtin model returned shape {list(out.shape)}; expected "
                                            f"[B, {want}, {x.shape[-2]}, {x.shape[-1]}]")
                # logits and the metal probability (as the ONNX graph gives them) back at the photo's size
                logits, metal = out[:, :NUM_CLASSES], (torch.sigmoid(out[:, NUM_CLASSES:]) if has_metal else None)
                if out.shape[-2:] != (H, W):
                    logits = F.interpolate(logits, size=(H, W), mode="bilinear", align_corners=False)
                    metal = None if metal is None else F.interpolate(metal, size=(H, W), mode="bilinear",
                                                                     align_corners=False)
                pr = logits.softmax(1)
                probs.append(pr.to(images.device, images.dtype))
                labs.append(pr.max(1).indices.to(images.device))  # max's indices: ~8x faster than argmax(1) on CPU
                if has_metal:
                    metals.append(metal[:, 0].to(images.device, images.dtype))
    finally:
        model.train(was)
    if not labs:
        return (torch.zeros(0, H, W, dtype=torch.long, device=images.device),
                torch.zeros(0, NUM_CLASSES, H, W, dtype=images.dtype, device=images.device),
                torch.zeros(0, H, W, dtype=images.dtype, device=images.device) if has_metal else None)
    return torch.cat(labs), torch.cat(probs), (torch.cat(metals) if has_metal else None)


def _onnx_session(model):
    import onnxruntime as ort

    if isinstance(model, ort.InferenceSession):
        return model, "<session>", {}
    path = Path(model)
    if not path.is_file():
        raise SegmentationError(f"ONNX segmenter not found: {path}")
    try:
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own types
        raise SegmentationError(f"ONNX Runtime could not load {path}: {e}") from e
    meta = dict(sess.get_modelmeta().custom_metadata_map or {})
    return sess, str(path), meta


def _predict_onnx(model, images: torch.Tensor, batch_size: int
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    sess, where, meta = _onnx_session(model)
    if not isinstance(model, (str, os.PathLike)):
        meta = dict(sess.get_modelmeta().custom_metadata_map or {})
    ins, outs = sess.get_inputs(), sess.get_outputs()
    contract = ("expected one float32 input N x 3 x H x W (RGB in [0, 1]) and a first output of logits N x 7 x h x w "
                "or int labels N x h x w")
    if len(ins) != 1:
        raise SegmentationError(f"{where}: the model has {len(ins)} inputs {[i.name for i in ins]}; {contract}")
    inp = ins[0]
    shape = list(inp.shape)
    if len(shape) != 4 or (isinstance(shape[1], int) and shape[1] != 3):
        raise SegmentationError(f"{where}: input '{inp.name}' has shape {shape}; {contract}")
    if inp.type not in ("tensor(float)", "tensor(float16)"):
        raise SegmentationError(f"{where}: input '{inp.name}' is {inp.type}; {contract}")
    np_dtype = np.float16 if inp.type == "tensor(float16)" else np.float32
    norm = meta.get("dars.normalize", "none").lower()
    if norm not in ("none", "imagenet"):
        raise SegmentationError(f"{where}: metadata dars.normalize={norm!r} is not 'none' or 'imagenet'")
    B, _, H, W = images.shape
    fixed_hw = (shape[2], shape[3]) if isinstance(shape[2], int) and isinstance(shape[3], int) else None
    step = 1 if isinstance(shape[0], int) else batch_size
    try:
        work = int(meta.get("dars.work_size", "0"))
    except ValueError:
        raise SegmentationError(f"{where}: metadata dars.work_size={meta.get('dars.work_size')!r} is not an integer")
    metal_out = next((o.name for o in outs[1:] if o.name == "metal"), None)
    metals = []
    if isinstance(shape[0], int) and shape[0] != 1:
        raise SegmentationError(f"{where}: input batch is fixed to {shape[0]}; use a dynamic batch or 1")
    labs, probs = [], []
    for s in range(0, B, step):
        x = images[s:s + step].detach().float().cpu()
        if fixed_hw is not None and fixed_hw != (H, W):
            x = F.interpolate(x, size=fixed_hw, mode="bilinear", align_corners=False,
                              antialias=fixed_hw[0] < H or fixed_hw[1] < W)
        elif fixed_hw is None and work > 0:
            x = _to_work_size(x, work)
        if norm == "imagenet":
            x = (x - torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)) / torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
        try:
            res = sess.run([outs[0].name] + ([metal_out] if metal_out else []), {inp.name: x.numpy().astype(np_dtype)})
            out = res[0]
        except Exception as e:  # onnxruntime's own types
            raise SegmentationError(f"{where}: ONNX Runtime failed on input {list(x.shape)}: {e}") from e
        n = x.shape[0]
        if metal_out:
            m = torch.from_numpy(np.asarray(res[1], dtype=np.float32)).reshape(n, 1, *res[1].shape[-2:])
            if m.shape[-2:] != (H, W):
                m = F.interpolate(m, size=(H, W), mode="bilinear", align_corners=False)
            metals.append(m[:, 0])
        if out.ndim == 4:
            if out.shape[0] != n or out.shape[1] != NUM_CLASSES:
                raise SegmentationError(f"{where}: output '{outs[0].name}' has shape {list(out.shape)}; expected "
                                        f"logits [{n}, {NUM_CLASSES}, h, w] ({contract})")
            if not np.issubdtype(out.dtype, np.floating):
                raise SegmentationError(f"{where}: 4-D output '{outs[0].name}' must be float logits, got {out.dtype}")
            logits = torch.from_numpy(out.astype(np.float32))
            if logits.shape[-2:] != (H, W):
                logits = F.interpolate(logits, size=(H, W), mode="bilinear", align_corners=False)
            pr = logits.softmax(1)
            probs.append(pr)
            labs.append(pr.max(1).indices)
        elif out.ndim == 3:
            if out.shape[0] != n or not np.issubdtype(out.dtype, np.integer):
                raise SegmentationError(f"{where}: output '{outs[0].name}' has shape {list(out.shape)} and type "
                                        f"{out.dtype}; 3-D outputs must be int labels [{n}, h, w] ({contract})")
            lab = torch.from_numpy(out.astype(np.int64))
            if lab.shape[-2:] != (H, W):
                lab = F.interpolate(lab[:, None].float(), size=(H, W), mode="nearest")[:, 0].long()
            lab = validate_labels(lab, name=f"labels from {where}")
            labs.append(lab)
            probs.append(_one_hot(lab, torch.float32))
        else:
            raise SegmentationError(f"{where}: output '{outs[0].name}' has shape {list(out.shape)}; {contract}")
    if not labs:
        return (torch.zeros(0, H, W, dtype=torch.long, device=images.device),
                torch.zeros(0, NUM_CLASSES, H, W, dtype=images.dtype, device=images.device), None)
    metal = torch.cat(metals).to(images.device, images.dtype) if metal_out else None
    return torch.cat(labs).to(images.device), torch.cat(probs).to(images.device, images.dtype), metal


def segment_images(
    images: torch.Tensor,
    cfg: SegmentConfig = SegmentConfig(),
    labels: torch.Tensor | None = None,
    model: "Segmenter | str | os.PathLike | None" = None,
) -> Segmentation:
    """Label every pixel with one of the 7 SPEC classes.

    Args:
        images: float [B, 3, H, W] in [0, 1] (sRGB photos as loaded).
        cfg: backend choice (:class:`SegmentConfig`).
        labels: int [B, H, W] scene labels (``provided`` backend only).
        model: a :class:`Segmenter` (``builtin``) or an ONNX file path / ``onnxruntime.InferenceSession``
            (``onnx``; else ``cfg.onnx_path``).

    Returns:
        :class:`Segmentation` (labels int64 [B, H, W], probabilities [B, 7, H, W]) on the images' device.

    Raises:
        SegmentationError: missing labels/model, unknown label ids, or an ONNX model outside the contract.
        ShapeError: images are not [B, 3, H, W].

    Example:
        >>> seg = segment_images(torch.rand(1, 3, 8, 8), labels=torch.full((1, 8, 8), 4))
        >>> seg.labels.unique().tolist(), seg.probabilities[0, 4].mean().item()
        ([4], 1.0)
    """
    dims = check_shape(images, "B 3 H W", name="images")
    if not images.is_floating_point():
        raise ShapeError(f"images: expected a floating tensor in [0, 1], got {images.dtype}")
    shape = (dims["B"], dims["H"], dims["W"])
    if cfg.backend == "provided":
        if labels is None:
            raise SegmentationError("backend 'provided' needs the scene's labels (semantic_path in the transforms "
                                    "file); without them use backend 'builtin' or 'onnx'")
        lab = validate_labels(labels, shape).to(images.device)
        return Segmentation(labels=lab, probabilities=_one_hot(lab, images.dtype), backend="provided")
    if cfg.backend == "builtin":
        if model is None or not isinstance(model, nn.Module):
            raise SegmentationError("backend 'builtin' needs a trained Segmenter: train_segmenter(...) or "
                                    "load_segmenter(path)")
        lab, prob, metal = _predict_builtin(model, images, cfg.batch_size)
        return Segmentation(labels=lab, probabilities=prob, backend="builtin", metal=metal)
    model = model if model is not None else cfg.onnx_path
    if model is None:
        raise SegmentationError("backend 'onnx' needs a model file (model=... or SegmentConfig(onnx_path=...))")
    lab, prob, metal = _predict_onnx(model, images, cfg.batch_size)
    return Segmentation(labels=lab, probabilities=prob, backend="onnx", metal=metal)


# ============================================================================ the scene's own class prior
SCENE_PRIOR_FLOOR = 0.03
"""Lowest scene prior :func:`estimate_scene_prior` gives a class, as a fraction of its training prior. 0 lets EM
remove a class the network sees only faintly (its false positives, e.g. a display case in a room without one, but
also a real frame seen at 0.1 % of the pixels); 0.03 was chosen on 40 procedural galleries the segmenter never saw
(prior seeds 109-116 and 200-231) before the validation galleries were scored (README, "Priors")."""


METAL_THRESHOLD = 0.7
"""A pixel is metal where the segmenter's metal probability exceeds this. The metal channel is trained with its
positives weighted up (metal is a few % of the pixels), so its probabilities run high and 0.5 gives too much metal.
0.7 was chosen on 40 procedural galleries the shipped segmenter never saw (walls profile, seeds 400-439: pooled metal
IoU 0.353 at 0.5, 0.379 at 0.6, 0.398 at 0.7, 0.389 at 0.8) and then checked on three other unseen sets, pooled
IoU at 0.5 → 0.7: walls 440-479 0.313 → 0.368, prior 300-315 0.311 → 0.371, the 8 validation galleries 0.353 →
0.390 (README, "A metal threshold chosen on unseen rooms")."""


SCENE_PRIOR_CEILING = 2.0
"""Highest scene prior :func:`estimate_scene_prior` gives a class, as a multiple of its training prior. Without one,
EM on a real capture the network barely understands (the fox: floral wallpaper it reads as painting) pushed one
class to 96 % of the scene and labelled every pixel with it; with 2 the fox's labels stay as the network drew them.
On the 40 procedural tuning galleries a ceiling of 2, 3, 4 or none scores the same (mIoU 0.663 mean)."""


def train_class_prior(class_pixels, class_balance: bool = True) -> torch.Tensor:
    """The class prior a network trained by :func:`train_segmenter` carries: float64 [7], sums to 1.

    Its weighted cross-entropy (weights ∝ 1/√frequency when ``class_balance``) is the plain cross-entropy of a data
    set whose class frequencies are ``frequency x weight ∝ √frequency``: that, normalised, is the prior its softmax
    answers under. Without class balance it is the frequency itself. A class with no pixel gets 1e-4.
    """
    c = torch.as_tensor(class_pixels, dtype=torch.float64).flatten()
    if c.numel() != NUM_CLASSES or bool((c < 0).any()) or float(c.sum()) <= 0:
        raise SegmentationError(f"class_pixels must be {NUM_CLASSES} non-negative counts, not all zero; got "
                                f"{c.tolist()}")
    f = c / c.sum()
    p = f.sqrt() if class_balance else f
    p = (p / p.sum()).clamp_min(1e-4)  # a class the training set lacked: a tiny prior, not 0 (EM divides by it)
    return p / p.sum()


def estimate_scene_prior(probabilities: torch.Tensor, train_prior: torch.Tensor, floor: float = SCENE_PRIOR_FLOOR,
                         ceiling: float = SCENE_PRIOR_CEILING, iters: int = 200, tol: float = 1e-7) -> torch.Tensor:
    """The scene's class prior from the network's per-pixel probabilities, by EM (Saerens, Latinne & Decaestecker,
    "Adjusting the outputs of a classifier to new a priori probabilities", Neural Computation 2002).

    A segmenter's softmax answers under the class prior of its training set (:func:`train_class_prior`). One
    scene's views share one prior that differs from it: a room without a display case has none. EM alternates
    ``q(c | x) ∝ p(c | x) π(c) / π_t(c)`` and ``π(c) = mean_x q(c | x)``, starting at ``π = π_t``; here each
    ``π(c)`` is kept within ``[floor, ceiling] · π_t(c)`` (then renormalised): a small class the network is sure of
    survives, and on photos unlike its training set (a real capture) a class it leans to everywhere cannot swallow
    the scene.

    Args:
        probabilities: float [N, 7] the network's class probabilities at N pixels of the scene's photos (a
            subsample is enough).
        train_prior: float [7] π_t.
        floor, ceiling: see above (0 and inf: plain EM).
        iters, tol: EM stops after ``iters`` rounds or when π moves by less than ``tol``.

    Returns:
        float64 [7] π, sums to 1. Relabel with :func:`apply_scene_prior`.
    """
    check_shape(probabilities, f"N {NUM_CLASSES}", name="probabilities")
    if not 0.0 <= floor <= 1.0 or not ceiling >= 1.0:
        raise ConfigError(f"floor={floor} must be in [0, 1] and ceiling={ceiling} >= 1")
    P = probabilities.double()
    pt = torch.as_tensor(train_prior, dtype=torch.float64).flatten()
    if pt.numel() != NUM_CLASSES or bool((pt <= 0).any()):
        raise SegmentationError(f"train_prior must be {NUM_CLASSES} positive values, got {pt.tolist()}")
    pt = pt / pt.sum()
    if P.shape[0] == 0:
        return pt.clone()
    pi = pt.clone()
    for _ in range(iters):
        q = P * (pi / pt)
        q = q / q.sum(1, keepdim=True).clamp_min(1e-300)
        new = _clip_simplex(q.mean(0), floor * pt, ceiling * pt)
        done = float((new - pi).abs().max()) < tol
        pi = new
        if done:
            break
    return pi


def segmenter_train_prior(net) -> torch.Tensor | None:
    """The training class prior (:func:`train_class_prior`) a network records in ``net.meta`` (``class_pixels`` and
    ``class_balance``, stored with its weights by ``bench/bench_segmenter.py`` and ``dars priors segment --backend
    builtin``), or None when it records none."""
    meta = getattr(net, "meta", None) or {}
    if meta.get("class_pixels") is None:
        return None
    return train_class_prior(meta["class_pixels"], bool(meta.get("class_balance", True)))


def _clip_simplex(v: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """``clip(t · v, lo, hi)`` with the scale t > 0 that makes it sum to 1 (bisection; the sum grows with t), so
    every entry ends inside its bounds (needs Σ lo ≤ 1 ≤ Σ hi)."""
    a, b = 0.0, 1.0
    while float(torch.clamp(b * v, lo, hi).sum()) < 1.0 and b < 1e12:
        b *= 2.0
    for _ in range(60):
        t = 0.5 * (a + b)
        a, b = (t, b) if float(torch.clamp(t * v, lo, hi).sum()) < 1.0 else (a, t)
    out = torch.clamp(b * v, lo, hi)
    return out / out.sum()


def apply_scene_prior(probabilities: torch.Tensor, scene_prior: torch.Tensor, train_prior: torch.Tensor) -> torch.Tensor:
    """Probabilities [B, 7, H, W] re-weighted by ``scene_prior / train_prior`` and renormalised (argmax: the labels)."""
    check_shape(probabilities, f"B {NUM_CLASSES} H W", name="probabilities")
    w = (torch.as_tensor(scene_prior, dtype=torch.float64) / torch.as_tensor(train_prior, dtype=torch.float64))
    q = probabilities * w.to(probabilities).view(1, -1, 1, 1)
    return q / q.sum(1, keepdim=True).clamp_min(1e-30)


# ============================================================================ persistence
def save_segmenter(path: str | os.PathLike, model: Segmenter, extra: dict | None = None) -> Path:
    """Write a :class:`Segmenter` (architecture + weights + ``extra`` JSON-able info) atomically.

    Returns:
        the path written.
    """
    if not isinstance(model, Segmenter):
        raise SegmentationError(f"save_segmenter expects a Segmenter, got {type(model).__name__}")
    payload = {
        "format": _FORMAT,
        "version": 1,
        "arch": {"widths": list(model.cfg.widths), "groups": model.cfg.groups, "num_classes": model.cfg.num_classes,
                 "metal": model.cfg.metal, "work_size": model.cfg.work_size},
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "extra": dict(extra or {}),
    }
    return save_torch(path, payload)


def load_segmenter(path: str | os.PathLike | None = None, map_location: str | torch.device = "cpu") -> Segmenter:
    """Read a file written by :func:`save_segmenter` (default: the shipped :data:`DEFAULT_SEGMENTER`); returns the
    network in eval mode. ``net.meta`` holds the ``extra`` stored with it.

    Raises:
        SegmentationError: missing file, not a segmenter file, or weights that do not fit the architecture.
    """
    shipped = path is None
    path = Path(path).expanduser() if path is not None else DEFAULT_SEGMENTER
    if not path.is_file():
        if shipped:
            raise SegmentationError(f"the shipped segmenter {path} is missing from this installation; reinstall dars "
                                    "or pass a trained segmenter.pt")
        raise SegmentationError(f"segmenter file not found: {path}")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:
        raise SegmentationError(f"{path} is not a readable segmenter file ({e})") from e
    if not isinstance(payload, dict) or payload.get("format") != _FORMAT:
        raise SegmentationError(f"{path} is not a dars segmenter file (written by save_segmenter)")
    arch = payload["arch"]
    net = Segmenter(SegmenterConfig(widths=tuple(arch["widths"]), groups=int(arch["groups"]),
                                    num_classes=int(arch["num_classes"]), metal=bool(arch.get("metal", False)),
                                    work_size=int(arch.get("work_size", 0))))
    try:
        net.load_state_dict(payload["state_dict"])
    except RuntimeError as e:
        raise SegmentationError(f"{path}: weights do not fit the stored architecture: {e}") from e
    net.meta = dict(payload.get("extra") or {}, path=str(path))
    return net.to(map_location).eval()

