"""Stage 4 — the light estimation network (paper §II.C.2, eq. 11): one photo → 27 SH coefficients of the room's light.

``l_env = FC_light(GlobalAvgPool(ResNet34(I)))``, FC 512 → 256 → 27, sigmoids mapped to a physical range, read as
``[9, 3]`` radiance SH in the SPEC convention (:mod:`toolkit.sh`): real SH order 2, incident radiance, **world
frame** (+z up), coefficient-major when flattened to 27.

Architecture (:class:`LightNet`, plain torch, no torchvision): ResNet stem (7x7/2 conv, BN, ReLU, 3x3/2 max-pool),
four stages of BasicBlocks (first block of stages 2-4 strided by 2 with a 1x1 projection), global average pool,
``Linear(width, fc_hidden) → ReLU → Linear(fc_hidden, 27)``, output mapping. Presets (:func:`lightnet_config`):

* ``resnet34`` — the paper's: blocks [3, 4, 6, 3], widths 64-128-256-512, FC 512 → 256 → 27 (21.42 M parameters;
  the trunk's layer names and shapes equal torchvision's ``resnet34``, so its ImageNet weights load into
  ``model.trunk`` with ``strict=False`` if you have them locally — nothing is downloaded).
* ``small`` — blocks [1, 1, 1, 1], widths 16-32-64-128, FC 128 → 256 → 27 (0.34 M parameters, 1.4 MB): tests and
  CPU training; the shipped weights ``toolkit/weights/lightnet_small.pt`` are this one.

Input: ``images`` float [B, 3, H, W], RGB, **sRGB-encoded** in [0, 1] (photos as :meth:`Scene.load_image` returns
them); inside the network they are normalised with the ImageNet mean/std. Any H, W works (global pooling);
:func:`predict_sh` resizes to ``cfg.input_size`` (64; area averaging in linear light when shrinking) as in training.

Output range (:func:`sh_from_logits`), per colour channel:

* DC: ``L00 = D · σ(z00)`` ∈ [0, D]. With the default ``output_range="image"``, ``D = dc_max · c / Y00`` where c is
  the input image's mean *linear* colour (computed in the graph) — ``c / Y00`` is the DC of a constant environment
  as bright as the image (baseline (b) below), so the network learns a gain in [0, dc_max] on it and its answer
  scales with the exposure like the true SH does. ``dc_max = 8``: the gain is ≈ 1/(mean albedo x fraction of the
  light that reaches visible surfaces); on the training set its 1st-99th percentiles are 0.65-24 and 96 % of views
  lie below 8 — the rest are lightings whose bright part is hidden behind the gallery wall, which no photo of the
  room can reveal. ``output_range="absolute"``: ``D = dc_max`` in the images' radiance units.
* bands l = 1, 2: ``L_lm = b_l · L00 · (2σ(z_lm) − 1)`` with ``b_l = √(2l + 1)``. This is the physical range of a
  non-negative radiance function: ``|L_lm| = |∫ L Y_lm| ≤ max|Y_lm| ∫ L`` and ``max|Y_lm| = √((2l+1)/4π) = √(2l+1)·Y00``
  (attained by Y_l0 at the poles), so every non-negative environment lies inside the range (necessary, not
  sufficient: some outputs in range still dip below zero somewhere).

Limit — the world frame: a network sees one photo from an unknown pose but must answer in world coordinates. Trained
on one room (``samples/render_lightings.py``: the gallery sample under many lightings) it reads the pose from the
picture and the DC gain from that room's albedos, and both extrapolate badly to another room. The shipped weights are
therefore trained on many procedural galleries (:func:`light_dataset_from_galleries`: rooms, albedos, lamps and probe
rotations all vary; one lighting per gallery), which trades accuracy on the sample room for generalisation; their
held-out figures per lighting source are in ``toolkit/weights/lightnet_small.json``. The trainer's alternating light
optimisation (eq. 22) refines ``l_env`` from all views either way.

Training data: rendered galleries (``samples/galleries.py``) → :func:`light_dataset_from_galleries`, or
``samples/render_lightings.py`` (Mitsuba, seeded, cached outside the repo) → :func:`load_light_dataset`;
:func:`train_lightnet` fits them (Adam, L2 on the 27 coefficients, Huber-robust per view); ``bench/bench_lightnet.py``
trains, evaluates on held-out lightings against the baselines (:func:`evaluate_lightnet`) and writes the shipped
weights with their command and figures (``toolkit/weights/lightnet_small.json``).

Example:
    >>> net = load_lightnet()                      # shipped small weights
    >>> sh = predict_sh(net, torch.rand(2, 3, 128, 128))
    >>> sh.shape
    torch.Size([2, 9, 3])
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ._checks import ConfigError, DarsError, check_shape
from .io import linear_to_srgb, save_torch, srgb_to_linear
from .segment import IMAGENET_MEAN, IMAGENET_STD
from .sh import SH_BAND_OF_K, SH_C0

__all__ = [
    "DEFAULT_WEIGHTS",
    "SH_BAND_BOUNDS",
    "LightNetError",
    "LightNetConfig",
    "lightnet_config",
    "LightNet",
    "sh_from_logits",
    "logits_from_sh",
    "camera_heading",
    "rotate_sh_heading",
    "MIRROR_Y_SIGNS",
    "LightDataset",
    "load_light_dataset",
    "gallery_dirs",
    "light_dataset_from_galleries",
    "concat_light_datasets",
    "TrainLightNetConfig",
    "LightNetHistory",
    "train_lightnet",
    "predict_sh",
    "mean_colour_sh",
    "aggregate_sh",
    "LightNetEvaluation",
    "evaluate_lightnet",
    "save_lightnet",
    "load_lightnet",
]

DEFAULT_WEIGHTS = Path(__file__).resolve().parent / "weights" / "lightnet_small.pt"
"""The shipped ``small`` weights (their training command and figures: ``lightnet_small.json`` beside them)."""

SH_BAND_BOUNDS = (1.0, math.sqrt(3.0), math.sqrt(5.0))
"""``b_l``: ``|L_lm| ≤ b_l · L00`` for any non-negative radiance (``max|Y_lm| / Y00 ≤ √(2l+1)``)."""

_FORMAT = "dars-lightnet"


class LightNetError(DarsError):
    """Missing/corrupt weights or data set, or inputs the light network cannot take."""


# ============================================================================ configuration
@dataclass(frozen=True)
class LightNetConfig:
    """Architecture of :class:`LightNet` (default: the paper's ResNet-34)."""

    name: str = "resnet34"
    """A label stored with the weights (``resnet34``, ``small`` or your own)."""
    blocks: tuple[int, int, int, int] = (3, 4, 6, 3)
    """BasicBlocks per stage."""
    widths: tuple[int, int, int, int] = (64, 128, 256, 512)
    """Channels per stage; the FC input is ``widths[-1]``."""
    fc_hidden: int = 256
    """Hidden width of the FC head (``widths[-1] → fc_hidden → 27``)."""
    dc_max: float = 8.0
    """Upper end of L00: a gain on the image's mean-colour DC (``output_range="image"``) or radiance units of the
    images (``"absolute"``); see the module docstring."""
    input_size: int = 64
    """Square size :func:`predict_sh` resizes images to (the training size)."""
    output_range: Literal["absolute", "image"] = "image"
    """``absolute``: L00 ∈ [0, dc_max]; ``image``: L00 ∈ [0, dc_max · c / Y00] with c the input image's mean
    linear colour per channel (the range follows the exposure)."""
    frame: Literal["world", "heading"] = "world"
    """``world``: the network answers in the world frame from the photo alone. ``heading``: it answers in the frame
    of the photo's heading (+x the camera's forward direction turned horizontal, +z up, +y to its left) and
    :func:`predict_sh` turns that into the world frame with the camera's pose (:func:`camera_heading`), which a photo
    cannot show."""

    def __post_init__(self):
        if len(self.blocks) != 4 or len(self.widths) != 4 or min(self.blocks) < 1 or min(self.widths) < 1:
            raise ConfigError(f"LightNetConfig: blocks {self.blocks} and widths {self.widths} need 4 positive entries")
        if self.output_range not in ("absolute", "image"):
            raise ConfigError(f"LightNetConfig: output_range={self.output_range!r}: choose 'absolute' or 'image'")
        if self.frame not in ("world", "heading"):
            raise ConfigError(f"LightNetConfig: frame={self.frame!r}: choose 'world' or 'heading'")
        if self.fc_hidden < 1 or not self.dc_max > 0 or self.input_size < 16:
            raise ConfigError(f"LightNetConfig: fc_hidden={self.fc_hidden} >= 1, dc_max={self.dc_max} > 0 and "
                              f"input_size={self.input_size} >= 16 are required")


_PRESETS = {
    "resnet34": LightNetConfig(),
    "resnet18": LightNetConfig(name="resnet18", blocks=(2, 2, 2, 2)),
    "small": LightNetConfig(name="small", blocks=(1, 1, 1, 1), widths=(16, 32, 64, 128)),
}


def lightnet_config(preset: Literal["resnet34", "resnet18", "small"] = "resnet34", **overrides: Any) -> LightNetConfig:
    """A named architecture with optional field overrides (e.g. ``lightnet_config("small", dc_max=6.0)``)."""
    if preset not in _PRESETS:
        raise ConfigError(f"unknown light-network preset {preset!r}: choose one of {sorted(_PRESETS)}")
    try:
        return replace(_PRESETS[preset], **overrides)
    except TypeError as e:
        raise ConfigError(f"lightnet_config({preset!r}): {e}") from e


# ============================================================================ network
class _BasicBlock(nn.Module):
    """Two 3x3 conv-BN layers with a residual (1x1 conv-BN projection when the shape changes); torchvision names."""

    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.downsample = (nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))
                           if stride != 1 or cin != cout else None)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return F.relu(y + (x if self.downsample is None else self.downsample(x)))


