"""Procedural content of the gallery sample: textures, the sculpture mesh and the random SH sky.

Everything is seeded and built in code (numpy + OpenCV), so the committed sample is reproducible.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = [
    "painting_texture", "plank_texture", "stone_texture", "twisted_sculpture_mesh", "write_ply", "sky_environment",
    "canvas_texture", "floor_texture", "wall_texture", "WALL_PATTERNS", "lathe_mesh", "vase_profile", "bowl_profile",
    "periodic_noise",
]


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
    faces = _ring_faces(rings, segments)
    bottom, top = len(verts), len(verts) + 1
    verts = np.vstack([verts, [[0, 0, 0], [0, 0, height]]])
    for j in range(segments):
        faces.append((bottom, (j + 1) % segments, j))
        faces.append((top, (rings - 1) * segments + j, (rings - 1) * segments + (j + 1) % segments))
    faces, normals = _smooth_normals(verts, np.asarray(faces, np.int32))
    return verts.astype(np.float32), faces, normals.astype(np.float32)


def _ring_faces(rings: int, segments: int) -> list[tuple[int, int, int]]:
    """Two triangles per quad of a (rings x segments) grid wrapped around the axis (outward for rings going up)."""
    faces = []
    for i in range(rings - 1):
        for j in range(segments):
            v00, v01 = i * segments + j, i * segments + (j + 1) % segments
            v10, v11 = v00 + segments, v01 + segments
            faces += [(v00, v01, v11), (v00, v11, v10)]
    return faces


def _smooth_normals(verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop degenerate triangles; vertex normals = normalised sums of the area-weighted face normals."""
    tri = verts[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    keep = np.linalg.norm(fn, axis=1) > 1e-14
    faces, fn = faces[keep], fn[keep]
    normals = np.zeros_like(verts)
    for k in range(3):
        np.add.at(normals, faces[:, k], fn)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True) + 1e-12
    return faces, normals


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


# ------------------------------------------------------------------------------------ procedural galleries (seeded)
def periodic_noise(rng: np.random.Generator, size: int, sigma: float) -> np.ndarray:
    """Tileable smooth noise: white noise low-passed by a Gaussian of ``sigma`` pixels in Fourier space (so the
    texture wraps without seams). float32 [size, size], zero mean, max |value| = 1."""
    white = rng.standard_normal((size, size))
    f = np.fft.fftfreq(size)
    g = np.exp(-2.0 * (math.pi * sigma) ** 2 * (f[:, None] ** 2 + f[None, :] ** 2))
    n = np.real(np.fft.ifft2(np.fft.fft2(white) * g))
    n -= n.mean()
    return (n / (np.abs(n).max() + 1e-12)).astype(np.float32)


def _hsv_rgb(h: float, s: float, v: float) -> np.ndarray:
    """HSV (h in [0, 1)) → sRGB float [3] in [0, 1]."""
    import colorsys

    return np.array(colorsys.hsv_to_rgb(h % 1.0, s, v), np.float32)


