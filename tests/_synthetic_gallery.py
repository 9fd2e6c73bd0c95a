"""A tiny multi-view 'gallery wall' built in code, for the prior-stage tests (edges, segment, colour).

The world is a plane (a wall with a framed painting, a base, a display case, a floor strip and small 'other'
objects) stored as a linear texture + label map + metal mask; each view is a perspective warp (homography) of it,
so views share content the way photos of a wall do. Poses are rigid and ordered along a path, so nearest-camera
pair selection finds overlapping views.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

WALL, PAINTING, FRAME, DISPLAY, BASE, FLOOR, OTHER = 4, 0, 1, 2, 3, 5, 6


def make_world(seed: int = 0, size: int = 512):
    """-> (texture float32 S-S-3 linear in ~[0.005, 0.6], labels uint8 S-S, metal bool S-S)."""
    import cv2

    rng = np.random.default_rng(seed)
    S = size

    def noise(scale, ch=3):
        n = rng.random((S // scale + 2, S // scale + 2, ch)).astype(np.float32)
        r = cv2.resize(n, (S, S), interpolation=cv2.INTER_CUBIC)
        return r.reshape(S, S, ch)

    tex = np.empty((S, S, 3), np.float32)
    lab = np.full((S, S), WALL, np.uint8)
    tex[:] = np.array([0.30, 0.28, 0.25]) * (0.85 + 0.3 * noise(32, 1))  # plaster wall, low-frequency shading
    # floor strip at the bottom: planks
    y_floor = int(S * 0.8)
    lab[y_floor:] = FLOOR
    planks = (np.arange(S) // 24 % 2)[None, :, None] * 0.04
    tex[y_floor:] = (np.array([0.22, 0.13, 0.07]) + planks) * (0.8 + 0.4 * noise(8, 1)[y_floor:])
    # painting in a gold frame
    y0, y1, x0, x1 = int(S * 0.15), int(S * 0.55), int(S * 0.2), int(S * 0.65)
    f = 10
    lab[y0 - f:y1 + f, x0 - f:x1 + f] = FRAME
    tex[y0 - f:y1 + f, x0 - f:x1 + f] = np.array([0.55, 0.40, 0.12]) * (0.8 + 0.4 * noise(4, 1)[y0 - f:y1 + f, x0 - f:x1 + f])
    lab[y0:y1, x0:x1] = PAINTING
    paint = 0.45 * noise(48) + 0.3 * noise(12) + 0.25 * noise(3)
    tex[y0:y1, x0:x1] = (paint[y0:y1, x0:x1] ** 2.2) * 0.6 + 0.01
    # base with a display case on top
    by0, bx0, bx1 = int(S * 0.62), int(S * 0.72), int(S * 0.9)
    lab[by0:y_floor, bx0:bx1] = BASE
    tex[by0:y_floor, bx0:bx1] = np.array([0.45, 0.45, 0.47]) * (0.85 + 0.3 * noise(6, 1)[by0:y_floor, bx0:bx1])
    dy0 = int(S * 0.35)
    lab[dy0:by0, bx0 + 6:bx1 - 6] = DISPLAY
    tex[dy0:by0, bx0 + 6:bx1 - 6] = tex[dy0:by0, bx0 + 6:bx1 - 6] * 0.7 + np.array([0.05, 0.07, 0.08])
    # a few 'other' objects (signs, hydrants)
    for _ in range(4):
        cx, cy = int(rng.integers(20, S // 6)), int(rng.integers(int(S * 0.2), int(S * 0.7)))
        r = int(rng.integers(6, 14))
        yy, xx = np.ogrid[:S, :S]
        m = (yy - cy) ** 2 + (xx - cx) ** 2 < r * r
        lab[m] = OTHER
        tex[m] = rng.random(3) * 0.5 + 0.05
    metal = lab == FRAME
    metal &= noise(16, 1)[..., 0] > 0.4
    return np.clip(tex, 0.005, 0.6).astype(np.float32), lab, metal


def make_views(world, n: int, seed: int = 1, size: int = 64, spread: float = 1.0):
    """Perspective views of the plane world.

    Returns:
        dict with ``images`` float32 [n, size, size, 3] linear, ``labels`` uint8 [n, size, size], ``metal`` bool,
        ``c2w`` float64 [n, 4, 4] rigid poses ordered along a path.
    """
    import cv2

    tex, lab, metal = world
    S = tex.shape[0]
    rng = np.random.default_rng(seed)
    imgs, labs, mets, poses = [], [], [], []
    for k in range(n):
        t = k / max(n - 1, 1)
        cx = S * (0.4 + 0.25 * t) + rng.normal(0, 10) * spread
        cy = S * 0.55 + rng.normal(0, 15) * spread
        sc = rng.uniform(0.7, 0.85) * S / size
        ang = rng.normal(0, 0.08)
        R = np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]]) * sc
        H = np.eye(3)
        H[:2, :2] = R
        H[:2, 2] = np.array([cx, cy]) - R @ np.array([size / 2, size / 2])
        H[2, :2] = rng.normal(0, 1.5e-4, 2) * (64 / size)
        flags = cv2.WARP_INVERSE_MAP
        imgs.append(cv2.warpPerspective(tex, H, (size, size), flags=cv2.INTER_LINEAR | flags, borderMode=cv2.BORDER_REFLECT))
        labs.append(cv2.warpPerspective(lab, H, (size, size), flags=cv2.INTER_NEAREST | flags, borderMode=cv2.BORDER_REFLECT))
        mets.append(cv2.warpPerspective(metal.astype(np.uint8), H, (size, size), flags=cv2.INTER_NEAREST | flags,
                                        borderMode=cv2.BORDER_REFLECT) > 0)
        c2w = np.eye(4)
        yaw = ang
        c2w[:3, :3] = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
        c2w[:3, 3] = [cx / S * 4.0, cy / S * 4.0, 3.0]
        poses.append(c2w)
    return {"images": np.stack(imgs), "labels": np.stack(labs), "metal": np.stack(mets), "c2w": np.stack(poses)}


def write_scene(root: Path, n_train: int = 8, n_test: int = 4, size: int = 48, seed: int = 0,
                with_labels: bool = True) -> Path:
    """Write a transforms-JSON scene (sRGB PNG photos, semantic and metal PNGs) under ``root``; returns ``root``."""
    from toolkit.io import linear_to_srgb, write_png

    root = Path(root)
    world = make_world(seed)
    for split, n, s in (("train", n_train, seed + 1), ("test", n_test, seed + 2)):
        v = make_views(world, n, s, size)
        frames = []
        for i in range(n):
            stem = f"{split}/r_{i:03d}"
            write_png(root / f"{stem}.png", linear_to_srgb(v["images"][i]))
            fr = {"file_path": f"{stem}.png", "transform_matrix": v["c2w"][i].tolist()}
            if with_labels:
                write_png(root / f"{stem}_semantic.png", v["labels"][i])
                write_png(root / f"{stem}_metal.png", v["metal"][i].astype(np.uint8) * 255)
                fr.update(semantic_path=f"{stem}_semantic.png", metal_path=f"{stem}_metal.png")
            frames.append(fr)
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames}, indent=1))
    return root