class _Trunk(nn.Module):
    """ResNet trunk up to the last stage (no pooling, no classifier)."""

    def __init__(self, cfg: LightNetConfig):
        super().__init__()
        w0 = cfg.widths[0]
        self.conv1 = nn.Conv2d(3, w0, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(w0)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        cin = w0
        for s, (n, w) in enumerate(zip(cfg.blocks, cfg.widths)):
            blocks = [_BasicBlock(cin if b == 0 else w, w, 2 if (b == 0 and s > 0) else 1) for b in range(n)]
            setattr(self, f"layer{s + 1}", nn.Sequential(*blocks))
            cin = w

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.maxpool(F.relu(self.bn1(self.conv1(x))))
        return self.layer4(self.layer3(self.layer2(self.layer1(x))))


def sh_from_logits(logits: torch.Tensor, dc_max: float | torch.Tensor) -> torch.Tensor:
    """Map 27 unconstrained outputs to SH in the physical range of the module docstring.

    Args:
        logits: float [B, 27], coefficient-major (k = 0..8, then channel).
        dc_max: upper end of L00: a float, or float [B, 3] per image and channel.

    Returns:
        float [B, 9, 3]: ``L00 = dc_max σ(z00)``, ``L_lm = b_l L00 (2σ(z_lm) − 1)`` per channel.
    """
    z = logits.reshape(logits.shape[0], 9, 3)
    if isinstance(dc_max, torch.Tensor):
        dc_max = dc_max.reshape(-1, 1, 3)
    dc = dc_max * torch.sigmoid(z[:, :1])
    bound = z.new_tensor([SH_BAND_BOUNDS[SH_BAND_OF_K[k]] for k in range(1, 9)])[:, None]
    rest = bound * dc * (2.0 * torch.sigmoid(z[:, 1:]) - 1.0)
    return torch.cat([dc, rest], 1)


def logits_from_sh(sh: torch.Tensor, dc_max: float | torch.Tensor, eps: float = 1e-4) -> torch.Tensor:
    """Inverse of :func:`sh_from_logits` (values outside the range are clamped into it): float [B, 9, 3] → [B, 27]."""
    check_shape(sh, "B 9 3", "sh")
    if isinstance(dc_max, torch.Tensor):
        dc_max = dc_max.reshape(-1, 1, 3)
    dc = (sh[:, :1] / dc_max).clamp(eps, 1 - eps)
    bound = sh.new_tensor([SH_BAND_BOUNDS[SH_BAND_OF_K[k]] for k in range(1, 9)])[:, None]
    u = (0.5 * (sh[:, 1:] / (bound * dc * dc_max) + 1.0)).clamp(eps, 1 - eps)
    return torch.logit(torch.cat([dc, u], 1)).reshape(sh.shape[0], 27)


def camera_heading(c2w: torch.Tensor) -> torch.Tensor:
    """Each camera's heading: float [N, 2] (cos ψ, sin ψ) of its forward direction turned horizontal (world +z up).

    The forward direction is ``−c2w[:, :3, 2]`` (OpenGL cameras look down −z). Its horizontal part vanishes for a
    camera looking straight up or down, so the camera's up vector, turned horizontal, is added with the sign that
    points it the same way (``f_xy − sign(f_z) u_xy``): the heading then turns smoothly through every pitch.

    Args:
        c2w: float [N, 4, 4] or [N, 3, 4] camera-to-world matrices (world +z up, as loaded scenes are).

    Returns:
        float [N, 2] unit vectors (cos ψ, sin ψ), ψ measured from world +x towards +y.
    """
    if c2w.ndim != 3 or tuple(c2w.shape[1:]) not in ((4, 4), (3, 4)):
        raise LightNetError(f"camera_heading: c2w must be [N, 4, 4] or [N, 3, 4], got {list(c2w.shape)}")
    fwd, up = -c2w[:, :3, 2], c2w[:, :3, 1]
    h = fwd[:, :2] - torch.sign(fwd[:, 2:3]) * up[:, :2]
    n = h.norm(dim=1, keepdim=True)
    if bool((n < 1e-6).any()):
        bad = int(torch.nonzero(n[:, 0] < 1e-6)[0])
        raise LightNetError(f"camera_heading: camera {bad} has no horizontal direction (a degenerate pose)")
    return h / n


def rotate_sh_heading(sh: torch.Tensor, heading: torch.Tensor, inverse: bool = False) -> torch.Tensor:
    """Rotate SH about world +z by each heading: heading frame → world frame (``inverse``: world → heading).

    The closed form of :func:`toolkit.sh.rotate_sh` for a rotation about z by ψ: the pairs (k 3, k 1) = (x, y) and
    (k 7, k 5) = (xz, yz) turn by ψ, (k 8, k 4) = (x² − y², 2xy) by 2ψ; k 0, 2 and 6 stay. Plain arithmetic
    (ONNX-traceable).

    Args:
        sh: float [B, 9, 3].
        heading: float [B, 2] (cos ψ, sin ψ) from :func:`camera_heading`.
        inverse: rotate by −ψ instead.

    Returns:
        float [B, 9, 3].
    """
    c = heading[:, 0:1]
    s = heading[:, 1:2] * (-1.0 if inverse else 1.0)
    c2, s2 = c * c - s * s, 2.0 * c * s

    def turn(a, b, cc, ss):  # (a, b): the coefficients of (cos, sin)-like basis functions
        return a * cc - b * ss, a * ss + b * cc

    x, y = turn(sh[:, 3], sh[:, 1], c, s)
    xz, yz = turn(sh[:, 7], sh[:, 5], c, s)
    d2, xy = turn(sh[:, 8], sh[:, 4], c2, s2)
    return torch.stack([sh[:, 0], y, sh[:, 2], x, xy, yz, sh[:, 6], xz, d2], dim=1)


MIRROR_Y_SIGNS = (1.0, -1.0, 1.0, 1.0, -1.0, -1.0, 1.0, 1.0, 1.0)
"""Per coefficient, its sign under the mirror y → −y (the coefficients odd in y: k 1 = y, 4 = xy, 5 = yz). In the
heading frame +y is the photo's left, so a photo flipped left-right has its heading-frame light mirrored so."""


class LightNet(nn.Module):
    """Eq. 11: ResNet trunk → global average pool → FC ``width → fc_hidden → 27`` → physical range → [B, 9, 3].

    ``forward(images, heading=None)``: images float [B, 3, H, W] sRGB in [0, 1] (any H, W ≥ 16); returns float
    [B, 9, 3] SH of incident radiance (SPEC convention) in the world frame. A ``cfg.frame == "heading"`` network
    answers in each photo's heading frame and turns that into the world frame by ``heading`` (float [B, 2],
    :func:`camera_heading`); without ``heading`` it returns the heading-frame SH (what it is trained on). A
    ``world`` network ignores ``heading``. The network is exportable to ONNX as is
    (:func:`export.onnx_light.export_lightnet_onnx`).
    """

    def __init__(self, cfg: LightNetConfig = LightNetConfig()):
        super().__init__()
        self.cfg = cfg
        self.trunk = _Trunk(cfg)
        self.head = nn.Sequential(nn.Linear(cfg.widths[-1], cfg.fc_hidden), nn.ReLU(inplace=True),
                                  nn.Linear(cfg.fc_hidden, 27))
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.meta: dict[str, Any] = {}
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
        for m in self.modules():  # zero-init the last BN of each block: every block starts as the identity
            if isinstance(m, _BasicBlock):
                nn.init.zeros_(m.bn2.weight)

    def features(self, images: torch.Tensor) -> torch.Tensor:
        """float [B, widths[-1]]: the globally pooled trunk features."""
        return self.trunk((images - self.mean) / self.std).mean(dim=(2, 3))

    def dc_range(self, images: torch.Tensor) -> torch.Tensor | float:
        """Upper end of L00: ``cfg.dc_max``, or float [B, 3] ``dc_max · c / Y00`` for ``output_range="image"``."""
        if self.cfg.output_range == "absolute":
            return self.cfg.dc_max
        c = srgb_to_linear(images).mean(dim=(2, 3)).clamp_min(1e-4)
        return self.cfg.dc_max * c / SH_C0

    def forward(self, images: torch.Tensor, heading: torch.Tensor | None = None) -> torch.Tensor:
        sh = sh_from_logits(self.head(self.features(images)), self.dc_range(images))
        if heading is not None and self.cfg.frame == "heading":
            sh = rotate_sh_heading(sh, heading.to(sh))
        return sh

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())


