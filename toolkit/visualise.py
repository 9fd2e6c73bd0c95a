"""Quick-look images: contact sheets of scenes, colour maps for labels, normals and scalar maps, displayable
render outputs. (The OpenGL preview of a baked asset is :mod:`viewers.preview`.)"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .io import linear_to_srgb, write_png
from .scene import SEMANTIC_CLASSES, UNLABELLED, Scene

__all__ = ["LABEL_COLOURS", "colourise_labels", "colourise_normals", "colourise_scalar", "contact_sheet", "tile",
           "OUTPUT_NAMES", "render_output_images"]

LABEL_COLOURS = np.array([
    [0.90, 0.30, 0.25],  # painting
    [0.95, 0.75, 0.20],  # frame
    [0.35, 0.80, 0.95],  # display
    [0.55, 0.45, 0.80],  # base
    [0.80, 0.80, 0.75],  # wall
    [0.45, 0.70, 0.35],  # floor
    [0.95, 0.45, 0.80],  # other
], dtype=np.float32)
"""RGB in [0, 1] per class of :data:`toolkit.scene.SEMANTIC_CLASSES`; unlabelled pixels are black."""
if len(LABEL_COLOURS) != len(SEMANTIC_CLASSES):  # keep the palette in step with the class list
    raise ImportError("LABEL_COLOURS must have one colour per semantic class")


def colourise_labels(labels: torch.Tensor | np.ndarray) -> np.ndarray:
    """int [H, W] class ids -> float H-W-3 colours (255 = black)."""
    lab = np.asarray(labels.cpu() if isinstance(labels, torch.Tensor) else labels).astype(np.int64)
    out = np.zeros(lab.shape + (3,), np.float32)
    ok = (lab >= 0) & (lab < len(LABEL_COLOURS)) & (lab != UNLABELLED)
    out[ok] = LABEL_COLOURS[lab[ok]]
    return out


def colourise_normals(normals_chw: torch.Tensor | np.ndarray) -> np.ndarray:
    """float [3, H, W] unit normals -> H-W-3 image (n+1)/2; zero vectors stay black."""
    n = np.asarray(normals_chw.cpu() if isinstance(normals_chw, torch.Tensor) else normals_chw).transpose(1, 2, 0)
    valid = np.abs(n).sum(-1, keepdims=True) > 0
    return np.where(valid, (n + 1) * 0.5, 0.0).astype(np.float32)


def colourise_scalar(x: torch.Tensor | np.ndarray, lo: float | None = None, hi: float | None = None,
                     cmap: str = "turbo") -> np.ndarray:
    """float [H, W] -> H-W-3 image through a matplotlib colour map (range [lo, hi], default min..max)."""
    import matplotlib

    a = np.asarray(x.detach().cpu() if isinstance(x, torch.Tensor) else x, dtype=np.float32)
    lo = float(np.nanmin(a)) if lo is None else lo
    hi = float(np.nanmax(a)) if hi is None else hi
    t = np.clip((a - lo) / max(hi - lo, 1e-12), 0, 1)
    return matplotlib.colormaps[cmap](t)[..., :3].astype(np.float32)


def tile(rows: list[list[np.ndarray]], pad: int = 2) -> np.ndarray:
    """Grid of equally sized H-W-3 float images with ``pad`` px white gutters."""
    h, w = rows[0][0].shape[:2]
    ncol = max(len(r) for r in rows)
    out = np.ones((len(rows) * (h + pad) + pad, ncol * (w + pad) + pad, 3), np.float32)
    for i, r in enumerate(rows):
        for j, img in enumerate(r):
            y, x = pad + i * (h + pad), pad + j * (w + pad)
            out[y:y + h, x:x + w] = img[..., :3] if img.ndim == 3 else img[..., None]
    return out


def contact_sheet(scene: Scene, out: Path, n: int = 6) -> Path:
    """Write a PNG grid: one row per view (evenly spread), columns image | labels | albedo | normals | depth.

    Columns whose map the scene lacks are left out.
    """
    idx = np.linspace(0, len(scene) - 1, min(n, len(scene))).round().astype(int)
    extras = scene.extras_available()
    rows = []
    for i in idx:
        row = [scene.load_image(int(i)).numpy().transpose(1, 2, 0)]
        if "semantic" in extras:
            row.append(colourise_labels(scene.load_extra(int(i), "semantic")))
        if "albedo" in extras:
            row.append(linear_to_srgb(scene.load_extra(int(i), "albedo").numpy().transpose(1, 2, 0)))
        if "normal" in extras:
            row.append(colourise_normals(scene.load_extra(int(i), "normal")))
        if "depth" in extras:
            d = scene.load_extra(int(i), "depth").numpy()
            valid = d > 0
            img = colourise_scalar(np.where(valid, d, np.nan), float(d[valid].min()) if valid.any() else 0,
                                   float(d[valid].max()) if valid.any() else 1, "viridis")
            row.append(np.where(valid[..., None], img, 0.0))
        rows.append(row)
    write_png(out, tile(rows))
    return out


def labelled_sheet(rows: list[list[np.ndarray]], columns: list[str], max_width: int = 256) -> np.ndarray:
    """A contact sheet of segmentation rows (photo | labels | metal | ...) with column titles and the class colour
    legend, as an H-W-3 float image. Every image is resized to the first photo's size, at most ``max_width`` wide."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch
    from PIL import Image

    h0, w0 = rows[0][0].shape[:2]
    k = min(max_width, max(w0, 128)) / w0  # small renders are enlarged so titles and legend fit
    size = (max(1, round(w0 * k)), max(1, round(h0 * k)))

    def fit(a):
        a = np.clip(a[..., :3] if a.ndim == 3 else np.repeat(a[..., None], 3, -1), 0, 1)
        if a.shape[1::-1] == size:
            return a
        return np.asarray(Image.fromarray((a * 255 + 0.5).astype(np.uint8)).resize(size, Image.NEAREST),
                          np.float32) / 255.0

    grid = tile([[fit(a) for a in r] for r in rows])
    dpi = 100
    fig = plt.figure(figsize=(grid.shape[1] / dpi, (grid.shape[0] + 90) / dpi), dpi=dpi)
    ax = fig.add_axes([0, 0, 1, grid.shape[0] / (grid.shape[0] + 90)])
    ax.imshow(grid, interpolation="nearest")
    ax.axis("off")
    ncol = max(len(r) for r in rows)
    for j, name in enumerate(columns[:ncol]):
        fig.text((j + 0.5) / ncol, 1 - 0.25 * 90 / (grid.shape[0] + 90), name, ha="center", va="center", fontsize=7)
    handles = [Patch(color=c, label=n) for c, n in zip(LABEL_COLOURS, SEMANTIC_CLASSES)]
    fig.legend(handles=handles, loc="upper center", ncol=min(len(handles), 2 * ncol), fontsize=7, frameon=False,
               bbox_to_anchor=(0.5, 1 - 0.45 * 90 / (grid.shape[0] + 90)))
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].astype(np.float32) / 255.0
    plt.close(fig)
    return img


