"""Room layout from posed photos: the box of a room's walls, floor and ceiling, found by a photometric plane sweep.

A textureless wall's depth is not fixed by the photos at its own pixels (README, "Where the room's geometry goes
wrong"), and SIFT finds few points on it (``bench/bench_sparse_planes.py``). Its *position* is fixed elsewhere,
though: the paintings hung on it, the line where it meets the floor, the ceiling and the next wall, and the
shading across it all line up between the photos only when the wall is placed where it is. Most rooms people
photograph in a museum are boxes (Manhattan world); on validation gallery 1000001, with its ground-truth room box,
98 % of the pixels of the photos' textureless regions lie on the box within 5 cm (scoring only, 2026-11-28).

:func:`fit_room_layout` estimates the box:

1. **Axes.** Up is :func:`toolkit.upright.estimate_world_up` (cameras, and the sparse points' dominant plane where
   it agrees with them: a few degrees of tilt put a 5 m room's walls and floor 10-20 cm off). The
   horizontal axes are the room's yaw from the photos' straight edges (:func:`line_yaw`: each segment of a
   horizontal 3D line votes for its direction), or, where those give no clear peak, the rotation about up whose
   coordinate histograms of the sparse points are sharpest (points on a wall share one coordinate); either way the
   result does not depend on the input's frame.
2. **Sweep.** Each of the six faces is moved, one at a time (coordinate descent: ``rounds`` coarse passes over
   ``candidates`` geometric offsets, then one fine pass over ``fine`` linear offsets round each minimum), beyond
   the outermost camera (a room holds its cameras). For each offset every view's box depth map is computed, the
   view's pixels are carried through it into its neighbour views, and the mean truncated colour difference of the
   pixels that land in view is the cost. Offsets that keep fewer than ``min_valid`` of the sweep's best share of
   pixels in view are skipped (a face pressed against the cameras would otherwise look cheap). The cheapest
   offset is kept.
3. **Cross-check.** A second fit on high-passed images (``highpass``). A glossy surface's reflections line up
   between the photos behind it and can draw a face there; where the high-passed fit puts a face clearly nearer
   the cameras, that position is taken.
4. **Confidence.** A face counts only where the cost rises by ``min_contrast`` (relative) both ``rise_ratio``
   times nearer the cameras and ``rise_ratio`` times farther than its minimum, and ``min_pixels`` of the pixels
   leave the box through it. Pixels whose ray leaves through a face that does not count get no target.

:func:`layout_depth_targets` turns the box into per-pixel depth targets for the pixels of the photos' textureless
regions (:func:`toolkit.regions.textureless_regions`), in the format of :func:`toolkit.bounds.sparse_depth_targets`.
No ground truth is read anywhere here.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ._checks import ConfigError
from .defaults import YAW_FROM_DEFAULT
from .cameras import Cameras, generate_rays

__all__ = ["LayoutConfig", "RoomLayout", "fit_room_layout", "layout_depth_targets", "face_normals", "box_depth",
           "line_yaw", "plot_layout"]

FACE_NAMES = ("-a", "+a", "-b", "+b", "floor", "ceiling")
"""Faces in the order of :attr:`RoomLayout.offsets`: the two horizontal axes' low and high sides, then along up."""