# ============================================================================ data
@dataclass(frozen=True)
class LightDataset:
    """Views of one room under known lightings (written by ``samples/render_lightings.py``).

    Attributes:
        radiance: float [N, 3, H, W] linear radiance, exposure applied (the camera's units).
        sh: float [N, 9, 3] ground-truth SH of the environment in the same units (SPEC convention, world frame).
        lighting: int64 [N] lighting index of each view.
        test: bool [N] held-out lightings.
        sources: per lighting, where it came from (``pisa``, ``sky``...).
        meta: what the generator recorded (command, seed...).
        heading: float [N, 2] each view's camera heading (:func:`camera_heading`), or None when the poses are
            unknown (a ``frame="heading"`` network cannot train on such data).
    """

    radiance: torch.Tensor
    sh: torch.Tensor
    lighting: torch.Tensor
    test: torch.Tensor
    sources: tuple[str, ...] = ()
    meta: dict = field(default_factory=dict)
    heading: torch.Tensor | None = None

    def __post_init__(self):
        n = check_shape(self.radiance, "N 3 H W", "radiance")["N"]
        check_shape(self.sh, f"{n} 9 3", "sh")
        if self.lighting.shape != (n,) or self.test.shape != (n,):
            raise LightNetError(f"LightDataset: lighting {list(self.lighting.shape)} and test {list(self.test.shape)} "
                                f"must both be [{n}]")
        if self.heading is not None:
            check_shape(self.heading, f"{n} 2", "heading")

    def __len__(self) -> int:
        return int(self.radiance.shape[0])

    def images(self) -> torch.Tensor:
        """float [N, 3, H, W]: the views as photos: clipped to [0, 1], sRGB-encoded (not quantised)."""
        return linear_to_srgb(self.radiance.clamp(0.0, 1.0))

    def split(self, which: Literal["train", "test"]) -> "LightDataset":
        """The training or held-out views."""
        if which not in ("train", "test"):
            raise ConfigError(f"split {which!r}: choose 'train' or 'test'")
        keep = self.test if which == "test" else ~self.test
        idx = torch.nonzero(keep).flatten()
        return LightDataset(self.radiance[idx], self.sh[idx], self.lighting[idx], self.test[idx], self.sources, self.meta,
                            None if self.heading is None else self.heading[idx])

    def source_of(self) -> list[str]:
        """Per view, the source of its lighting (``"?"`` when unknown)."""
        return [self.sources[i] if i < len(self.sources) else "?" for i in self.lighting.tolist()]