OUTPUT_NAMES = ("rgb", "albedo", "diffuse", "specular", "roughness", "metallic", "opacity", "normal", "semantic",
                "depth", "samples")
"""Every image :func:`render_output_images` can return (``dars render`` writes ``<view>_<name>.png``)."""


def render_output_images(outputs, srgb: bool = True) -> dict[str, np.ndarray]:
    """Turn render outputs — a :class:`toolkit.pipeline.RenderedImage` or a dict of [H, W(, C)] arrays by the same
    names (e.g. :func:`export.infer.render_view`'s) — into displayable H-W-3 float images in [0, 1].

    ``rgb``/``albedo``/``diffuse``/``specular`` are linear and shown through the sRGB transfer (when ``srgb``);
    ``roughness``/``metallic``/``opacity`` as grey; ``normal`` as (n+1)/2; ``semantic`` from the argmax of the
    logits (black where opacity < 0.5); ``depth`` through a colour map; ``samples`` (samples per ray) likewise.
    """
    if hasattr(outputs, "as_dict"):
        outputs = outputs.as_dict()

    def to_np(t):
        return t.detach().float().cpu().numpy() if isinstance(t, torch.Tensor) else np.asarray(t, np.float32)

    enc = linear_to_srgb if srgb else (lambda x: x)
    imgs: dict[str, np.ndarray] = {}
    for k in ("rgb", "albedo", "diffuse", "specular"):
        if k in outputs:
            imgs[k] = np.clip(enc(np.clip(to_np(outputs[k]), 0, None)), 0, 1)
    for k in ("roughness", "metallic", "opacity"):
        if k in outputs:
            imgs[k] = np.repeat(np.clip(to_np(outputs[k]), 0, 1)[..., None], 3, -1)
    op = to_np(outputs["opacity"]) if "opacity" in outputs else None
    if "normal" in outputs:
        n = to_np(outputs["normal"])
        img = (n + 1) * 0.5
        imgs["normal"] = img if op is None else img * (op[..., None] > 0.5)
    if "semantic_logits" in outputs:
        lab = to_np(outputs["semantic_logits"]).argmax(-1)
        if op is not None:
            lab = np.where(op > 0.5, lab, UNLABELLED)
        imgs["semantic"] = colourise_labels(lab)
    if "depth" in outputs:
        d = to_np(outputs["depth"])
        valid = (op > 0.5) if op is not None else np.isfinite(d)
        lo = float(d[valid].min()) if valid.any() else 0.0
        hi = float(d[valid].max()) if valid.any() else 1.0
        imgs["depth"] = np.where(valid[..., None], colourise_scalar(d, lo, hi, "viridis"), 0.0)
    if "samples" in outputs:
        imgs["samples"] = colourise_scalar(to_np(outputs["samples"]), 0, None, "magma")
    return imgs