def canvas_texture(seed: int, style: str = "strokes", aspect: float = 0.75, width: int = 512) -> np.ndarray:
    """A procedural canvas of a given aspect (height / width), linear RGB float32 [H, W, 3], row 0 = top.

    Styles: ``strokes`` (the sample's brush strokes on a random gradient, random palette), ``bands`` (a landscape-
    like stack of horizontal colour fields under strokes), ``blocks`` (hard-edged colour rectangles, a geometric
    abstract), ``portrait`` (dark ground, a lit oval figure, fine strokes). ``strokes`` at aspect 0.75 with the
    sample's palette is :func:`painting_texture`; here the palette, stroke count and widths vary with ``seed``.
    """
    import cv2

    rng = np.random.default_rng(seed + 505)
    height = max(16, int(round(width * aspect)))
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    yy /= height
    xx /= width
    hue0 = rng.uniform(0, 1)
    spread = rng.uniform(0.05, 0.5)  # palette width in hue
    if style == "bands":
        edges = np.sort(rng.uniform(0.15, 0.9, int(rng.integers(2, 5))))
        img = np.zeros((height, width, 3), np.float32)
        k = np.searchsorted(edges, yy + 0.03 * np.sin(xx * rng.uniform(3, 12) + rng.uniform(0, 6)))
        for b in range(len(edges) + 1):
            img[k == b] = _hsv_rgb(hue0 + rng.uniform(-spread, spread), rng.uniform(0.2, 0.8), rng.uniform(0.3, 0.95))
    elif style == "blocks":
        img = np.broadcast_to(_hsv_rgb(hue0, rng.uniform(0.0, 0.3), rng.uniform(0.7, 0.95)), (height, width, 3)).copy()
        for _ in range(int(rng.integers(3, 9))):
            x0, y0 = rng.uniform(0, 0.8, 2)
            x1, y1 = x0 + rng.uniform(0.1, 0.6), y0 + rng.uniform(0.1, 0.6)
            m = (xx >= x0) & (xx < x1) & (yy >= y0) & (yy < y1)
            img[m] = _hsv_rgb(hue0 + rng.uniform(-spread, spread) + rng.choice([0, 0.5]), rng.uniform(0.4, 1.0), rng.uniform(0.2, 0.95))
        for _ in range(int(rng.integers(0, 5))):  # dark grid lines
            if rng.uniform() < 0.5:
                x = int(rng.uniform(0, width)); img[:, x : x + int(rng.integers(3, 9))] = 0.05  # noqa: E702
            else:
                y = int(rng.uniform(0, height)); img[y : y + int(rng.integers(3, 9))] = 0.05  # noqa: E702
    elif style == "portrait":
        ground = _hsv_rgb(hue0, rng.uniform(0.3, 0.8), rng.uniform(0.05, 0.2))
        face = _hsv_rgb(rng.uniform(0.03, 0.1), rng.uniform(0.3, 0.6), rng.uniform(0.6, 0.9))
        cx, cy = rng.uniform(0.4, 0.6), rng.uniform(0.35, 0.5)
        r = ((xx - cx) / 0.22) ** 2 + ((yy - cy) / (0.3 / max(aspect, 0.3) * 0.75)) ** 2
        body = ((xx - cx) / 0.4) ** 2 + ((yy - 1.05) / 0.45) ** 2
        img = np.broadcast_to(ground, (height, width, 3)).copy() * (0.7 + 0.6 * (1 - yy))[..., None]
        img[body < 1] = _hsv_rgb(hue0 + 0.5, rng.uniform(0.3, 0.9), rng.uniform(0.1, 0.5))
        img = np.where((r < 1)[..., None], face * (1.1 - 0.4 * r[..., None]), img)
    else:  # strokes
        c0 = _hsv_rgb(hue0, rng.uniform(0.1, 0.5), rng.uniform(0.4, 0.9))
        c1 = _hsv_rgb(hue0 + spread, rng.uniform(0.1, 0.5), rng.uniform(0.4, 0.9))
        t = (0.5 * xx + 0.5 * yy)[..., None]
        img = c0 * (1 - t) + c1 * t
    img = np.clip(img, 0, 1) * 255.0
    n_strokes = {"strokes": int(rng.integers(120, 320)), "bands": int(rng.integers(40, 160)),
                 "blocks": int(rng.integers(0, 40)), "portrait": int(rng.integers(30, 120))}.get(style, 200)
    wmin, wmax = (2, 8) if style in ("portrait", "blocks") else (4, 18)
    for _ in range(n_strokes):
        col = _hsv_rgb(hue0 + rng.uniform(-spread, spread) + (0.5 if rng.uniform() < 0.2 else 0.0),
                       rng.uniform(0.3, 1.0), rng.uniform(0.3, 1.0)) * 255.0
        overlay = img.copy()
        x0, y0 = rng.uniform(0, width), rng.uniform(0, height)
        ang = rng.uniform(0, math.pi) if style != "bands" else rng.normal(0, 0.25)
        length = rng.uniform(15, 130)
        pts = []
        for t in np.linspace(0, 1, 8):
            bend = 12 * math.sin(math.pi * t) * rng.uniform(-1, 1)
            pts.append((x0 + t * length * math.cos(ang) - bend * math.sin(ang), y0 + t * length * math.sin(ang) + bend * math.cos(ang)))
        cv2.polylines(overlay, [np.int32(pts)], False, col.tolist(), int(rng.uniform(wmin, wmax)), lineType=cv2.LINE_AA)
        a = rng.uniform(0.4, 0.9)
        img = img * (1 - a) + overlay * a
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.8)
    return _srgb_to_lin(np.clip(img / 255.0, 0, 1))