def load_light_dataset(path: str | os.PathLike) -> LightDataset:
    """Read a ``.npz`` written by ``samples/render_lightings.py`` (exposure applied to radiance and SH).

    Raises:
        LightNetError: missing or unreadable file, or missing arrays (the message says how to regenerate it).
    """
    path = Path(path).expanduser()
    hint = ("generate it with `DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 .venv/bin/python "
            "samples/render_lightings.py --seed 0 --out PATH`")
    if not path.is_file():
        raise LightNetError(f"light data set not found: {path}; {hint}")
    try:
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
    except Exception as e:
        raise LightNetError(f"{path} is not a readable .npz light data set ({e}); {hint}") from e
    missing = [k for k in ("radiance", "sh", "exposure", "lighting", "test") if k not in d]
    if missing:
        raise LightNetError(f"{path} lacks arrays {missing}; {hint}")
    k = torch.from_numpy(d["exposure"].astype(np.float32))
    rad = torch.from_numpy(d["radiance"].astype(np.float32)).permute(0, 3, 1, 2).contiguous() * k[:, None, None, None]
    meta = json.loads(str(d["meta"])) if "meta" in d else {}
    meta["path"] = str(path)
    heading = camera_heading(torch.from_numpy(d["c2w"].astype(np.float32))) if "c2w" in d else None
    return LightDataset(radiance=rad, sh=torch.from_numpy(d["sh"].astype(np.float32)) * k[:, None, None],
                        lighting=torch.from_numpy(d["lighting"].astype(np.int64)),
                        test=torch.from_numpy(d["test"].astype(bool)),
                        sources=tuple(str(s) for s in d.get("sources", [])), meta=meta, heading=heading)


def gallery_dirs(*roots: str | os.PathLike) -> list[Path]:
    """Finished galleries under ``roots``: each root is a gallery (it has ``transforms_train.json``) or a profile
    folder whose ``seed_<N>`` sub-folders are galleries; only those with a ``stamp.json`` (written last by
    ``samples/galleries.py``) count. Sorted by seed. Raises LightNetError when a root is neither."""
    out: list[Path] = []
    for r in roots:
        r = Path(r).expanduser()
        if (r / "transforms_train.json").is_file():
            out.append(r)
            continue
        if not r.is_dir():
            raise LightNetError(f"gallery folder not found: {r}")
        subs = [d for d in r.glob("seed_*") if (d / "stamp.json").is_file() and (d / "transforms_train.json").is_file()]
        out += sorted(subs, key=lambda d: int(d.name[5:]) if d.name[5:].isdigit() else -1)
    return out


def _probe_name(env: str) -> str:
    """``probulator_pisa_256x128.hdr`` → ``pisa``."""
    stem = Path(str(env)).name.split(".")[0]
    parts = stem.split("_")
    if parts[0] == "probulator" and len(parts) >= 3:
        return "_".join(parts[1:-1])
    return stem