@dataclass(frozen=True)
class LayoutConfig:
    """Options of :func:`fit_room_layout`."""

    max_side: int = 128
    """Photos are reduced to this longest side for the sweep."""
    max_views: int = 32
    """Views used (evenly spaced)."""
    stride: int = 2
    """Every ``stride``-th pixel of each reduced photo (in both directions) is carried into its neighbours; the
    neighbours are sampled at full reduced size. 1: every pixel (the fit as first landed, ~4× slower)."""
    neighbours: int = 3
    """Neighbour views each view is compared with."""
    candidates: int = 24
    """Offsets tried per face in a coarse round (geometric spacing beyond the outermost camera)."""
    fine: int = 20
    """Offsets tried per face in the final, fine round (linear, one coarse step either side of the minimum)."""
    range_scale: float = 3.0
    """The sweep reaches this many scene scales (median camera-to-point distance) beyond the outermost camera."""
    rounds: int = 1
    """Coarse coordinate-descent passes over the six faces (then one fine pass)."""
    truncate: float = 0.1
    """Colour differences are truncated here (occluders and specular highlights are outliers, not evidence)."""
    min_contrast: float = 0.05
    """A face counts when the cost rises by this fraction of its minimum on both sides: at offsets
    ``rise_ratio`` times nearer the cameras and ``rise_ratio`` times farther (a flat side means the face may lie
    anywhere there: a ceiling above the photos' view, a wall the photos only show blank, open sky). Measured
    (2026-11-28): faces that exist rose by 0.10-1.97 (the walls, floors and ceiling of galleries 1000000 and
    1000001, the sample's wall and floor, the fox's wallpaper wall, the synthetic room of the tests); the open top
    of gallery 1000000, which has no ceiling, by 0.0135, and counted at the earlier 0.01.

    A known weakness (2026-11-29): the rise is read off the coarse round's curve, where the faces swept after this
    one were still at their starting places, against the final box's cost. That overstates the rise of the faces
    swept first: gallery 1000002's misplaced south wall (before ``highpass``) showed 0.24 while its own curve
    varied by < 1 %. Measuring the rise with the final box, on the face's own pixels, is the honest version, but it
    also called correct blank walls flat on these scenes; it is not calibrated yet."""
    rise_ratio: float = 1.3
    """See ``min_contrast``."""
    min_valid: float = 0.8
    """Offsets whose pixels stay in their neighbours' views less than this fraction of the sweep's best are
    skipped."""
    blur: float = 1.0
    """Gaussian blur (σ, pixels of the sweep's images) before comparing: a wider basin round the true offset."""
    highpass: float = 1 / 16
    """A second fit, on each image minus its Gaussian blur of this σ (a fraction of the sweep images' longest side:
    8 px at 128), cross-checks the first; 0: off. A glossy surface shows blurred reflections of the room, and a
    reflection lines up between the photos at the depth of what it reflects, *behind* the surface: with colours
    alone the sweep followed it, and placed the dark (base colour 0.03-0.05), roughness-0.5 south wall of
    validation gallery 1000002 0.72 m too far (24.6 % of that scene's targets > 50 cm off). The blurred reflections
    are low frequencies, and the high-passed fit put that wall within 5 cm; but sharp reflections stay, and it put
    the same gallery's glossy stone floor 3 m too low (probably the ceiling openings' sharp reflections in it).
    Both failures lie *behind* the surface, so a face takes the high-passed fit's position only where that is
    nearer the cameras by more than ``band_tolerance``; elsewhere the colour fit's stands. :attr:`RoomLayout.band`
    says which fit each face took."""
    band_tolerance: float = 0.05
    """See ``highpass``; a fraction of the scene scale (median camera-to-point distance: 0.18-0.21 m on the
    validation galleries), above the 6-10 cm the two fits differ by on faces both place right (gallery 1000001)."""
    min_pixels: float = 0.01
    """... and at least this fraction of the sweep's pixels leave the box through it."""
    yaw_from: str = YAW_FROM_DEFAULT
    """How the horizontal axes are found: ``"lines"`` — the photos' straight edges (:func:`line_yaw`: every
    segment of a horizontal 3D line votes for its direction; picture rails, frames, the walls' feet), falling back
    to the points where the edges give no clear peak; ``"points"`` — the sharpest histograms of the sparse points'
    coordinates (the only way before 2026-12-05). Measured (2026-12-05, scoring only, the eight validation
    galleries, their worlds also turned by 17.3°, 41.1° and 63.7° about up; ``max_views`` photos): the edges' yaw
    within 0.17° of the generator's walls in all 32 cases (0.10° on the mean), the points' up to 2.4° off (gallery
    1000006, 737 points: 1.5° in its own frame, which put its walls ±13 cm off at their ends)."""
    min_line_peak: float = 5.0
    """The edges' yaw is used when its histogram's peak is at least this many times its median (the eight
    validation galleries: 38-102); below it, or with fewer than 20 segments, the points decide."""

    def __post_init__(self):
        if (self.max_side < 16 or self.max_views < 2 or self.neighbours < 1 or self.candidates < 4 or self.fine < 2
                or self.rounds < 1 or self.rise_ratio <= 1 or not 1 <= self.stride <= 8
                or self.yaw_from not in ("lines", "points") or self.min_line_peak < 1):
            raise ConfigError("LayoutConfig: need max_side >= 16, max_views >= 2, neighbours >= 1, candidates >= 4, "
                              "fine >= 2, rounds >= 1, rise_ratio > 1, 1 <= stride <= 8, yaw_from 'lines' or "
                              "'points', min_line_peak >= 1")
        if (self.range_scale <= 0 or self.truncate <= 0 or self.min_contrast < 0 or not 0 <= self.min_pixels < 1
                or not 0 <= self.highpass <= 1 or self.band_tolerance < 0):
            raise ConfigError("LayoutConfig: need range_scale > 0, truncate > 0, min_contrast >= 0, "
                              "0 <= min_pixels < 1, 0 <= highpass <= 1, band_tolerance >= 0")


