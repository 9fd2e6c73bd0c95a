"""Training data: the training views' tensors and priors (:func:`prepare_data`), read through
:func:`toolkit.priors.read_priors`; W maps are computed here when the priors folder has none."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from ..io import srgb_to_linear
from ..priors import priors_path, read_priors
from ..scene import Scene
from .config import TrainConfig

__all__ = ["TrainData", "prepare_data", "grey_ambient_sh"]


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


def prepare_data(scene: Scene, cfg: TrainConfig, log=print, priors_root: str | Path | None = None) -> TrainData:
    """Load training images and priors (labels, metal mask, W maps, light, colour) for ``scene``.

    Priors come from the scene (provided labels and metal masks) or from the prior stages' outputs under
    ``priors_root/<stage>/`` (default ``<scene>/priors/<stage>/``; :func:`toolkit.priors.read_priors`); W maps are
    computed here when absent. Without any priors: uniform weights, no labels, SH initialised to a grey ambient —
    training still works.
    """
    from ..edges import WeightMapConfig, weight_map

    images = scene.load_images()
    V, _, H, W = images.shape
    source = {"ground-truth": "scene", "none": None}.get(cfg.labels, "segment")
    if source == "segment":  # predictions when the segmentation prior was run, else no labels
        seg = priors_path(scene, "segment", priors_root)
        if not all((seg / f"{f.key}.png").is_file() for f in scene.frames):
            source = "none"
    # labels feed L_semantic and W's edge term E (cfg.semantics: the semantic input) and L_mat's class terms
    # (cfg.mat_labels); read them when either uses them
    use_mat = cfg.mat_labels and cfg.losses.mat > 0 and cfg.shading == "pbr"
    pri = read_priors(scene, priors_root, labels=source if (cfg.semantics or use_mat) else None, weights=cfg.semantics,
                      colour=cfg.colour_correction != "off",
                      metal={"ground-truth": "scene", "predicted": "segment"}.get(cfg.labels, "none"))
    labels, metal = pri.labels, pri.metal
    priors: dict = {"labels": pri.labels_source, "metal": pri.metal_source}
    if labels is not None:
        priors["labels_used_by"] = ", ".join(u for u, on in (("L_semantic", cfg.semantics), ("W (E)", cfg.semantics),
                                                             ("L_mat", use_mat)) if on)
    if cfg.labels == "ground-truth":
        priors["ground_truth_inputs"] = "labels and metal masks (--labels ground-truth)"
    if pri.weights is not None:
        wm, dist = pri.weights, pri.distortion
        priors["weights"] = pri.weights_source
    else:
        wcfg = WeightMapConfig()
        w_labels = labels if cfg.semantics else None  # without the semantic input W has no label edges
        maps_w, maps_d = [], []
        for i in range(0, V, 16):
            wm_i = weight_map(images[i:i + 16], None if w_labels is None else w_labels[i:i + 16].long(),
                              None if metal is None else metal[i:i + 16], wcfg)
            maps_w.append(wm_i.weights.float())
            maps_d.append(wm_i.distortion_loss.float())
        wm, dist = torch.cat(maps_w), torch.cat(maps_d)
        priors["weights"] = "computed (G" + ("+E" if w_labels is not None else "") + ("+M" if metal is not None else "") + ")"
    albedo_gt = None
    if cfg.albedo_supervision and scene.has_extra("albedo"):
        albedo_gt = torch.stack([scene.load_extra(i, "albedo") for i in range(V)])
        priors["albedo_supervision"] = "ground truth"
    if pri.light is not None:
        l_env, l_src = pri.light, pri.light_source
    else:
        lin = srgb_to_linear(images) if scene.srgb else images
        fg = lin
        if scene.background is not None:  # RGBA photos on a known background: the ambient level of the object only
            bg = torch.tensor(scene.background, dtype=images.dtype).view(1, 3, 1, 1)
            obj = ((images - bg).abs().amax(1, keepdim=True) > 0.02).expand_as(lin)
            if bool(obj.any()):
                fg = lin[obj]
        l_env, l_src = grey_ambient_sh(float(fg.mean())), "grey ambient"
    priors["light"] = l_src
    if pri.colour is not None:
        priors["colour"] = pri.colour_source
    elif cfg.colour_correction == "on":
        priors["colour"] = "identity (learned)"
    log("[dars] priors: " + ", ".join(f"{k}={v}" for k, v in priors.items()))
    wm = wm.clamp(0, 1)
    if cfg.sampler.normalise == "quantile":
        from ..edges import quantile_normalise

        wm = quantile_normalise(wm)
    return TrainData(scene=scene, images=images, labels=labels, metal=metal, weights=wm, distortion=dist,
                     albedo_gt=albedo_gt, l_env_init=l_env, l_env_source=l_src, colour_init=pri.colour,
                     priors_used=priors)