def light_dataset_from_galleries(dirs: list[str | os.PathLike], size: int = 64, holdout_probes: tuple[str, ...] = (),
                                 heldout_galleries: tuple[str | os.PathLike, ...] = (),
                                 splits: tuple[str, ...] = ("train", "test"), progress: bool = False) -> LightDataset:
    """Views of rendered galleries (``samples/galleries.py``) as a :class:`LightDataset`: one lighting per gallery.

    Per gallery, every frame of ``splits`` is read from its linear ``radiance_path`` (.hdr), area-averaged in linear
    light to ``size`` x ``size`` (the network's input; the 8-bit ``file_path`` PNG is sRGB(clip(radiance)) quantised),
    and paired with the gallery's top-level ``sh`` (SPEC SH of the incident radiance at the room centre). Units: the
    generator bakes its exposure into the light powers (``render.exposure.env_scale`` / ``lamp_scale``), so radiance
    and ``sh`` are already in the photo's units — unlike ``samples/render_lightings.py`` data, nothing is multiplied
    (a sample scene's ``render.exposure`` number is likewise already applied to its .hdr and ``sh``).

    The lighting source of a gallery is its HDR probe (``render.env``, e.g. ``pisa``); galleries listed in
    ``heldout_galleries`` (matched by resolved path) are labelled by their folder name instead. Views are held out
    (``test``) when their gallery is in ``heldout_galleries`` or its probe is in ``holdout_probes``.

    Args:
        dirs: gallery folders (see :func:`gallery_dirs`); ``heldout_galleries`` are added if missing.
        size: output resolution.
        holdout_probes: probe names (``pisa``, ``ennis``, ``grace_new``, ``wells``) whose galleries are held out.
        heldout_galleries: galleries held out as a whole.
        splits: which transforms files to read per gallery.
        progress: a tqdm bar on stderr.

    Returns:
        LightDataset with ``meta["galleries"]``: per gallery path, seed, probe, source, views, held out.

    Raises:
        LightNetError: no galleries, a gallery without ``sh`` or frames, or unreadable files.
    """
    from .io import read_hdr, read_json

    held = [Path(d).expanduser().resolve() for d in heldout_galleries]
    all_dirs = [Path(d).expanduser().resolve() for d in dirs]
    all_dirs += [d for d in held if d not in all_dirs]
    if not all_dirs:
        raise LightNetError("light_dataset_from_galleries: no galleries (render some with samples/galleries.py)")
    rads, shs, light, test, sources, info, c2ws = [], [], [], [], [], [], []
    it = all_dirs
    if progress:
        from tqdm import tqdm

        it = tqdm(all_dirs, desc="read galleries", file=sys.stderr, leave=False)
    for gi, d in enumerate(it):
        metas = [read_json(d / f"transforms_{s}.json", "gallery transforms") for s in splits
                 if (d / f"transforms_{s}.json").is_file()]
        if not metas or metas[0].get("sh") is None:
            raise LightNetError(f"{d}: no transforms with a top-level 'sh' (not a rendered gallery?)")
        sh = torch.tensor(metas[0]["sh"], dtype=torch.float32)
        check_shape(sh, "9 3", f"{d} sh")
        probe = _probe_name(metas[0].get("render", {}).get("env", "?"))
        source = d.name if d in held else probe
        n0 = len(rads)
        for m in metas:
            for f in m.get("frames", []):
                if not f.get("radiance_path"):
                    raise LightNetError(f"{d}: frame {f.get('file_path')} has no radiance_path (linear .hdr)")
                r = torch.from_numpy(read_hdr(d / f["radiance_path"])).permute(2, 0, 1)[None]
                rads.append(F.adaptive_avg_pool2d(r, (size, size))[0] if r.shape[-2:] != (size, size) else r[0])
                c2ws.append(torch.tensor(f["transform_matrix"], dtype=torch.float32))
        nv = len(rads) - n0
        if nv == 0:
            raise LightNetError(f"{d}: no frames in {splits}")
        is_test = d in held or probe in holdout_probes
        shs += [sh] * nv
        light += [gi] * nv
        test += [is_test] * nv
        sources.append(source)
        info.append({"path": str(d), "seed": metas[0].get("render", {}).get("gallery_seed"),
                     "profile": metas[0].get("render", {}).get("profile"), "probe": probe,
                     "source": source, "views": nv, "heldout": is_test})
    return LightDataset(radiance=torch.stack(rads).float().contiguous(), sh=torch.stack(shs), lighting=torch.tensor(light),
                        test=torch.tensor(test), sources=tuple(sources),
                        meta={"galleries": info, "size": size, "holdout_probes": list(holdout_probes),
                              "heldout_galleries": [str(d) for d in held]},
                        heading=camera_heading(torch.stack(c2ws)))


def concat_light_datasets(*datasets: LightDataset) -> LightDataset:
    """One :class:`LightDataset` from several of the same image size (lighting indices renumbered, sources kept)."""
    if not datasets:
        raise LightNetError("concat_light_datasets: nothing to concatenate")
    sizes = {tuple(d.radiance.shape[-2:]) for d in datasets}
    if len(sizes) > 1:
        raise LightNetError(f"concat_light_datasets: image sizes differ {sorted(sizes)}")
    light, sources, off = [], [], 0
    for d in datasets:
        n_l = max(len(d.sources), int(d.lighting.max()) + 1 if len(d) else 0)
        light.append(d.lighting + off)
        sources += [d.sources[i] if i < len(d.sources) else "?" for i in range(n_l)]
        off += n_l
    heading = (torch.cat([d.heading for d in datasets]) if all(d.heading is not None for d in datasets) else None)
    return LightDataset(torch.cat([d.radiance for d in datasets]), torch.cat([d.sh for d in datasets]),
                        torch.cat(light), torch.cat([d.test for d in datasets]), tuple(sources),
                        {"parts": [d.meta for d in datasets]}, heading)


# ============================================================================ training
@dataclass(frozen=True)
class TrainLightNetConfig:
    """Options of :func:`train_lightnet`."""

    arch: LightNetConfig = _PRESETS["small"]
    """The network to train (``lightnet_config("resnet34")`` for the paper's)."""
    steps: int = 4000
    batch_size: int = 32
    lr: float = 2e-3
    """Peak learning rate of Adam (one-cycle schedule: warm-up then cosine decay)."""
    weight_decay: float = 0.0
    """Adam's L2 penalty."""
    loss: Literal["l2", "huber"] = "huber"
    """``l2``: squared error summed over the 27 coefficients; ``huber``: r² for r = ‖pred − gt‖ ≤ δ, 2δr − δ² above
    (outlier lightings — light hidden behind the wall — cannot dominate)."""
    huber_delta: float = 1.0
    band_weights: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Loss weight per SH band; (1, 1, 1) makes the loss the squared Env-light L2 (eq. 36)."""
    exposure_jitter: float = 0.5
    """Each sample's exposure (image and GT SH together) is scaled by 2^u, u ~ U(−j, j) stops."""
    shift_px: int = 3
    """Random translation of up to this many pixels (edge padding): small camera jitter."""
    hflip: bool = False
    """Flip half the photos left-right with their targets mirrored (:data:`MIRROR_Y_SIGNS`). Only for a
    ``frame="heading"`` network: a flipped photo of a world-frame target would mirror the world."""
    seed: int = 0
    progress: bool = True

    def __post_init__(self):
        if self.loss not in ("l2", "huber") or not self.huber_delta > 0:
            raise ConfigError(f"TrainLightNetConfig: loss={self.loss!r} must be 'l2' or 'huber' and "
                              f"huber_delta={self.huber_delta} > 0")
        if self.steps < 0 or self.batch_size < 1 or not self.lr > 0 or self.exposure_jitter < 0 or self.shift_px < 0:
            raise ConfigError(f"TrainLightNetConfig: steps={self.steps} >= 0, batch_size={self.batch_size} >= 1, "
                              f"lr={self.lr} > 0, exposure_jitter, shift_px >= 0 are required")
        if self.hflip and self.arch.frame != "heading":
            raise ConfigError("TrainLightNetConfig: hflip=True needs arch.frame='heading' (flipping a photo of a "
                              "world-frame target would mirror the world)")


