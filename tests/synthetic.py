"""A tiny analytic scene built in code: a textured sphere on a checkered floor, ray-traced in numpy.

Per view: sRGB PNG, semantic labels (sphere = painting 0, floor = 5, background 255) and a metal mask
(upper half of the sphere). Cameras on a ring looking at the origin; world up +z.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from toolkit.io import linear_to_srgb, write_png
from toolkit.pinhole import look_at


def render_view(c2w, size, focal):
    H = W = size
    v, u = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    d = np.stack([(u + 0.5 - W / 2) / focal, -(v + 0.5 - H / 2) / focal, -np.ones_like(u, float)], -1)
    d = d @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = c2w[:3, 3]
    # sphere r = 0.5 at the origin
    b = (d * o).sum(-1)
    c = (o * o).sum() - 0.25
    disc = b * b - c
    t_s = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
    t_s = np.where(t_s > 0, t_s, np.inf)
    # floor z = -0.5 within |x|,|y| < 1.5
    t_f = np.where(np.abs(d[..., 2]) > 1e-6, (-0.5 - o[2]) / d[..., 2], np.inf)
    p_f = o + t_f[..., None] * d
    t_f = np.where((t_f > 0) & (np.abs(p_f[..., 0]) < 1.5) & (np.abs(p_f[..., 1]) < 1.5), t_f, np.inf)
    hit_s = t_s < t_f
    hit_f = np.isfinite(t_f) & ~hit_s
    img = np.zeros((H, W, 3))
    lab = np.full((H, W), 255, np.uint8)
    metal = np.zeros((H, W), np.uint8)
    p = o + np.where(hit_s, t_s, 0)[..., None] * d
    n = p / 0.5
    phi = np.arctan2(n[..., 1], n[..., 0])
    stripes = 0.5 + 0.5 * np.sign(np.sin(6 * phi))
    base = np.stack([0.2 + 0.6 * stripes, 0.3 + 0.2 * (n[..., 2] > 0), 0.7 - 0.5 * stripes], -1)
    shade = 0.35 + 0.65 * np.clip(n @ np.array([0.3, 0.2, 0.93]), 0, 1)
    img = np.where(hit_s[..., None], base * shade[..., None], img)
    lab[hit_s] = 0
    metal[hit_s & (n[..., 2] > 0.3)] = 255
    pf = o + np.where(hit_f, t_f, 0)[..., None] * d
    checker = ((np.floor(pf[..., 0] * 3) + np.floor(pf[..., 1] * 3)) % 2)
    fcol = np.stack([0.25 + 0.45 * checker, 0.25 + 0.4 * checker, 0.2 + 0.3 * checker], -1)
    img = np.where(hit_f[..., None], fcol, img)
    lab[hit_f] = 5
    return linear_to_srgb(np.clip(img, 0, 1)).astype(np.float32), lab, metal


def make_scene(root: Path, n_train: int = 40, n_test: int = 8, size: int = 32, radius: float = 2.5, height: float = 1.2) -> Path:
    """Train views on two elevation rings (heights ``height`` ± 0.4), test views between them."""
    root = Path(root)
    focal = 0.5 * size / math.tan(0.5 * 0.8)
    for split, n in (("train", n_train), ("test", n_test)):
        frames = []
        for k in range(n):
            if split == "train":
                a = 2 * math.pi * (k // 2) / (n // 2) + math.pi * (k % 2) / (n // 2)
                z = height + (0.4 if k % 2 else -0.4)
            else:
                a = 2 * math.pi * (k + 0.5) / n
                z = height + 0.2 * math.sin(3 * a)
            c2w = look_at([radius * math.cos(a), radius * math.sin(a), z], [0.0, 0.0, 0.0])
            img, lab, metal = render_view(c2w, size, focal)
            name = f"{split}/r_{k:03d}"
            write_png(root / f"{name}.png", img)
            write_png(root / f"{name}_semantic.png", lab)
            write_png(root / f"{name}_metal.png", metal)
            frames.append({"file_path": f"{name}.png", "transform_matrix": c2w.tolist(),
                           "semantic_path": f"{name}_semantic.png", "metal_path": f"{name}_metal.png"})
        meta = {"camera_angle_x": 0.8, "aabb": [[-1.6, -1.6, -0.7], [1.6, 1.6, 1.0]], "frames": frames}
        (root / f"transforms_{split}.json").write_text(json.dumps(meta))
    return root