@dataclass
class RoomLayout:
    """A room box in the scene's frame: ``origin + axes.T @ q`` for box coordinates ``q`` in ``[lo, hi]``."""

    origin: np.ndarray
    """float [3] the box frame's origin (world)."""
    axes: np.ndarray
    """float [3, 3] rows: the two horizontal axes and up (world, orthonormal)."""
    lo: np.ndarray
    """float [3] the low faces' coordinates."""
    hi: np.ndarray
    """float [3] the high faces' coordinates."""
    confident: np.ndarray
    """bool [6] which faces count (order :data:`FACE_NAMES`)."""
    contrast: np.ndarray
    """float [6] each face's cost contrast (see :class:`LayoutConfig`)."""
    coverage: np.ndarray
    """float [6] the fraction of the sweep's pixels that leave the box through each face."""
    photos: int = 0
    """How many photos the box was fitted from (the sweep uses at most ``LayoutConfig.max_views`` of them)."""
    curves: list = field(default_factory=list)
    """Per face: (offsets, costs) of the coarse round's sweep, for plots."""
    band: list = field(default_factory=list)
    """Per face: which fit placed it, "colour" or "high-pass" (:attr:`LayoutConfig.highpass`); empty: unknown."""
    yaw: str = ""
    """What set the horizontal axes: "lines" (the photos' edges), "points" (the sparse points), "cameras" (too few
    points; the frame of up); empty: unknown (a box recorded before 2026-12-05)."""

    def planes(self, confident_only: bool = True) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """The box's faces as world planes ``n · x = c``: (normals float [P, 3], offsets float [P], names), in the
        order of :data:`FACE_NAMES`; only the faces that count unless ``confident_only`` is False."""
        normals, offsets, names = [], [], []
        for j, name in enumerate(FACE_NAMES):
            if confident_only and not self.confident[j]:
                continue
            k = j // 2
            q = self.lo[k] if j % 2 == 0 else self.hi[k]
            normals.append(self.axes[k])
            offsets.append(q + float(self.axes[k] @ self.origin))
            names.append(name)
        return np.asarray(normals, np.float64).reshape(-1, 3), np.asarray(offsets, np.float64), names

    def to_json(self) -> dict:
        faces = {n: {"confident": bool(c), "contrast": round(float(k), 4), "coverage": round(float(v), 4)}
                 for n, c, k, v in zip(FACE_NAMES, self.confident, self.contrast, self.coverage)}
        for n, b in zip(FACE_NAMES, self.band):
            faces[n]["band"] = b
        return {"origin": self.origin.tolist(), "axes": self.axes.tolist(), "lo": self.lo.tolist(),
                "hi": self.hi.tolist(), "photos": int(self.photos), "yaw": self.yaw, "faces": faces}

    @classmethod
    def from_json(cls, d: dict) -> "RoomLayout":
        """The box :meth:`to_json` wrote (a run's ``config.json`` key ``room_layout``); ``curves`` are not kept.

        Raises:
            ConfigError: a record without the box's keys or faces."""
        try:
            faces = [d["faces"][n] for n in FACE_NAMES]
            return cls(origin=np.asarray(d["origin"], np.float64).reshape(3),
                       axes=np.asarray(d["axes"], np.float64).reshape(3, 3),
                       lo=np.asarray(d["lo"], np.float64).reshape(3), hi=np.asarray(d["hi"], np.float64).reshape(3),
                       confident=np.array([bool(f["confident"]) for f in faces]),
                       contrast=np.array([float(f["contrast"]) for f in faces]),
                       coverage=np.array([float(f["coverage"]) for f in faces]), photos=int(d.get("photos", 0)),
                       band=[str(f["band"]) for f in faces] if all("band" in f for f in faces) else [],
                       yaw=str(d.get("yaw", "")))
        except (KeyError, TypeError, ValueError) as e:
            raise ConfigError(f"not a room layout record (origin, axes, lo, hi and the faces {', '.join(FACE_NAMES)} "
                              f"expected): {e!r}") from e