@dataclass(frozen=True)
class LightNetHistory:
    """What :func:`train_lightnet` measured.

    Attributes:
        losses: per step, the batch mean of the weighted squared error over the 27 coefficients.
        seconds: wall-clock training time.
        train_mean_sh: float [9, 3] mean ground-truth SH of the training views (baseline (a); output-bias init).
        views: number of training views.
        config: the configuration used.
    """

    losses: list[float]
    seconds: float
    train_mean_sh: torch.Tensor
    views: int
    config: TrainLightNetConfig


def _batch(ds: LightDataset, idx: torch.Tensor, cfg: TrainLightNetConfig, g: torch.Generator, size: int):
    rad, sh = ds.radiance[idx], ds.sh[idx]
    if cfg.exposure_jitter > 0:
        k = torch.exp2((torch.rand(len(idx), generator=g) * 2 - 1) * cfg.exposure_jitter).to(rad)
        rad, sh = rad * k[:, None, None, None], sh * k[:, None, None]
    x = linear_to_srgb(rad.clamp(0.0, 1.0))
    if cfg.hflip:
        flip = torch.rand(len(idx), generator=g) < 0.5
        x = torch.where(flip[:, None, None, None], x.flip(-1), x)
        signs = torch.tensor(MIRROR_Y_SIGNS, dtype=sh.dtype)[None, :, None]
        sh = torch.where(flip[:, None, None], sh * signs, sh)
    if cfg.shift_px > 0:
        s = cfg.shift_px
        H, W = x.shape[-2:]
        xp = F.pad(x, (s, s, s, s), mode="replicate")
        off = torch.randint(0, 2 * s + 1, (len(idx), 2), generator=g).tolist()
        x = torch.stack([xp[i, :, oy:oy + H, ox:ox + W] for i, (oy, ox) in enumerate(off)])
    return _resize(x, size), sh


def train_lightnet(dataset: LightDataset, cfg: TrainLightNetConfig = TrainLightNetConfig(),
                   model: LightNet | None = None) -> tuple[LightNet, LightNetHistory]:
    """Train :class:`LightNet` on the training views of ``dataset`` (its held-out views are never read).

    Adam with a one-cycle schedule; per view the squared error ``r² = Σ_k,c w_l(k) (pred − gt)²`` over the 27
    coefficients (with unit weights, the squared Env-light L2 of eq. 36), Huber-robust by default (``2δr − δ²``
    above ``r = δ``: views whose light is hidden behind the wall cannot dominate), averaged over the batch.
    Augmentation: exposure jitter (image and SH scale together, so the radiance units stay consistent) and small
    translations — no flips (they would mirror the world frame). The last FC layer starts near zero with its bias at
    the logits of the training targets (of the mean SH for ``output_range="absolute"``, the mean of per-view logits
    for ``"image"``), so step 0 predicts a sensible average. Seeded (model init, batches, augmentation); runs on
    ``dataset.radiance.device``.

    Args:
        dataset: views with ground truth; ``dataset.split("train")`` is used.
        cfg: :class:`TrainLightNetConfig`.
        model: continue training this network instead of a fresh ``LightNet(cfg.arch)``.

    Returns:
        ``(model in eval mode, LightNetHistory)``.

    Raises:
        LightNetError: no training views.
    """
    train = dataset.split("train")
    if len(train) == 0:
        raise LightNetError("train_lightnet: the data set has no training views (all are marked held-out)")
    torch.manual_seed(cfg.seed)
    g = torch.Generator().manual_seed(cfg.seed)
    device = train.radiance.device
    mean_sh = train.sh.mean(0)  # world frame: baseline (a)
    net = model if model is not None else LightNet(cfg.arch)
    if net.cfg.frame == "heading":  # targets in each view's heading frame
        if train.heading is None:
            raise LightNetError("train_lightnet: a frame='heading' network needs the views' camera headings "
                                "(LightDataset.heading, from the cameras' poses); this data set has none")
        train = replace(train, sh=rotate_sh_heading(train.sh, train.heading, inverse=True))
    net = net.to(device)
    if model is None:
        with torch.no_grad():
            net.head[-1].weight.mul_(0.1)
            if net.cfg.output_range == "absolute":
                net.head[-1].bias.copy_(logits_from_sh(mean_sh[None], net.cfg.dc_max)[0])
            else:  # the mean of the per-image logits of the GT (a seeded subset)
                sub = torch.randperm(len(train), generator=g)[:512]
                x = _resize(linear_to_srgb(train.radiance[sub].clamp(0.0, 1.0)), net.cfg.input_size).to(device)
                net.head[-1].bias.copy_(logits_from_sh(train.sh[sub].to(device), net.dc_range(x)).mean(0))
    w = torch.tensor([cfg.band_weights[SH_BAND_OF_K[k]] for k in range(9)], device=device)[:, None]
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=cfg.lr, total_steps=max(cfg.steps, 1), pct_start=0.1)
    losses: list[float] = []
    t0 = time.time()
    steps = range(cfg.steps)
    if cfg.progress:
        from tqdm import tqdm

        steps = tqdm(steps, desc=f"train lightnet ({net.cfg.name})", file=sys.stderr, leave=False)
    net.train()
    for _ in steps:
        idx = torch.randint(0, len(train), (cfg.batch_size,), generator=g)
        x, y = _batch(train, idx, cfg, g, net.cfg.input_size)
        sq = (w * (net(x.to(device)) - y.to(device)) ** 2).sum(dim=(1, 2))
        if cfg.loss == "huber":
            r = sq.clamp_min(1e-12).sqrt()
            d = cfg.huber_delta
            sq = torch.where(r <= d, sq, 2 * d * r - d * d)
        loss = sq.mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
        if cfg.progress and len(losses) % 20 == 0:
            steps.set_postfix(loss=f"{np.mean(losses[-50:]):.4f}")
    net.eval()
    net.meta = {"train_mean_sh": mean_sh.cpu().tolist(), "train_views": len(train)}
    return net, LightNetHistory(losses=losses, seconds=time.time() - t0, train_mean_sh=mean_sh.cpu(), views=len(train),
                                config=cfg)


