"""Training data: the training views' pixels and priors (:func:`prepare_data`), read through
:func:`toolkit.priors.read_priors`; W maps are computed here when the priors folder has none.

Memory does not grow with megapixels beyond the stored pixels themselves: every per-pixel quantity is packed
(:class:`toolkit.pixels.PackedViews`, views of any sizes one after another) at reduced precision and converted to
float per batch (:func:`toolkit.train.step.sample_batch`). Bytes per training pixel:

=================  =============================================  =====
quantity           storage                                        bytes
=================  =============================================  =====
colour             uint8 x 3, ``round(255 c)``                    3
W (DARS)           uint8, ``round(255 W)`` (rank-normalised W)    1
labels             uint8 class ids (255 unlabelled)               1
metal mask         bool                                           1
albedo (optional)  float16 x 3 (``--albedo-supervision``)         6
valid (optional)   bool, the photos' masks (``masks="ignore"``)   1
=================  =============================================  =====

so 4-6 bytes a pixel (colour and W always, labels and the metal mask when used; albedo supervision adds 6): 58
photos of 1 MP take 0.35 GB, where the float32 images alone were 0.7 GB and the whole loader with its float64 sampling
table and float temporaries peaked near 30 bytes a pixel. Colour at 8 bits is exact for 8-bit photos (JPEG/PNG); RGBA
composites and resampled (``downscale``) images round to 1/255. Each W map is normalised at full precision
(:func:`toolkit.edges.normalise_weight_map`: rank normalisation, so ranks are taken before any rounding) and then
written once at 8 bits, an error of at most 1/510 (float16 W took 2 bytes a pixel). Images are decoded one at a time
(the transient is one photo in float32); with ``cache_dir`` the colour buffer is a memory-mapped file on disk instead
of RAM.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .._checks import ConfigError
from ..io import srgb_to_linear
from ..pixels import PackedViews
from ..priors import priors_path, read_priors
from ..scene import SEMANTIC_CLASSES, Scene
from .config import TrainConfig, photos_have_transparency

__all__ = ["TrainData", "prepare_data", "grey_ambient_sh", "PLANAR_PIXELS_PER_REGION", "LAYOUT_CLASSES",
           "layout_pixels"]

PLANAR_PIXELS_PER_REGION = 2048
"""Pixels kept of each textureless region (``losses.planar``): the loss draws a few dozen a step, and a region of a
large photo would otherwise hold hundreds of thousands."""

LAYOUT_CLASSES = (SEMANTIC_CLASSES.index("wall"), SEMANTIC_CLASSES.index("floor"))
"""Classes whose textureless pixels get the room box's depth (``losses.layout_depth``) when the run has labels
(predicted by default); the ceiling is ``wall`` in the SPEC's classes. Measured 2026-11-29 with the box of each
scene (labels and depth of the ground truth used for scoring only): of the targets on every textureless pixel,
1.5-9 % lay on plain pedestal sides, and 73-99 % of those were > 50 cm off (the box's depth is the wall behind
them). Keeping the pixels the shipped segmenter calls wall or floor kept 90-97 % of the targets and took the share
> 50 cm off from 7.6 / 2.9 / 1.6 / 1.6 % to 0.9 / 0.2 / 0.0 / 0.0 % on the sample and galleries 1000000-1000002
(``python bench/bench_layout.py --labels none``, then the default)."""



def layout_pixels(textureless: np.ndarray, labels: PackedViews | None, i: int) -> np.ndarray:
    """bool [H, W]: the pixels of photo ``i`` that get a room-layout target: its textureless pixels, kept to
    :data:`LAYOUT_CLASSES` where the run has labels (``bench/bench_layout.py`` scores the same set)."""
    room_px = textureless > 0
    if labels is not None:  # a plain pedestal side is textureless too, but stands in front of the box
        room_px &= np.isin(labels.raw(i).numpy(), LAYOUT_CLASSES)
    return room_px


@dataclass
class TrainData:
    """Training-view pixels (CPU, packed: :class:`toolkit.pixels.PackedViews`) and priors.

    Attributes:
        scene: the training split (views may differ in size: ``scene.cameras.width/height``).
        images: uint8 [P, 3] colour as stored (sRGB when ``scene.srgb``), quantised (read as float by ``gather``);
            float16 for linear (HDR) scenes.
        labels: uint8 [P] class ids (255 unlabelled) or None.
        metal: bool [P] or None.
        weights: uint8 [P] DARS weight maps W, ``quantised`` (``round(255 W)``; ``[i]`` and ``gather`` read floats in
            [0, 1]), rank-normalised per view unless ``sampler.normalise == "none"``.
        distortion: float [V] L_distortion of each map.
        albedo_gt: float16 [P, 3] linear ground-truth albedo (only with albedo supervision) or None.
        l_env_init: float [9, 3] initial light and where it came from.
        colour_init: ColourTransforms or None.
        sparse_depth: pixels with a known depth (``losses.sparse_depth`` > 0;
            :func:`toolkit.bounds.sparse_depth_targets`) or None.
        layout_depth: textureless-region pixels with a depth on the room's box (``losses.layout_depth`` > 0;
            :func:`toolkit.layout.layout_depth_targets`) or None.
        room_layout: the room's box (:meth:`toolkit.layout.RoomLayout.to_json`) when ``losses.layout_depth`` > 0,
            whether or not any pixel got a depth on it; else None.
        valid: bool [P] the pixels training may use (the photos' ``mask_path`` > 0, ``cfg.masks == "ignore"``), or
            None when every pixel may be used. The ray sampler never draws the others, and the geometry targets
            taken from the photos (sparse depth, room layout, planar regions) leave them out.
        planar: the large textureless regions of the photos (``losses.planar`` > 0;
            :func:`toolkit.regions.textureless_regions`) or None: ``{"views", "rows", "cols"}`` int64 [N] pixels
            (at most ``PLANAR_PIXELS_PER_REGION`` of each region, drawn at random), ``"offsets"`` int64 [K + 1]
            (region k is ``offsets[k]:offsets[k + 1]``).
    """

    scene: Scene
    images: PackedViews
    labels: PackedViews | None
    metal: PackedViews | None
    weights: PackedViews
    distortion: torch.Tensor
    albedo_gt: PackedViews | None
    l_env_init: torch.Tensor
    l_env_source: str
    colour_init: Any
    priors_used: dict
    sparse_depth: dict | None = None
    planar: dict | None = None
    layout_depth: dict | None = None
    room_layout: dict | None = None
    valid: PackedViews | None = None

    @property
    def nbytes(self) -> int:
        """Bytes held by the per-pixel buffers."""
        return sum(b.nbytes for b in (self.images, self.labels, self.metal, self.weights, self.albedo_gt, self.valid)
                   if b is not None)


def grey_ambient_sh(mean_linear: float) -> torch.Tensor:
    """[9, 3] SH of a constant grey radiance that renders an albedo-0.5 Lambertian surface at ``mean_linear``."""
    sh = torch.zeros(9, 3)
    sh[0] = 2.0 * mean_linear / 0.282095
    return sh


def prepare_data(scene: Scene, cfg: TrainConfig, log=print, priors_root: str | Path | None = None,
                 cache_dir: str | Path | None = None, with_images: bool = True, room_layout=None) -> TrainData:
    """Load training pixels and priors (labels, metal mask, W maps, light, colour) for ``scene``, one photo at a time.

    Priors come from the scene (provided labels and metal masks) or from the prior stages' outputs under
    ``priors_root/<stage>/`` (default ``<scene>/priors/<stage>/``; :func:`toolkit.priors.read_priors`); W maps are
    computed here when absent. Either way each W map is normalised at full precision (``cfg.sampler.normalise``,
    :func:`toolkit.edges.normalise_weight_map`) and written once to a uint8 buffer. Without any priors: uniform
    weights, no labels, SH initialised to a grey ambient — training still works.

    Args:
        scene: the training split (views may differ in size).
        cfg: the run's configuration (labels, semantics, sampler normalisation, colour correction, albedo supervision).
        log: one-line progress messages.
        priors_root: where the prior stages wrote their outputs (default: next to the scene).
        cache_dir: keep the colour buffer in a memory-mapped file ``cache_dir/images.npy`` (created; a capture
            larger than RAM), or None for RAM.
        with_images: False: only what rendering needs (W maps, light); ``images`` is then an empty layout.
        room_layout: the room's box (:class:`toolkit.layout.RoomLayout`) for ``losses.layout_depth``, already fitted
            (a resumed run's, or rank 0's under torch.distributed); None: fitted here from ``scene``'s photos.
    """
    from ..edges import WeightMapConfig, normalise_weight_map, weight_map
    from ..regions import textureless_regions

    V = len(scene)
    hs, ws = scene.cameras.height, scene.cameras.width
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
                      metal={"ground-truth": "scene", "predicted": "segment"}.get(cfg.labels, "none"),
                      weights_normalise=cfg.sampler.normalise)
    labels, metal = pri.labels, pri.metal
    priors: dict = {"labels": pri.labels_source, "metal": pri.metal_source}
    if labels is not None:
        priors["labels_used_by"] = ", ".join(u for u, on in (("L_semantic", cfg.semantics), ("W (E)", cfg.semantics),
                                                             ("L_mat", use_mat)) if on)
    if cfg.labels == "ground-truth":
        priors["ground_truth_inputs"] = "labels and metal masks (--labels ground-truth)"
    w_labels = labels if cfg.semantics else None  # without the semantic input W has no label edges
    if with_images:
        path = None if cache_dir is None else Path(cache_dir) / "images.npy"
        images = (PackedViews.allocate(hs, ws, 3, quantised=True, path=path) if scene.srgb
                  else PackedViews.allocate(hs, ws, 3, dtype=torch.float16, path=path))
    else:
        images = _layout_only(hs, ws)
    computed = pri.weights is None
    wm = pri.weights if not computed else PackedViews.allocate(hs, ws, quantised=True)
    dist = pri.distortion if not computed else torch.zeros(V)
    albedo_gt = None
    if cfg.albedo_supervision and scene.has_extra("albedo") and with_images:
        albedo_gt = PackedViews.allocate(hs, ws, 3, dtype=torch.float16)
        priors["albedo_supervision"] = "ground truth"
    # The light network reads whole photos of lit rooms. On RGBA photos of an object on a known background most
    # pixels are that compositing colour, not light, and its estimate is out of its domain (NeRF Lego: DC 5.8
    # against the object pixels' grey ambient 1.9, and a white fog that fitted the too-bright shading, README
    # "NeRF Lego"). There the light starts from the object pixels' grey ambient, as without a light prior.
    known_bg = pri.light is not None and photos_have_transparency(scene)
    need_light = pri.light is None or known_bg
    want_planar = cfg.losses.planar > 0 and with_images
    want_layout = cfg.losses.uses_room_layout and with_images
    planar_parts: list[tuple[int, np.ndarray]] = []
    layout_regions: list[np.ndarray] = []  # textureless pixels (bool [H, W]) of each photo, for the layout targets
    gen = np.random.default_rng(cfg.seed)
    valid = None
    if cfg.masks == "ignore" and with_images and any("mask" in f.extras for f in scene.frames):
        valid = PackedViews.allocate(hs, ws, dtype=torch.bool)
    kept, total = 0, 0
    need_pixels = with_images or computed or need_light
    wcfg = WeightMapConfig()
    bg = torch.tensor(scene.background, dtype=torch.float32).view(3, 1, 1)
    lin_sum, lin_n, all_sum, all_n = 0.0, 0, 0.0, 0
    for i in range(V):
        img = scene.load_image(i) if need_pixels else None  # float [3, H, W], the only full-precision copy
        if with_images:
            images.write(i, img.permute(1, 2, 0))
        ok = scene.valid_mask(i) if valid is not None else None  # bool [H, W], None: every pixel
        if valid is not None:
            valid.write(i, ok if ok is not None else torch.ones(int(hs[i]), int(ws[i]), dtype=torch.bool))
            kept, total = kept + (int(ok.sum()) if ok is not None else int(hs[i] * ws[i])), total + int(hs[i] * ws[i])
        reg = textureless_regions(img) if want_planar or want_layout else None
        if reg is not None and ok is not None:
            reg = np.where(ok.numpy(), reg, 0)
        if want_layout:
            layout_regions.append(layout_pixels(reg, labels, i))
        if want_planar:
            reg = reg.reshape(-1)
            for k in range(1, int(reg.max()) + 1):
                px = np.flatnonzero(reg == k)
                if len(px) > PLANAR_PIXELS_PER_REGION:
                    px = np.sort(gen.choice(px, PLANAR_PIXELS_PER_REGION, replace=False))
                planar_parts.append((i, px))
        if computed:
            lab = None if w_labels is None else w_labels.raw(i).long()[None]
            met = None if metal is None else metal.raw(i)[None]
            wm_i = weight_map(img[None], lab, met, wcfg)
            wm.write(i, normalise_weight_map(wm_i.weights[0], cfg.sampler.normalise))  # one write, at 8 bits
            dist[i] = float(wm_i.distortion_loss[0])
        if albedo_gt is not None:
            albedo_gt.write(i, scene.load_extra(i, "albedo").permute(1, 2, 0))
        if need_light:  # the ambient level of the photos (of the object only, for RGBA photos on a known background;
            # of the pixels the masks keep)
            lin = srgb_to_linear(img) if scene.srgb else img
            kept_px = None if ok is None else ok[None].expand_as(lin)
            all_sum += float((lin if kept_px is None else lin[kept_px]).sum(dtype=torch.float64))
            all_n += lin.numel() if kept_px is None else int(kept_px.sum())
            if scene.background is not None:
                obj = ((img - bg).abs().amax(0, keepdim=True) > 0.02).expand_as(lin)
                if kept_px is not None:
                    obj = obj & kept_px
                lin_sum, lin_n = lin_sum + float(lin[obj].sum(dtype=torch.float64)), lin_n + int(obj.sum())
    if valid is not None:
        if kept == 0:
            raise ConfigError(f"{scene.source}: every pixel of the training photos is masked out (mask_path 0 "
                              "everywhere); a mask marks the pixels to keep with values > 0 (or use --masks alpha / off)")
        priors["masks"] = f"mask_path: {100.0 * (total - kept) / max(total, 1):.1f} % of the pixels left out"
    if computed:
        priors["weights"] = "computed (G" + ("+E" if w_labels is not None else "") + ("+M" if metal is not None else "") + ")"
    else:
        priors["weights"] = pri.weights_source
    if pri.light is not None and not known_bg:
        l_env, l_src = pri.light, pri.light_source
        if cfg.light_init == "ambient":
            l_env = l_env.clone()
            l_env[1:] = 0.0
            l_src += " (band 0 only: light_init=ambient)"
    else:
        mean = lin_sum / lin_n if lin_n else all_sum / max(all_n, 1)
        l_env, l_src = grey_ambient_sh(mean), "grey ambient"
        if known_bg:
            l_src += (f" of the object pixels ({pri.light_source} not used: the photos are RGBA on a known "
                      "background, outside the light network's domain)")
    priors["light"] = l_src
    if pri.colour is not None:
        priors["colour"] = pri.colour_source
    elif cfg.colour_correction == "on":
        priors["colour"] = "identity (learned)"
    log("[dars] priors: " + ", ".join(f"{k}={v}" for k, v in priors.items()))
    sparse, points = None, None
    if (cfg.losses.sparse_depth or 0.0) > 0 and with_images:
        from ..bounds import sparse_depth_targets, triangulate_sparse_points

        points = triangulate_sparse_points(scene, log=log)
        sparse = sparse_depth_targets(scene, points)
        if valid is not None:  # no depth target on a masked pixel (a person, a tripod)
            keep = valid.gather(valid.flat_index(sparse["views"], sparse["rows"], sparse["cols"]))
            sparse = {k: v[keep] for k, v in sparse.items()}
        log(f"[dars] sparse depth: {len(sparse['depth'])} pixels with a triangulated depth "
            f"(weight {cfg.losses.sparse_depth:g})" + ("; none: the loss is off" if not len(sparse["depth"]) else ""))
        if not len(sparse["depth"]):
            sparse = None
    layout, room = None, room_layout
    if want_layout:
        from ..layout import FACE_NAMES, fit_room_layout, layout_depth_targets

        if room is None:  # the sparse-depth loss's points when it triangulated them, else triangulated here
            room = fit_room_layout(scene, None if points is None else points.points, log=log)
        layout = layout_depth_targets(scene, room, regions=layout_regions.__getitem__)
        faces = [n for n, c in zip(FACE_NAMES, room.confident) if c]
        which = ("labelled wall or floor" if labels is not None else
                 "of any class (no labels: a plain object in front of a wall gets the wall's depth)")
        priors["layout_targets"] = f"textureless pixels {which}"
        log(f"[dars] room layout: box {np.round(room.hi - room.lo, 2).tolist()}, faces used: "
            f"{', '.join(faces) or 'none'}; {len(layout['depth'])} textureless pixels {which} with a depth on it "
            f"(weight {cfg.losses.layout_depth:g}, normals {cfg.losses.layout_normal or 0.0:g})"
            + ("; none: the loss is off" if not len(layout["depth"]) else ""))
        if not len(layout["depth"]):
            layout = None
    planar = None
    if want_planar:
        log(f"[dars] planar loss: {len(planar_parts)} textureless regions in {len({v for v, _ in planar_parts})} "
            f"of {V} photos (weight {cfg.losses.planar:g})" + ("; none: the loss is off" if not planar_parts else ""))
        if planar_parts:
            wv = ws.numpy().astype(np.int64)
            views = np.concatenate([np.full(len(px), v, np.int64) for v, px in planar_parts])
            flat = np.concatenate([px for _, px in planar_parts]).astype(np.int64)
            planar = {"views": torch.from_numpy(views), "rows": torch.from_numpy(flat // wv[views]),
                      "cols": torch.from_numpy(flat % wv[views]),
                      "offsets": torch.from_numpy(np.cumsum([0] + [len(px) for _, px in planar_parts]))}
    return TrainData(scene=scene, images=images, labels=labels, metal=metal, weights=wm, distortion=dist,
                     albedo_gt=albedo_gt, l_env_init=l_env, l_env_source=l_src, colour_init=pri.colour,
                     priors_used=priors, sparse_depth=sparse, planar=planar,
                     layout_depth=layout, room_layout=room.to_json() if room is not None else None, valid=valid)


def _layout_only(heights: torch.Tensor, widths: torch.Tensor) -> PackedViews:
    """The view sizes without pixels (``data`` empty)."""
    h = torch.as_tensor(heights, dtype=torch.long)
    w = torch.as_tensor(widths, dtype=torch.long)
    return PackedViews(torch.zeros(0, 3, dtype=torch.uint8), h, w,
                       torch.cat([torch.zeros(1, dtype=torch.long), torch.cumsum(h * w, 0)]))