def floor_texture(kind: str, seed: int, tone: tuple[float, float, float], size: int = 512) -> np.ndarray:
    """A tileable floor texture for a 2 m x 2 m tile, linear RGB float32 [size, size, 3].

    Kinds: ``planks`` (boards along x in ``tone``, seams, grain), ``stone`` (0.5 m slabs, mottled, grout lines),
    ``concrete`` (large smooth blotches, fine speckle), ``carpet`` (fine fibre noise, a faint weave). ``tone`` is the
    mean sRGB colour.
    """
    rng = np.random.default_rng(seed + 606)
    base = np.asarray(tone, np.float32)
    yy, xx = np.mgrid[0:size, 0:size]
    if kind == "planks":
        planks = int(rng.integers(8, 14))
        rows = (yy * planks) // size
        seams = np.sort(rng.uniform(0, size, (planks, 2)), axis=1)  # two boards per row; one of them wraps around x
        streak = periodic_noise(rng, size, 1.5)
        streak = 0.7 * streak.mean(1, keepdims=True) / (np.abs(streak.mean(1)).max() + 1e-6) + 0.3 * streak  # grain along x
        img = np.zeros((size, size, 3), np.float32)
        for p in range(planks):
            m = rows == p
            xs = xx[m]
            part = ((xs >= seams[p, 0]) & (xs < seams[p, 1])).astype(int)
            tones = base[None] * rng.uniform(0.8, 1.15, (2, 1)) + rng.uniform(-0.02, 0.02, (2, 3))
            img[m] = tones[part]
        img *= (1.0 + 0.2 * streak)[..., None]
        edge = ((yy * planks) % size) < max(2, size // 256)
        img[edge] *= 0.55
        for p in range(planks):
            for s in seams[p]:
                img[(rows == p) & (np.abs(xx - s) < 1.5)] *= 0.55
    elif kind == "stone":
        slabs = 4
        n = periodic_noise(rng, size, 2.0) + 0.6 * periodic_noise(rng, size, 10.0)
        cell = (yy * slabs // size) * slabs + (xx * slabs // size)
        shade = rng.uniform(0.85, 1.12, slabs * slabs)[cell]
        img = base[None, None] * (shade * (1.0 + 0.12 * n))[..., None]
        grout = ((xx * slabs) % size < 3) | ((yy * slabs) % size < 3)
        img[grout] = base * 0.5
    elif kind == "concrete":
        n = periodic_noise(rng, size, 25.0) + 0.4 * periodic_noise(rng, size, 4.0) + 0.25 * periodic_noise(rng, size, 0.7)
        img = base[None, None] * (1.0 + 0.12 * n)[..., None]
    else:  # carpet
        n = 0.6 * periodic_noise(rng, size, 0.6) + 0.4 * periodic_noise(rng, size, 12.0)
        weave = 0.04 * np.sin(2 * math.pi * xx * 64 / size) * np.sin(2 * math.pi * yy * 64 / size)
        img = base[None, None] * (1.0 + 0.25 * n + weave)[..., None]
    return _srgb_to_lin(np.clip(img, 0, 1))


WALL_PATTERNS = ("floral", "damask", "stripes", "dots", "brick", "panels", "plaster")
"""Kinds of :func:`wall_texture`: patterned papers, brick, boarding and rough plaster — the walls real rooms have
beside paint (a segmenter trained on plain walls calls a papered wall a painting)."""


def _soft(d: np.ndarray, width: float = 1.0) -> np.ndarray:
    """Anti-aliased inside test: 1 where the signed distance ``d`` (pixels, < 0 inside) is well inside, 0 outside."""
    return np.clip(0.5 - d / max(width, 1e-6), 0.0, 1.0).astype(np.float32)


def _wrap_delta(a: np.ndarray, c: float, size: int) -> np.ndarray:
    """Shortest signed distance from ``c`` to ``a`` on a circle of ``size`` pixels (the tile wraps)."""
    return (a - c + size / 2) % size - size / 2


def wall_texture(kind: str, seed: int, tone: tuple[float, float, float], size: int = 512) -> np.ndarray:
    """A tileable wall texture for one square tile (the wall's ``uv_scale`` sets its size in metres), linear RGB
    float32 [size, size, 3]; rows run along the wall's height, columns along its length.

    Kinds (:data:`WALL_PATTERNS`): ``floral`` (a half-drop repeat of blooms and leaves on a pale or dark ground),
    ``damask`` (a mirrored motif a shade off the ground), ``stripes`` (vertical bands of two or three tones),
    ``dots`` (a lattice of spots or diamonds), ``brick`` (courses with mortar), ``panels`` (vertical boards),
    ``plaster`` (mottled render). ``tone`` is the ground's sRGB colour; the other colours are drawn from ``seed``.
    """
    if kind not in WALL_PATTERNS:
        raise ValueError(f"unknown wall pattern {kind!r}: choose one of {WALL_PATTERNS}")
    rng = np.random.default_rng(seed + 909)
    base = np.clip(np.asarray(tone, np.float32), 0.0, 1.0)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    img = np.broadcast_to(base, (size, size, 3)).copy()

    def paint(mask: np.ndarray, colour) -> None:
        img[:] = img * (1.0 - mask[..., None]) + np.asarray(colour, np.float32) * mask[..., None]

    if kind == "floral":
        per = int(rng.integers(1, 3))  # motifs per tile side (half-drop repeat)
        cell = size / per
        hues = rng.uniform(0, 1, 2)
        bloom = _hsv_rgb(hues[0], rng.uniform(0.3, 0.8), rng.uniform(0.45, 0.9))
        leaf = _hsv_rgb(rng.uniform(0.2, 0.45), rng.uniform(0.25, 0.6), rng.uniform(0.3, 0.7))
        centres = []
        for i in range(per):
            for j in range(per):
                centres.append(((i + 0.5) * cell, (j + 0.25) * cell))
                centres.append(((i + 1.0) * cell % size, (j + 0.75) * cell))  # the half drop
        for cx, cy in centres:
            cx, cy = cx + rng.uniform(-0.08, 0.08) * cell, cy + rng.uniform(-0.08, 0.08) * cell
            r = cell * rng.uniform(0.12, 0.24)
            for _ in range(int(rng.integers(1, 4))):  # leaves around the bloom
                a = rng.uniform(0, 2 * math.pi)
                lx, ly = cx + 1.2 * r * math.cos(a), cy + 1.2 * r * math.sin(a)
                dx, dy = _wrap_delta(xx, lx, size), _wrap_delta(yy, ly, size)
                u, v = dx * math.cos(a) + dy * math.sin(a), -dx * math.sin(a) + dy * math.cos(a)
                paint(_soft((np.sqrt((u / (0.9 * r)) ** 2 + (v / (0.35 * r)) ** 2) - 1.0) * 0.35 * r), leaf)
            dx, dy = _wrap_delta(xx, cx, size), _wrap_delta(yy, cy, size)
            rad, ang = np.sqrt(dx ** 2 + dy ** 2), np.arctan2(dy, dx)
            petals = int(rng.integers(4, 8))
            outline = r * (0.8 + 0.2 * np.cos(petals * ang + rng.uniform(0, 6.3)))
            paint(_soft(rad - outline), bloom)
            for k, f in enumerate((0.65, 0.35)):  # darker whorls inside
                ring = np.abs(rad - f * r * (1.0 + 0.15 * np.sin(3 * ang + k))) - 0.05 * r
                paint(_soft(ring) * 0.7, bloom * rng.uniform(0.45, 0.75))
    elif kind == "damask":
        per = int(rng.integers(2, 4))
        m = 128
        half = periodic_noise(rng, m, m / 14.0)[:, : m // 2]
        motif = np.concatenate([half, half[:, ::-1]], 1)  # mirrored left-right, as damask is
        fy, fx = np.meshgrid(np.linspace(-1, 1, m), np.linspace(-1, 1, m), indexing="ij")
        shape = ((motif + 0.6 * (1.0 - np.sqrt(fx ** 2 + fy ** 2))) > rng.uniform(0.15, 0.35)).astype(np.float32)
        iy = ((yy * per / size) % 1.0 * m).astype(int)
        ix = ((xx * per / size) % 1.0 * m).astype(int)
        tile = shape[iy, ix]
        shade = rng.choice([0.75, 0.85, 1.15, 1.3])
        paint(tile, np.clip(base * shade + rng.uniform(-0.03, 0.03, 3), 0, 1))
    elif kind == "stripes":
        n = int(rng.choice([4, 6, 8, 12, 16]))
        edges = np.sort(rng.uniform(0, 1, n)) * size
        tones = [base, np.clip(base * rng.uniform(0.6, 0.9) + rng.uniform(-0.05, 0.05, 3), 0, 1),
                 _hsv_rgb(rng.uniform(0, 1), rng.uniform(0.2, 0.6), rng.uniform(0.3, 0.85))]
        band = np.searchsorted(edges, xx[0]) % n
        which = rng.integers(0, 3, n)
        for b in range(n):
            paint((band == b).astype(np.float32)[None, :].repeat(size, 0), tones[int(which[b])])
    elif kind == "dots":
        per = int(rng.choice([6, 8, 10, 14]))
        cell = size / per
        colour = _hsv_rgb(rng.uniform(0, 1), rng.uniform(0.2, 0.8), rng.uniform(0.2, 0.9))
        fx, fy = (xx % cell) - cell / 2, (yy % cell) - cell / 2
        r = cell * rng.uniform(0.12, 0.3)
        d = (np.abs(fx) + np.abs(fy) - 1.3 * r) if rng.uniform() < 0.5 else (np.sqrt(fx ** 2 + fy ** 2) - r)
        paint(_soft(d), colour)
    elif kind == "brick":
        courses = int(rng.choice([8, 10, 12, 16]))
        h = size / courses
        row = (yy // h).astype(int)
        bw = 2.0 * h * rng.uniform(1.6, 2.2)
        per_row = max(2, int(round(size / bw)))
        bw = size / per_row
        col = ((xx + (row % 2) * bw / 2) // bw).astype(int) % per_row
        ids = row * per_row + col
        brick = np.clip(base[None] * rng.uniform(0.8, 1.15, (courses * per_row, 1)) + rng.uniform(-0.03, 0.03, (courses * per_row, 3)), 0, 1)
        img[:] = brick[ids] * (1.0 + 0.08 * periodic_noise(rng, size, 1.0))[..., None]
        mortar = ((yy % h) < 2.5) | (((xx + (row % 2) * bw / 2) % bw) < 2.5)
        paint(mortar.astype(np.float32), np.clip(np.full(3, rng.uniform(0.55, 0.85)), 0, 1))
    elif kind == "panels":
        boards = int(rng.integers(4, 10))
        col = (xx * boards // size).astype(int)
        grain = periodic_noise(rng, size, 1.2)
        grain = 0.7 * grain.mean(0, keepdims=True) / (np.abs(grain.mean(0)).max() + 1e-6) + 0.3 * grain  # grain along y
        tones = np.clip(base[None] * rng.uniform(0.85, 1.12, (boards, 1)), 0, 1)
        img[:] = tones[col] * (1.0 + 0.15 * grain)[..., None]
        paint(((xx * boards) % size < max(2, size // 200)).astype(np.float32), base * 0.5)
    else:  # plaster
        n = periodic_noise(rng, size, 18.0) + 0.5 * periodic_noise(rng, size, 3.0) + 0.3 * periodic_noise(rng, size, 0.8)
        img[:] = base[None, None] * (1.0 + rng.uniform(0.08, 0.2) * n)[..., None]
    return _srgb_to_lin(np.clip(img, 0, 1))


def _smooth_outline(knots_t, knots_r, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Piecewise-linear radius through knots, smoothed by a 7-tap box (ends kept): t [n], r [n]."""
    t = np.linspace(0.0, 1.0, n)
    r = np.interp(t, knots_t, knots_r)
    r = np.convolve(np.pad(r, 3, mode="edge"), np.ones(7) / 7, mode="valid")
    return t, r


def vase_profile(rng: np.random.Generator, radius: float, height: float, n: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """A closed vase outline for :func:`lathe_mesh`: (radii, heights) from the base centre, up the outside, to the
    lid centre; the widest point is ``radius``."""
    belly, neck_t = rng.uniform(0.25, 0.5), rng.uniform(0.65, 0.85)
    foot, neck, lip = rng.uniform(0.4, 0.7), rng.uniform(0.3, 0.6), rng.uniform(0.4, 0.8)
    t, r = _smooth_outline([0.0, belly, neck_t, 1.0], [foot, 1.0, neck, lip], n)
    r = radius * r / r.max()
    return np.concatenate([[0.0], r, [0.0]]), np.concatenate([[0.0], t * height, [height]])


def bowl_profile(rng: np.random.Generator, radius: float, height: float, n: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """An open bowl: base centre → foot → outer wall up to the rim → inner wall back down to the inner bottom
    centre (a closed outline for :func:`lathe_mesh`; the rim radius is ``radius``)."""
    wall = radius * rng.uniform(0.06, 0.1)
    foot = rng.uniform(0.35, 0.55)
    t = np.linspace(0.0, 1.0, n)
    outer_r = radius * (foot + (1 - foot) * np.sin(0.5 * math.pi * t) ** rng.uniform(0.6, 1.2))
    outer_z = height * t
    ti = t[::-1]
    inner_r = np.maximum(outer_r[::-1] - wall, 0.0) * ti**0.35
    inner_z = wall + (height - wall) * ti
    return np.concatenate([[0.0], outer_r, inner_r, [0.0]]), np.concatenate([[0.0], outer_z, inner_z, [wall]])


def lathe_mesh(radii: np.ndarray, heights: np.ndarray, segments: int = 64):
    """Revolve an outline ``(r(s), z(s))`` about +z (points with r = 0 become poles).

    Returns:
        vertices float32 [V, 3], faces int32 [F, 3] (outward for an outline that runs base → top on the outside),
        smooth vertex normals float32 [V, 3].
    """
    radii = np.asarray(radii, np.float64)
    heights = np.asarray(heights, np.float64)
    a = np.linspace(0.0, 2 * math.pi, segments, endpoint=False)
    rings = len(radii)
    verts = np.stack([radii[:, None] * np.cos(a)[None], radii[:, None] * np.sin(a)[None], np.broadcast_to(heights[:, None], (rings, segments))], -1)
    verts = verts.reshape(-1, 3)
    faces, normals = _smooth_normals(verts, np.asarray(_ring_faces(rings, segments), np.int32))  # the poles' slivers go
    return verts.astype(np.float32), faces, normals.astype(np.float32)