# ============================================================================ inference and baselines
def _resize(images: torch.Tensor, size: int) -> torch.Tensor:
    """sRGB [B, 3, H, W] → [B, 3, size, size]: area average in linear light when shrinking, else bilinear."""
    H, W = images.shape[-2:]
    if (H, W) == (size, size):
        return images
    if H >= size and W >= size:
        return linear_to_srgb(F.adaptive_avg_pool2d(srgb_to_linear(images), (size, size))).clamp(0.0, 1.0)
    return F.interpolate(images, size=(size, size), mode="bilinear", align_corners=False).clamp(0.0, 1.0)


def predict_sh(model: LightNet, images: torch.Tensor, batch_size: int = 64, *, c2w: torch.Tensor | None = None,
               heading: torch.Tensor | None = None) -> torch.Tensor:
    """Per-image SH from photos.

    Args:
        model: a :class:`LightNet` (set to eval mode here).
        images: float [B, 3, H, W] sRGB in [0, 1] (resized to ``model.cfg.input_size``: area averaging in linear
            light when shrinking, bilinear when enlarging).
        batch_size: images per forward pass.
        c2w: float [B, 4, 4] the photos' camera-to-world poses (world +z up, as :func:`toolkit.scene.load_scene`
            gives them). Required by a ``frame="heading"`` network (the shipped one), which answers relative to
            each photo's heading; ignored by a ``world`` one.
        heading: float [B, 2] the headings themselves (:func:`camera_heading`), instead of ``c2w``.

    Returns:
        float [B, 9, 3] radiance SH (SPEC convention, world frame) on ``images.device``.

    Raises:
        ShapeError / LightNetError: wrong shape, values outside [0, 1] (linear HDR input: convert to sRGB first), or
        a heading network without poses.
    """
    check_shape(images, "B 3 H W", "images")
    if images.numel() and (float(images.min()) < -1e-3 or float(images.max()) > 1 + 1e-3):
        raise LightNetError(f"images must be sRGB in [0, 1], got values in [{float(images.min()):.3g}, "
                            f"{float(images.max()):.3g}] (convert linear HDR with toolkit.io.linear_to_srgb after clipping)")
    if model.cfg.frame == "heading":
        if heading is None and c2w is None:
            raise LightNetError("this light network answers relative to each photo's heading: pass the photos' "
                                "camera poses (predict_sh(..., c2w=scene.cameras.c2w)); a photo alone cannot say "
                                "which way the room's light lies in the world")
        heading = camera_heading(c2w.float()) if heading is None else heading
        check_shape(heading, f"{images.shape[0]} 2", "heading")
    model = model.eval()
    dev = next(model.parameters()).device
    out = []
    with torch.no_grad():
        for i in range(0, images.shape[0], batch_size):
            x = _resize(images[i:i + batch_size].to(dev, torch.float32), model.cfg.input_size)
            h = None if model.cfg.frame != "heading" else heading[i:i + batch_size].to(dev, torch.float32)
            out.append(model(x, h).to(images.device))
    return torch.cat(out) if out else images.new_zeros(0, 9, 3)


def mean_colour_sh(images: torch.Tensor, srgb: bool = True) -> torch.Tensor:
    """Baseline (b): the SH of a constant environment whose radiance is the image's mean linear colour.

    Args:
        images: float [B, 3, H, W] in [0, 1].
        srgb: the images are sRGB-encoded (decoded before averaging).

    Returns:
        float [B, 9, 3]: ``L00 = c / 0.282095`` per channel, bands 1-2 zero.
    """
    check_shape(images, "B 3 H W", "images")
    lin = srgb_to_linear(images) if srgb else images
    out = images.new_zeros(images.shape[0], 9, 3)
    out[:, 0] = lin.mean(dim=(2, 3)) / SH_C0
    return out


def aggregate_sh(per_image: torch.Tensor, reduce: Literal["mean", "median"] = "mean") -> torch.Tensor:
    """One [9, 3] estimate from per-image ones [B, 9, 3]: the mean, or the per-coefficient median (robust)."""
    check_shape(per_image, "B 9 3", "per_image")
    if per_image.shape[0] == 0:
        raise LightNetError("aggregate_sh: no per-image estimates to combine")
    if reduce == "mean":
        return per_image.mean(0)
    if reduce == "median":
        return per_image.median(0).values
    raise ConfigError(f"reduce={reduce!r}: choose 'mean' or 'median'")


@dataclass(frozen=True)
class LightNetEvaluation:
    """Env-light L2 (eq. 36) on a set of views, mean over images (and over lightings, per-lighting aggregates).

    Attributes:
        network: the network's per-image prediction.
        network_per_lighting: the mean of the network's predictions over each lighting's views (as ``dars priors
            light`` does for a scene), mean over lightings.
        train_mean_sh: baseline (a), the training-set mean SH.
        mean_colour: baseline (b), :func:`mean_colour_sh`.
        zero_light: predicting no light at all (``‖gt‖``).
        grey_ambient: the trainer's default without a light prior (``toolkit.train.grey_ambient_sh``: twice
            baseline (b)'s grey level, i.e. an albedo-0.5 assumption), for reference.
        per_source: per lighting source (``pisa``, ``sky``...), the network's and baselines' means over images, and
            ``network_per_lighting`` over that source's lightings.
        images, lightings: how many were evaluated.
        per_lighting: per lighting, ``{"lighting", "source", "images", "network", "grey_ambient", "zero_light",
            "true_over_network_level", "network_true_level"}``: the network's mean over the lighting's views (as
            ``dars priors light`` combines them) and the grey ambient of their mean level (as the trainer starts
            without a light prior), against that lighting's truth; the ratio of the true to the predicted level
            (mean DC over the colour channels), and, for diagnosis only, the L2 of the network's estimate scaled to
            the true level (the truth tells it its level: what is left is the light's direction and colour).
    """

    network: float
    network_per_lighting: float
    train_mean_sh: float
    mean_colour: float
    grey_ambient: float
    zero_light: float
    per_source: dict[str, dict[str, float]]
    images: int
    lightings: int
    per_lighting: list[dict] = field(default_factory=list)

    def to_json(self) -> dict:
        return asdict(self)


