"""Procedural content of the gallery sample: textures, the sculpture mesh and the random SH sky.

Everything is seeded and built in code (numpy + OpenCV), so the committed sample is reproducible.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = ["painting_texture", "plank_texture", "stone_texture", "twisted_sculpture_mesh", "write_ply", "sky_environment"]


def _srgb_to_lin(x: np.ndarray) -> np.ndarray:
    from toolkit.io import srgb_to_linear

    return srgb_to_linear(np.asarray(x, dtype=np.float32)).astype(np.float32)


def painting_texture(seed: int, width: int = 512, height: int = 384) -> np.ndarray:
    """Colourful brush-stroke-like canvas, linear RGB float32 [H, W, 3] (row 0 = top of the canvas)."""
    import cv2

    rng = np.random.default_rng(seed + 101)
    yy, xx = np.mgrid[0:height, 0:width] / max(width, height)
    base = np.stack([0.55 + 0.25 * xx, 0.45 + 0.2 * yy, 0.35 + 0.2 * (1 - xx)], -1)
    img = (base * 255).astype(np.float32)
    for _ in range(260):
        hue = rng.uniform(0, 180)
        hsv = np.uint8([[[hue, rng.uniform(140, 255), rng.uniform(120, 255)]]])
        col = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0].astype(np.float32)
        overlay = img.copy()
        x0, y0 = rng.uniform(0, width), rng.uniform(0, height)
        ang = rng.uniform(0, math.pi)
        length = rng.uniform(20, 120)
        pts = []
        for t in np.linspace(0, 1, 8):
            bend = 12 * math.sin(math.pi * t) * rng.uniform(-1, 1)
            pts.append((x0 + t * length * math.cos(ang) - bend * math.sin(ang), y0 + t * length * math.sin(ang) + bend * math.cos(ang)))
        cv2.polylines(overlay, [np.int32(pts)], False, col.tolist(), int(rng.uniform(4, 16)), lineType=cv2.LINE_AA)
        a = rng.uniform(0.5, 0.9)
        img = img * (1 - a) + overlay * a
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    return _srgb_to_lin(np.clip(img / 255.0, 0, 1))


def plank_texture(seed: int, size: int = 1024, planks: int = 10) -> np.ndarray:
    """Wooden planks along x for a 2 m x 2 m tile, linear RGB float32 [size, size, 3]."""
    import cv2

    rng = np.random.default_rng(seed + 202)
    img = np.zeros((size, size, 3), np.float32)
    ph = size // planks
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    grain = cv2.GaussianBlur(rng.standard_normal((size, size)).astype(np.float32), (0, 0), sigmaX=25, sigmaY=1.2)
    grain /= np.abs(grain).max() + 1e-6
    for p in range(planks):
        rows = slice(p * ph, (p + 1) * ph if p < planks - 1 else size)
        seam = rng.uniform(0, size)
        for half in (0, 1):
            tone = np.array([0.50, 0.33, 0.20]) * rng.uniform(0.75, 1.15) + rng.uniform(-0.03, 0.03, 3)
            mask = (xx[rows] >= seam) if half else (xx[rows] < seam)
            img[rows][mask] = tone
        img[rows.start : rows.start + 2] *= 0.55
        img[rows, int(seam) % size : int(seam) % size + 2] *= 0.55
    img *= (1.0 + 0.18 * grain)[..., None]
    return _srgb_to_lin(np.clip(img, 0, 1))


def stone_texture(seed: int, size: int = 256) -> np.ndarray:
    """Mottled light stone, linear RGB float32 [size, size, 3]."""
    import cv2

    rng = np.random.default_rng(seed + 303)
    n = sum(cv2.GaussianBlur(rng.standard_normal((size, size)).astype(np.float32), (0, 0), s) * s**0.5 for s in (1.0, 3.0, 9.0))
    n /= np.abs(n).max() + 1e-6
    img = np.array([0.74, 0.71, 0.66], np.float32) * (1.0 + 0.12 * n[..., None])
    return _srgb_to_lin(np.clip(img, 0, 1))


def twisted_sculpture_mesh(height: float, radius: float, rings: int = 96, segments: int = 120):
    """A twisted five-lobed column (vase profile, 180° twist), solid in the middle.

    Returns:
        vertices float32 [V, 3] (base centre at the origin, +z up), faces int32 [F, 3], smooth vertex normals [V, 3].
    """
    h = np.linspace(0.0, 1.0, rings)
    a = np.linspace(0.0, 2 * math.pi, segments, endpoint=False)
    H, A = np.meshgrid(h, a, indexing="ij")
    profile = 0.75 + 0.35 * np.sin(math.pi * (0.15 + 0.85 * H)) - 0.15 * H
    r = radius * profile * (1.0 + 0.22 * np.cos(5 * A))
    ang = A + math.pi * H
    verts = np.stack([r * np.cos(ang), r * np.sin(ang), H * height], -1).reshape(-1, 3)
    faces = []
    for i in range(rings - 1):
        for j in range(segments):
            v00, v01 = i * segments + j, i * segments + (j + 1) % segments
            v10, v11 = v00 + segments, v01 + segments
            faces += [(v00, v01, v11), (v00, v11, v10)]
    bottom, top = len(verts), len(verts) + 1
    verts = np.vstack([verts, [[0, 0, 0], [0, 0, height]]])
    for j in range(segments):
        faces.append((bottom, (j + 1) % segments, j))
        faces.append((top, (rings - 1) * segments + j, (rings - 1) * segments + (j + 1) % segments))
    faces = np.asarray(faces, np.int32)
    tri = verts[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = np.zeros_like(verts)
    for k in range(3):
        np.add.at(normals, faces[:, k], fn)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True) + 1e-12
    return verts.astype(np.float32), faces, normals.astype(np.float32)


def write_ply(path: Path, verts: np.ndarray, faces: np.ndarray, normals: np.ndarray) -> None:
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(verts)}\nproperty float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    vdata = np.hstack([verts, normals]).astype("<f4").tobytes()
    fdata = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    fdata["n"], fdata["i"] = 3, faces
    path.write_bytes(header.encode() + vdata + fdata.tobytes())


def sky_environment(seed: int, H: int = 128, W: int = 256) -> np.ndarray:
    """A random smooth SH sky (bright, bluish above, warm ground bounce below), float32 [H, W, 3]."""
    import torch

    from toolkit.sh import render_sh_envmap

    rng = np.random.default_rng(seed + 404)
    c = np.zeros((9, 3))
    c[0] = np.array([1.0, 1.05, 1.15]) * rng.uniform(2.0, 3.0)
    c[2] = np.array([0.8, 0.9, 1.1]) * rng.uniform(0.8, 1.4)  # brighter up
    c[1:4] += rng.normal(0, 0.25, (3, 3))
    c[4:9] += rng.normal(0, 0.15, (5, 3))
    m = render_sh_envmap(torch.as_tensor(c), H, W).numpy()
    return np.clip(m, 0.02, None).astype(np.float32)