def _frame_from_up(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0, 0]) if abs(up[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = a - (a @ up) * up
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1)


def _sharpness(x: np.ndarray, b: float) -> float:
    h = np.bincount(np.floor((x - x.min()) / b).astype(int)).astype(float)
    return float((h ** 2).sum()) / max(len(x), 1) ** 2


def line_yaw(scene, up: np.ndarray, views=None, step: float = 0.25, min_length: float = 8.0,
             min_tilt_deg: float = 5.0, load=None) -> tuple[float, float, int]:
    """The room's yaw from the photos' straight edges (Manhattan world): (angle in degrees in [-45, 45) of the
    walls' direction from :func:`_frame_from_up`'s first axis, the histogram's peak over its median, segments used).

    Each line segment (OpenCV's LSD, at least ``min_length`` px) spans a plane through its camera's centre, with
    normal n. If the segment is a horizontal 3D line, its direction is ``n × up``; its angle about up, taken modulo
    90°, votes with the segment's length. Segments whose plane is within ``min_tilt_deg`` of vertical may be vertical
    lines (whose ``n × up`` is any direction) and do not vote; a segment at eye height, whose plane is horizontal,
    gives no direction either. Walls, the lines where they meet the floor and ceiling, frames, rails and cases all
    vote for the room's two axes; other edges spread. The histogram (``step`` degrees) is smoothed (σ = 2 bins) and
    its peak refined by a parabola through the three bins round it. Returns (nan, 0, n) where nothing votes.
    ``load(v)``: view ``v``'s photo as a float tensor [C, H, W] (default ``scene.load_image``; every view is loaded
    once, in order)."""
    import cv2

    e1, e2 = _frame_from_up(up)
    c = scene.cameras
    cams = Cameras(c.c2w.double(), c.fx.double(), c.fy.double(), c.cx.double(), c.cy.double(), c.width, c.height)
    lsd = cv2.createLineSegmentDetector()
    nb = int(round(90.0 / step))
    hist = np.zeros(nb)
    used = 0
    sin_tilt = np.sin(np.deg2rad(min_tilt_deg))
    for v in (range(len(scene)) if views is None else views):
        img = (scene.load_image(int(v)) if load is None else load(int(v))).float().clamp(0, 1)
        grey = (img.mean(0) * 255).round().to(torch.uint8).numpy()  # RGB or one channel
        segs = lsd.detect(grey)[0]
        if segs is None:
            continue
        segs = segs.reshape(-1, 4).astype(np.float64)
        length = np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1])
        keep = length >= min_length
        segs, length = segs[keep], length[keep]
        if not len(segs):
            continue
        px = torch.from_numpy(np.concatenate([segs[:, :2], segs[:, 2:]], 0))  # LSD and generate_rays: centres at k
        d = generate_rays(cams, int(v), pixels=px).directions.numpy()
        n = np.cross(d[:len(segs)], d[len(segs):])
        n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
        h = np.cross(n, up)
        ok = (np.abs(n @ up) > sin_tilt) & (np.linalg.norm(h, axis=1) > 1e-6)
        ang = np.degrees(np.arctan2(h[ok] @ e2, h[ok] @ e1)) % 90.0
        np.add.at(hist, (ang / step).astype(int) % nb, length[ok])
        used += int(ok.sum())
    if used == 0:
        return float("nan"), 0.0, used
    k = np.arange(-6, 7)
    w = np.exp(-0.5 * (k / 2.0) ** 2)
    sm = sum(wi * np.roll(hist, -ki) for ki, wi in zip(k, w))  # circular smoothing (angles mod 90°)
    i = int(np.argmax(sm))
    a, b, cc = sm[(i - 1) % nb], sm[i], sm[(i + 1) % nb]
    den = a - 2 * b + cc
    off = 0.5 * (a - cc) / den if den < 0 else 0.0
    angle = ((i + 0.5 + off) * step + 45.0) % 90.0 - 45.0  # the turn of the frame's axes nearest them, in [-45, 45)
    med = float(np.median(sm))
    return float(angle), float(sm[i] / med) if med > 0 else float("inf"), used


def _axes_at(up: np.ndarray, angle: float) -> np.ndarray:
    """Rows: :func:`_frame_from_up`'s horizontal axes turned by ``angle`` (radians) about up, and up."""
    e1, e2 = _frame_from_up(up)
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * e1 + s * e2, -s * e1 + c * e2, up])


def _horizontal_axes(points: np.ndarray, up: np.ndarray, scale: float) -> np.ndarray:
    """Rows: the two horizontal axes (sharpest point histograms, 0.5° steps) and up."""
    e1, e2 = _frame_from_up(up)
    if len(points) < 10:
        return np.stack([e1, e2, up])
    X = points - np.median(points, 0)
    x1, x2 = X @ e1, X @ e2
    b = 0.005 * scale
    best, th_best = -1.0, 0.0
    for th in np.deg2rad(np.arange(0.0, 90.0, 0.5)):
        c, s = np.cos(th), np.sin(th)
        v = _sharpness(c * x1 + s * x2, b) + _sharpness(-s * x1 + c * x2, b)
        if v > best:
            best, th_best = v, th
    return _axes_at(up, th_best)


def box_depth(layout: RoomLayout, origins: torch.Tensor, dirs: torch.Tensor):
    """Distance along each ray to where it leaves the box, and the face it leaves through.

    Args:
        origins: float [..., 3] world ray origins (inside the box). dirs: float [..., 3] unit world directions.
    Returns:
        (t float [...], face int64 [...] in :data:`FACE_NAMES` order).
    """
    axes = torch.as_tensor(layout.axes, dtype=dirs.dtype, device=dirs.device)
    org = torch.as_tensor(layout.origin, dtype=dirs.dtype, device=dirs.device)
    lo = torch.as_tensor(layout.lo, dtype=dirs.dtype, device=dirs.device)
    hi = torch.as_tensor(layout.hi, dtype=dirs.dtype, device=dirs.device)
    d, pos = _box_dirs(dirs @ axes.T)
    return _box_exit((origins - org) @ axes.T, d, pos, lo, hi)


def _box_dirs(d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Ray directions in the box's frame, kept off zero, and whether each component points to the ``hi`` face."""
    return torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d), d > 0


def _box_exit(o: torch.Tensor, d: torch.Tensor, pos: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor):
    """(distance, face) where rays from ``o`` along ``d`` (both in the box's frame; ``d`` from :func:`_box_dirs`)
    leave the box ``lo``..``hi``."""
    t = torch.where(pos, (hi - o) / d, (lo - o) / d)
    t = torch.where(t > 0, t, torch.full_like(t, float("inf")))
    tmin, k = t.min(-1)
    side = torch.gather(pos.long(), -1, k[..., None])[..., 0]
    return tmin, 2 * k + side