def evaluate_lightnet(model: LightNet, dataset: LightDataset, train_mean_sh: torch.Tensor,
                      batch_size: int = 64) -> LightNetEvaluation:
    """Env-light L2 of the network and of the baselines on every view of ``dataset`` (pass ``.split("test")``)."""
    from .metrics import env_light_l2

    if len(dataset) == 0:
        raise LightNetError("evaluate_lightnet: empty data set")
    images = dataset.images()
    gt = dataset.sh
    if model.cfg.frame == "heading" and dataset.heading is None:
        raise LightNetError("evaluate_lightnet: a frame='heading' network needs the views' headings (LightDataset.heading)")
    pred = predict_sh(model, images, batch_size, heading=dataset.heading)
    base_a = train_mean_sh.to(gt)[None].expand_as(gt)
    base_b = mean_colour_sh(images)
    lin_mean = srgb_to_linear(images).mean(dim=(1, 2, 3))
    grey = torch.zeros_like(gt)
    grey[:, 0] = (2.0 * lin_mean / 0.282095)[:, None]
    errs = {"network": env_light_l2(pred, gt), "train_mean_sh": env_light_l2(base_a, gt),
            "mean_colour": env_light_l2(base_b, gt), "grey_ambient": env_light_l2(grey, gt),
            "zero_light": env_light_l2(torch.zeros_like(gt), gt)}
    lights = dataset.lighting.unique()
    src = np.array(dataset.source_of())
    src_l = np.array([dataset.sources[l] if l < len(dataset.sources) else "?" for l in lights.tolist()])
    per_lighting, per_l = [], []
    for k, l in enumerate(lights.tolist()):
        m = dataset.lighting == l
        p_l, g_l = pred[m].mean(0), gt[m][0]  # the room's estimate, as dars priors light combines its views
        grey_l = torch.zeros(9, 3)  # the trainer's grey ambient (toolkit.train.data.grey_ambient_sh; the layering
        grey_l[0] = 2.0 * float(lin_mean[m].mean()) / 0.282095  # forbids importing train here) at the room's mean level
        per_l.append(env_light_l2(p_l, g_l))
        level = float(g_l[0].mean()) / max(float(p_l[0].mean()), 1e-12)
        per_lighting.append({"lighting": int(l), "source": str(src_l[k]), "images": int(m.sum()),
                             "network": float(per_l[-1]),
                             "grey_ambient": float(env_light_l2(grey_l, g_l)),
                             "zero_light": float(g_l.norm()), "true_over_network_level": level,
                             "network_true_level": float(env_light_l2(p_l * level, g_l))})
    per_l = torch.stack(per_l)
    per_source = {s: {k: float(v[torch.from_numpy(src == s)].mean()) for k, v in errs.items()}
                  | {"network_per_lighting": float(per_l[torch.from_numpy(src_l == s)].mean()),
                     "images": int((src == s).sum()), "lightings": int((src_l == s).sum())}
                  for s in sorted(set(src.tolist()))}
    return LightNetEvaluation(network=float(errs["network"].mean()), network_per_lighting=float(per_l.mean()),
                              train_mean_sh=float(errs["train_mean_sh"].mean()), mean_colour=float(errs["mean_colour"].mean()),
                              grey_ambient=float(errs["grey_ambient"].mean()),
                              zero_light=float(errs["zero_light"].mean()), per_source=per_source,
                              images=len(dataset), lightings=int(len(lights)), per_lighting=per_lighting)


# ============================================================================ persistence
def save_lightnet(path: str | os.PathLike, model: LightNet, extra: dict | None = None) -> Path:
    """Write a :class:`LightNet` (architecture, weights, ``model.meta`` + ``extra``) atomically; returns the path.

    Weights are stored as float16 when ``half`` is set in ``extra`` (``{"half": True}``; halves the file, ~1e-3
    relative change of the outputs); default float32.
    """
    if not isinstance(model, LightNet):
        raise LightNetError(f"save_lightnet expects a LightNet, got {type(model).__name__}")
    extra = dict(extra or {})
    half = bool(extra.pop("half", False))
    state = {k: (v.detach().cpu().half() if half and v.is_floating_point() else v.detach().cpu())
             for k, v in model.state_dict().items()}
    payload = {"format": _FORMAT, "version": 1, "arch": asdict(model.cfg), "state_dict": state,
               "meta": {**model.meta, **extra}}
    return save_torch(path, payload)


def load_lightnet(path: str | os.PathLike | None = None, map_location: str | torch.device = "cpu") -> LightNet:
    """Load a file written by :func:`save_lightnet` (default: the shipped :data:`DEFAULT_WEIGHTS`), in eval mode.

    ``model.meta`` holds what was stored with it (``train_mean_sh``, training command and figures...).

    Raises:
        LightNetError: the file is missing, unreadable, not a light-network file, or does not fit its architecture.
    """
    path = Path(path).expanduser() if path is not None else DEFAULT_WEIGHTS
    what = "shipped light-network weights" if path == DEFAULT_WEIGHTS else "light-network weights"
    if not path.is_file():
        raise LightNetError(f"{what} not found: {path} (train them with bench/bench_lightnet.py --save {path}, "
                            "or pass --weights FILE)")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:
        raise LightNetError(f"{path} is not a readable light-network file ({type(e).__name__}: {e}); "
                            "re-train or re-copy it") from e
    if not isinstance(payload, dict) or payload.get("format") != _FORMAT:
        raise LightNetError(f"{path} is not a dars light-network file (written by toolkit.lightnet.save_lightnet)")
    try:
        arch = payload["arch"]
        cfg = LightNetConfig(**{**arch, "blocks": tuple(arch["blocks"]), "widths": tuple(arch["widths"])})
        net = LightNet(cfg)
        net.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in payload["state_dict"].items()})
    except (KeyError, TypeError, RuntimeError, ConfigError) as e:
        raise LightNetError(f"{path}: weights do not fit the stored architecture ({e})") from e
    net.meta = dict(payload.get("meta", {}))
    return net.to(map_location).eval()