def _sweep_image(im: torch.Tensor, cfg: LayoutConfig) -> torch.Tensor:
    """A photo [C, H, W] as the sweep compares it: float, area-downsized to ``cfg.max_side`` on its long side."""
    im = im.float()
    h, w = im.shape[1:]
    s = min(1.0, cfg.max_side / max(h, w))
    if s < 1.0:
        im = F.interpolate(im[None], size=(max(1, round(h * s)), max(1, round(w * s))), mode="area")[0]
    return im


class _Sweep:
    """Photometric cost of a box hypothesis over view pairs (small images, all pixels).

    The box's frame is fixed during a fit, so everything but the distance along each ray is computed once: the rays
    in the box's frame, and, per view pair (i, j), ``(o_i - c_j) R_j`` and ``d_i R_j`` — the point ``o_i + t d_i``
    lands at ``(o_i - c_j) R_j + t d_i R_j`` in camera j. A cost is then a few elementwise passes and one
    ``grid_sample`` (float32: the projections are of metres at 128 px, far inside its precision)."""

    def __init__(self, scene, views: np.ndarray, cfg: LayoutConfig, layout: "RoomLayout", images=None):
        """``images``: the views' photos already at :func:`_sweep_image` size (one per view, in order), else each
        is read from ``scene``."""
        from .sampling import neighbour_views

        cams = scene.cameras[views.tolist()]
        imgs = list(images) if images is not None else [_sweep_image(scene.load_image(int(v)), cfg) for v in views]
        H, W = imgs[0].shape[1:]
        if any(im.shape[1:] != (H, W) for im in imgs):
            imgs = [F.interpolate(im[None], size=(H, W), mode="area")[0] for im in imgs]
        img = torch.stack(imgs)  # [V, 3, H, W]
        if cfg.blur > 0:
            from .metrics import gaussian_blur

            img = gaussian_blur(img.flatten(0, 1), cfg.blur).view_as(img)
        sx, sy = W / cams.width.double(), H / cams.height.double()
        small = Cameras(cams.c2w.double(), cams.fx.double() * sx, cams.fy.double() * sy, cams.cx.double() * sx,
                        cams.cy.double() * sy, torch.full_like(cams.width, W), torch.full_like(cams.height, H))
        K, c2w = small.intrinsics(), small.c2w
        dirs = generate_rays(small).directions.reshape(len(views), H * W, 3).double()  # every pixel, row-major
        s = cfg.stride  # the pixels carried: every s-th row and column, from the middle of the first s x s cell
        rows, cols = torch.arange(s // 2, H, s), torch.arange(s // 2, W, s)
        keep = (rows[:, None] * W + cols[None, :]).reshape(-1)
        dirs = dirs[:, keep]
        origins = c2w[:, :3, 3]
        nb = neighbour_views(cams, min(cfg.neighbours, len(views) - 1))
        pi = torch.arange(len(views)).repeat_interleave(nb.shape[1])
        pj = nb.reshape(-1).long()
        axes = torch.as_tensor(layout.axes, dtype=torch.float64)
        org = torch.as_tensor(layout.origin, dtype=torch.float64)
        self.o_box = ((origins - org) @ axes.T)[:, None, :].float()  # [V, 1, 3] ray origins in the box's frame
        d_box, self.pos = _box_dirs(dirs @ axes.T)
        self.d_box = d_box.float()
        rot = c2w[pj, :3, :3]
        self.a = ((origins[pi] - c2w[pj, :3, 3])[:, None, :] @ rot).float()  # [Np, 1, 3]
        self.b = (dirs[pi] @ rot).float()  # [Np, P, 3]
        self.fx, self.cx = K[pj, 0, 0, None].float(), K[pj, 0, 2, None].float()
        self.fy, self.cy = K[pj, 1, 1, None].float(), K[pj, 1, 2, None].float()
        self.pi, self.pj, self.H, self.W, self.keep, self.img = pi, pj, H, W, keep, img
        self.img_j = img[pj]  # [Np, 3, H, W]
        self.target = img.flatten(2)[:, :, keep][pi]  # [Np, 3, P]
        self.truncate = cfg.truncate

    def high_passed(self, sigma: float) -> "_Sweep":
        """The same sweep on each image minus its Gaussian blur of σ = ``sigma`` × the images' longest side."""
        from .metrics import gaussian_blur

        img = self.img - gaussian_blur(self.img.flatten(0, 1), sigma * max(self.H, self.W)).view_as(self.img)
        out = copy.copy(self)
        out.img, out.img_j, out.target = img, img[self.pj], img.flatten(2)[:, :, self.keep][self.pi]
        return out

    def cost(self, lo: np.ndarray, hi: np.ndarray) -> tuple[float, np.ndarray, float]:
        """(mean truncated colour difference of the pixels carried into a neighbour's view, the fraction of pixels
        leaving the box through each face, the fraction of pixel pairs in view)."""
        lo_, hi_ = torch.as_tensor(lo, dtype=torch.float32), torch.as_tensor(hi, dtype=torch.float32)
        t, face = _box_exit(self.o_box, self.d_box, self.pos, lo_, hi_)  # [V, P]
        ti = t[self.pi]
        rel = self.a + ti[..., None] * self.b  # [Np, P, 3]: the points in the neighbour's camera frame
        z = -rel[..., 2]
        inv_z = 1.0 / z.clamp_min(1e-9)  # points behind the camera are masked below
        u = (self.fx * rel[..., 0] * inv_z + self.cx) * (2.0 / self.W) - 1.0  # grid_sample's [-1, 1]
        v = (-self.fy * rel[..., 1] * inv_z + self.cy) * (2.0 / self.H) - 1.0
        ok = (z > 0) & (u >= -1) & (u <= 1) & (v >= -1) & (v <= 1) & torch.isfinite(ti)
        grid = torch.stack([u, v], -1).masked_fill_(~ok[..., None], 0.0)
        sampled = F.grid_sample(self.img_j, grid[:, None], mode="bilinear", padding_mode="border",
                                align_corners=False)[:, :, 0]
        err = (sampled - self.target).abs().mean(1).clamp_max(self.truncate)
        n = ok.sum()
        c = float((err * ok).sum() / n.clamp_min(1)) if n > 0 else float("inf")
        cover = np.bincount(face.reshape(-1).numpy(), minlength=6) / face.numel()
        return c, cover, float(n) / ok.numel()


def fit_room_layout(scene, points: np.ndarray | None = None, cfg: LayoutConfig = LayoutConfig(), log=None,
                    up: np.ndarray | None = None) -> RoomLayout:
    """Estimate the room's box from posed photos (see the module docstring).

    Args:
        scene: a :class:`toolkit.scene.Scene` (train split).
        points: float [P, 3] sparse points (:func:`toolkit.bounds.triangulate_sparse_points`); None: triangulated.
        cfg: options.
        log: optional callable for progress lines.
        up: optional unit world up; default :func:`toolkit.upright.estimate_world_up`.
    Returns:
        :class:`RoomLayout`; faces without a clear photometric minimum have ``confident`` False.
    """
    from .bounds import camera_point_distance
    from .upright import estimate_world_up

    c2w = scene.cameras.c2w.double().numpy()
    cams = c2w[:, :3, 3]
    if points is None:
        from .bounds import triangulate_sparse_points

        points = triangulate_sparse_points(scene, log=log).points
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if up is None:
        up = estimate_world_up(c2w, points if len(points) >= 10 else None).up
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    if len(points) >= 10:
        scale = camera_point_distance(points, cams)
    else:
        scale = float(np.median(np.linalg.norm(cams - cams.mean(0), axis=-1))) or 1.0
    views = np.unique(np.linspace(0, len(scene) - 1, min(len(scene), cfg.max_views)).round().astype(int))
    axes, yaw = _horizontal_axes(points, up, scale), ("points" if len(points) >= 10 else "cameras")
    small: list[torch.Tensor] = []  # the sweep's images, kept small as the edge yaw reads each photo once

    def load(v: int) -> torch.Tensor:
        img = scene.load_image(v)
        small.append(_sweep_image(img, cfg))
        return img

    if cfg.yaw_from == "lines":
        angle, peak, segments = line_yaw(scene, up, views, load=load)
        if np.isfinite(angle) and segments >= 20 and peak >= cfg.min_line_peak:
            axes, yaw = _axes_at(up, np.deg2rad(angle)), "lines"
        if log is not None:
            log(f"[dars] room layout: yaw from {yaw}" + (f" ({segments} edge segments, peak {peak:.1f}x the median, "
                                                      f"{angle:.2f} deg)" if np.isfinite(angle) else
                                                      " (the photos' edges gave no direction)"))
    origin = cams.mean(0)
    qc = (cams - origin) @ axes.T
    cmin, cmax = qc.min(0), qc.max(0)
    margin = 0.02 * scale
    steps = np.geomspace(0.02, cfg.range_scale, cfg.candidates) * scale
    lo, hi = cmin - margin - steps[0], cmax + margin + steps[0]
    if len(points) >= 10:  # start from the points' robust extremes (beyond the cameras)
        qp = (points - origin) @ axes.T
        lo = np.minimum(lo, np.percentile(qp, 1, axis=0))
        hi = np.maximum(hi, np.percentile(qp, 99, axis=0))
    layout = RoomLayout(origin=origin, axes=axes, lo=lo.copy(), hi=hi.copy(), confident=np.zeros(6, bool),
                        contrast=np.zeros(6), coverage=np.zeros(6), photos=len(scene), yaw=yaw)
    sweep = _Sweep(scene, views, cfg, layout, images=small if len(small) == len(views) else None)
    # per face: the outermost camera's coordinate and the margin; the sweep's offsets are distances beyond it
    ext = [cmax[f // 2] + margin if f % 2 else cmin[f // 2] - margin for f in range(6)]

    def fit(sweep: _Sweep, band: str) -> tuple:
        lo_, hi_ = lo.copy(), hi.copy()

        def sweep_face(f, offs):
            k, side = divmod(f, 2)
            costs, valid = [], []
            for o in offs:
                lo2, hi2 = lo_.copy(), hi_.copy()
                (hi2 if side else lo2)[k] = o
                c, _, v = sweep.cost(lo2, hi2)
                costs.append(c)
                valid.append(v)
            costs, valid = np.array(costs), np.array(valid)
            # a face pressed against the cameras carries its pixels out of the neighbours' views, and the few pixels
            # left compare well: offsets that keep too few pixels in view are not candidates
            return np.where(valid >= cfg.min_valid * valid.max(), costs, np.inf)

        curves = [None] * 6
        for rnd in range(cfg.rounds + 1):
            for f in range(6):
                k, side = divmod(f, 2)
                sgn = 1.0 if side else -1.0
                if rnd < cfg.rounds:  # coarse: geometric offsets beyond the outermost camera
                    dist = steps
                else:  # fine: linear offsets round the coarse minimum, one coarse step either side
                    d0 = abs((hi_ if side else lo_)[k] - ext[f])
                    j = int(np.argmin(np.abs(steps - d0)))
                    a, b = steps[max(j - 1, 0)], steps[min(j + 1, len(steps) - 1)]
                    dist = np.unique(np.concatenate([np.linspace(a, b, cfg.fine), [d0]]))
                offs = ext[f] + sgn * dist
                costs = sweep_face(f, offs)
                j = int(np.argmin(costs))
                (hi_ if side else lo_)[k] = offs[j]
                if rnd < cfg.rounds:
                    curves[f] = (offs, costs)
            if log is not None:
                log(f"[dars] room layout ({band}) pass {rnd + 1}/{cfg.rounds + 1}: "
                    f"size {np.round(hi_ - lo_, 2).tolist()}")
        cmin_, _, _ = sweep.cost(lo_, hi_)  # the fitted box
        contrast = np.zeros(6)
        for f in range(6):  # confidence from the coarse curve: the cost must rise on both sides of the minimum
            k, side = divmod(f, 2)
            offs, costs = curves[f]
            dist = np.abs(offs - ext[f])
            d0 = abs((hi_ if side else lo_)[k] - ext[f])
            o = np.argsort(dist)
            o = o[np.isfinite(costs[o])]
            at = np.interp([d0 / cfg.rise_ratio, d0 * cfg.rise_ratio], dist[o], costs[o], left=np.nan, right=np.nan)
            rise_near, rise_far = (at - cmin_) / max(cmin_, 0.01 * cfg.truncate)  # blank photos: no rise at all
            rise_near, rise_far = (0.0 if not np.isfinite(r) else float(r) for r in (rise_near, rise_far))
            contrast[f] = min(rise_near, rise_far)
        return lo_, hi_, curves, contrast

    lo, hi, curves, contrast = fit(sweep, "colour")
    band = ["colour"] * 6
    if cfg.highpass > 0:  # the cross-check: where the high-passed fit puts a face clearly nearer, it is taken
        lo_h, hi_h, curves_h, contrast_h = fit(sweep.high_passed(cfg.highpass), "high-pass")
        for f in range(6):
            k, side = divmod(f, 2)
            near, near_h = abs((hi if side else lo)[k] - ext[f]), abs((hi_h if side else lo_h)[k] - ext[f])
            if near - near_h > cfg.band_tolerance * scale:
                (hi if side else lo)[k] = (hi_h if side else lo_h)[k]
                curves[f], contrast[f], band[f] = curves_h[f], contrast_h[f], "high-pass"
    _, coverage, _ = sweep.cost(lo, hi)
    layout.lo, layout.hi, layout.curves, layout.coverage, layout.contrast = lo, hi, curves, coverage, contrast
    layout.confident = (contrast >= cfg.min_contrast) & (coverage >= cfg.min_pixels)
    layout.band = band
    return layout


def face_normals(layout: RoomLayout) -> np.ndarray:
    """float [6, 3] the inward unit normal of each face (:data:`FACE_NAMES` order, world): a low face's is its axis,
    a high face's the axis negated (the floor's is up, the ceiling's down)."""
    axes = np.asarray(layout.axes, np.float64)
    return np.stack([axes[f // 2] * (1.0 if f % 2 == 0 else -1.0) for f in range(6)])


def layout_depth_targets(scene, layout: RoomLayout, regions=None) -> dict[str, torch.Tensor]:
    """Depth targets for the pixels of the photos' textureless regions whose ray leaves the box through a face
    that counts; the format of :func:`toolkit.bounds.sparse_depth_targets` (depth along the camera axis), plus
    ``normal``: float [N, 3] the inward unit normal of the face each pixel's ray leaves through (world), the target
    of ``losses.layout_normal``.

    ``regions``: optional callable, view index -> label map or bool mask [H, W] of its textureless pixels (nonzero);
    default :func:`toolkit.regions.textureless_regions` of the decoded photo."""
    from .regions import textureless_regions

    c = scene.cameras
    cams = Cameras(c.c2w.double(), c.fx.double(), c.fy.double(), c.cx.double(), c.cy.double(), c.width, c.height)
    conf = torch.as_tensor(layout.confident)
    inward = torch.from_numpy(face_normals(layout)).float()
    out = {"views": [], "rows": [], "cols": [], "depth": [], "normal": []}
    for v in range(len(scene)):
        reg = textureless_regions(scene.load_image(v)) if regions is None else regions(v)
        rows, cols = np.nonzero(reg > 0)
        if not len(rows):
            continue
        rays = generate_rays(cams, v, pixels=torch.from_numpy(np.stack([cols, rows], -1)))
        t, face = box_depth(layout, rays.origins, rays.directions)
        ok = conf[face] & torch.isfinite(t)
        z = t * rays.z_scale  # distance along the ray -> depth along the camera axis
        out["views"].append(torch.full((int(ok.sum()),), v, dtype=torch.int64))
        out["rows"].append(torch.from_numpy(rows)[ok].long())
        out["cols"].append(torch.from_numpy(cols)[ok].long())
        out["depth"].append(z[ok].float())
        out["normal"].append(inward[face[ok]])
    if not out["views"]:
        return {"views": torch.zeros(0, dtype=torch.int64), "rows": torch.zeros(0, dtype=torch.int64),
                "cols": torch.zeros(0, dtype=torch.int64), "depth": torch.zeros(0), "normal": torch.zeros(0, 3)}
    return {k: torch.cat(v) for k, v in out.items()}


_FACE_COLOURS = np.array([[0.90, 0.30, 0.25], [0.95, 0.65, 0.15], [0.30, 0.70, 0.30], [0.25, 0.55, 0.90],
                          [0.60, 0.40, 0.80], [0.20, 0.80, 0.80]])
"""A colour per face (:data:`FACE_NAMES` order) for :func:`plot_layout`."""


def plot_layout(scene, layout: RoomLayout, path, views: int = 6) -> None:
    """A figure a person can judge the box by, written to ``path`` (PNG, atomically).

    Top row: each face's sweep (cost against the face's coordinate; the chosen offset marked; whether the face
    counts, and its contrast and share of pixels). Bottom row: ``views`` photos spread over the capture, each pixel
    tinted by the face its ray leaves the box through (faces that count only), with the box's edges drawn where the
    face changes: on a good fit they run along the room's corners and the walls' feet."""
    from .report import _plt, _save

    plt = _plt()
    n = max(1, min(int(views), len(scene)))
    fig, axs = plt.subplots(2, max(6, n), figsize=(2.6 * max(6, n), 5.6), squeeze=False)
    for f, name in enumerate(FACE_NAMES):
        ax = axs[0, f]
        curve = layout.curves[f] if f < len(layout.curves) and layout.curves[f] is not None else None
        if curve is not None:
            offs, costs = (np.asarray(c, np.float64) for c in curve)
            ok = np.isfinite(costs)
            ax.plot(offs[ok], costs[ok], ".-", color=_FACE_COLOURS[f], lw=1)
            ax.axvline((layout.hi if f % 2 else layout.lo)[f // 2], color="k", lw=0.8, ls="--")
        fit = f" ({layout.band[f]})" if f < len(layout.band) else ""
        ax.set_title(f"{name}: {'counts' if layout.confident[f] else 'no face'}{fit}\n"
                     f"contrast {layout.contrast[f]:.2f}, px {100 * layout.coverage[f]:.0f} %", fontsize=8)
        ax.tick_params(labelsize=6)
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.set_xlabel("face coordinate (scene units)", fontsize=6)
    axs[0, 0].set_ylabel("photometric cost", fontsize=7)
    for j in range(6, axs.shape[1]):
        axs[0, j].axis("off")
    conf = np.asarray(layout.confident, bool)
    for j, v in enumerate(np.unique(np.linspace(0, len(scene) - 1, n).round().astype(int))):
        img = scene.load_image(int(v)).permute(1, 2, 0).clamp(0, 1).numpy()
        h, w = img.shape[:2]
        rays = generate_rays(scene.cameras, [int(v)])
        _, face = box_depth(layout, rays.origins.double(), rays.directions.double())
        face = face.reshape(h, w).numpy()
        tint = np.where(conf[face][..., None], _FACE_COLOURS[face], img)
        out = 0.6 * img + 0.4 * tint
        edge = np.zeros((h, w), bool)
        edge[:, 1:] |= face[:, 1:] != face[:, :-1]
        edge[1:, :] |= face[1:, :] != face[:-1, :]
        out[edge] = 1.0
        axs[1, j].imshow(np.clip(out, 0.0, 1.0))  # float rounding: 1.0000000238 draws a warning
        axs[1, j].set_title(f"photo {int(v)}", fontsize=8)
    for ax in axs[1]:
        ax.axis("off")
    size = np.round(layout.hi - layout.lo, 2).tolist()
    fig.suptitle(f"room box {size} (scene units), fitted on {layout.photos} photos; tinted: faces that count",
                 fontsize=9)
    fig.tight_layout()
    _save(fig, Path(path))
