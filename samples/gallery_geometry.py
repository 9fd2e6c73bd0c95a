"""Gallery geometry: walls, primitive parts, obstacle boxes, camera paths and the constraints every procedural
gallery obeys (pure numpy). Conventions: see ``procedural.py``."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from gallery_config import (  # noqa: F401
    BACKGROUND, CLASSES, WALLS, CameraPlan, Exhibit, Fixture, GalleryConfig, Lamp, Lighting, Material, Painting, Pedestal,
    Room, Vec2, Vec3,
)

# -------------------------------------------------------------------------------------------------------- transforms
Xform = tuple
"""A transform recipe: ops applied right to left as in Mitsuba's ``T().translate(..).rotate(..).scale(..)``:
``("t", x, y, z)``, ``("r", ax, ay, az, deg)``, ``("s", x, y, z)``."""


def xform_matrix(ops: Xform) -> np.ndarray:
    """float64 [4, 4] of a recipe."""
    m = np.eye(4)
    for op in ops:
        if op[0] == "t":
            a = np.eye(4)
            a[:3, 3] = op[1:4]
        elif op[0] == "s":
            a = np.diag([op[1], op[2], op[3], 1.0])
        else:
            axis = np.asarray(op[1:4], np.float64)
            axis /= np.linalg.norm(axis)
            t = math.radians(op[4])
            K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
            a = np.eye(4)
            a[:3, :3] = np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * K @ K
        m = m @ a
    return m


# --------------------------------------------------------------------------------------------------------- geometry
def wall_frame(room: Room, wall: str) -> dict[str, Any]:
    """A wall's midpoint (at z = 0), inward normal, right axis, length, and yaw (the rotation about z that takes the
    north wall's frame to this one)."""
    (x0, x1), (y0, y1) = room.x, room.y
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    table = {
        "north": ((cx, y1), (0.0, -1.0), (1.0, 0.0), x1 - x0, 0.0),
        "east": ((x1, cy), (-1.0, 0.0), (0.0, -1.0), y1 - y0, -90.0),
        "south": ((cx, y0), (0.0, 1.0), (-1.0, 0.0), x1 - x0, 180.0),
        "west": ((x0, cy), (1.0, 0.0), (0.0, 1.0), y1 - y0, 90.0),
    }
    if wall not in table:
        raise ValueError(f"unknown wall {wall!r}: choose one of {WALLS}")
    mid, n, r, length, yaw = table[wall]
    return {"mid": np.array([mid[0], mid[1], 0.0]), "normal": np.array([n[0], n[1], 0.0]), "right": np.array([r[0], r[1], 0.0]),
            "length": float(length), "yaw": yaw}


def wall_point(room: Room, wall: str, u: float, z: float, offset: float = 0.0) -> np.ndarray:
    """World point at (u, z) on a wall, ``offset`` metres in front of it (into the room)."""
    f = wall_frame(room, wall)
    return f["mid"] + u * f["right"] + np.array([0.0, 0.0, z]) + offset * f["normal"]


@dataclass(frozen=True)
class Part:
    """A primitive of the scene: Mitsuba ``rectangle`` (local [−1, 1]², normal +z), ``cube`` ([−1, 1]³), ``sphere``
    (unit, at the origin) or ``mesh`` (generated from ``mesh``), placed by ``xform``."""

    name: str
    cls: str
    shape: Literal["rectangle", "cube", "sphere", "mesh"]
    xform: Xform
    material: Material
    mesh: tuple = ()
    """(generator, args...): ``("twisted", height, radius)``, ``("vase"|"bowl", seed, radius, height)``."""
    glass: Literal["", "case", "cover"] = ""
    """Glass kind (GT looks through it): the panes of a display ``case``, or a painting's ``cover``."""
    emission: Vec3 | None = None
    """Area-light radiance (before exposure), emitted on the +z side."""
    skylight: bool = False
    """A skylight diffuser: emits the probe's daylight (radiance set when the scene is built), on the +z side."""

    @property
    def metal(self) -> bool:
        """Counts toward the ``metal`` mask: metallic ≥ 0.5 and class frame, base or other."""
        return self.material.metallic >= 0.5 and self.cls in ("frame", "base", "other")


def _frame_parts(cfg: GalleryConfig, k: int, p: Painting, legacy: bool) -> list[Part]:
    room = cfg.room
    f = wall_frame(room, p.wall)
    yaw = f["yaw"]
    rz: Xform = () if yaw == 0.0 else (("r", 0.0, 0.0, 1.0, yaw),)
    u, z = p.center
    pw, ph = p.size[0] / 2, p.size[1] / 2
    fw, fd = p.frame_width, p.frame_depth
    name = (lambda s: s) if legacy else (lambda s: f"{s}_{k}")  # noqa: E731
    centre = wall_point(room, p.wall, u, z, p.canvas_inset)
    parts = [Part(name("painting"), "painting", "rectangle",
                  (("t", *centre.tolist()), *rz, ("r", 1.0, 0.0, 0.0, 90.0), ("s", pw, ph, 1.0)), p.canvas)]
    bars = {  # north-local (x along the wall, y out of it toward −y... i.e. depth, z up): centre offset, half extents
        "top": ((0.0, z + ph + fw / 2), (pw + fw, fd / 2, fw / 2)),
        "bottom": ((0.0, z - ph - fw / 2), (pw + fw, fd / 2, fw / 2)),
        "left": ((-pw - fw / 2, z), (fw / 2, fd / 2, ph)),
        "right": ((pw + fw / 2, z), (fw / 2, fd / 2, ph)),
    }
    for side, ((du, bz), half) in bars.items():
        c = wall_point(room, p.wall, u + du, bz, fd / 2)
        parts.append(Part(f"frame_{side}" if legacy else f"frame_{k}_{side}", "frame", "cube",
                          (("t", *c.tolist()), *rz, ("s", *half)), p.frame_material))
    if p.frame == "glass":
        c = wall_point(room, p.wall, u, z, fd - 0.004)
        parts.append(Part(f"cover_{k}", "painting", "rectangle", (("t", *c.tolist()), *rz, ("r", 1.0, 0.0, 0.0, 90.0), ("s", pw, ph, 1.0)),
                          Material(base_color=(1.0, 1.0, 1.0), roughness=0.0, bsdf="thindielectric"), glass="cover"))
    if p.plaque is not None:
        c = wall_point(room, p.wall, u + pw + fw + 0.12, z - ph + 0.06, 0.006)
        parts.append(Part(f"plaque_{k}", "other", "cube", (("t", *c.tolist()), *rz, ("s", 0.07, 0.006, 0.05)), p.plaque))
    return parts


def _room_parts(cfg: GalleryConfig) -> list[Part]:
    room = cfg.room
    (x0, x1), (y0, y1), h = room.x, room.y, room.height
    legacy = cfg.preset == "sample"
    eps = 0.0 if legacy else 0.02  # walls overlap outward at the corners: no cracks for light to leak through
    parts = []
    for wall, mat in zip(room.walls, room.wall_materials):
        f = wall_frame(room, wall)
        c = f["mid"] + np.array([0.0, 0.0, h / 2])
        rz = () if f["yaw"] == 0.0 else (("r", 0.0, 0.0, 1.0, f["yaw"]),)
        hz = h / 2 + eps + (room.well_depth / 2 if room.ceiling else 0.0)
        c[2] += room.well_depth / 2 if room.ceiling else 0.0
        parts.append(Part("wall" if legacy else f"wall_{wall}", "wall", "rectangle",
                          (("t", *c.tolist()), *rz, ("r", 1.0, 0.0, 0.0, 90.0), ("s", f["length"] / 2 + eps, hz, 1.0)), mat))
    parts.append(Part("floor", "floor", "rectangle",
                      (("t", (x0 + x1) / 2, (y0 + y1) / 2, 0.0), ("s", (x1 - x0) / 2 + eps, (y1 - y0) / 2 + eps, 1.0)), room.floor))
    if room.ceiling:
        for k, (a0, a1, b0, b1) in enumerate(_ceiling_cells(room)):
            parts.append(Part(f"ceiling_{k}", "wall", "rectangle",
                              (("t", (a0 + a1) / 2, (b0 + b1) / 2, h), ("r", 1.0, 0.0, 0.0, 180.0), ("s", (a1 - a0) / 2, (b1 - b0) / 2, 1.0)),
                              room.ceiling_material))
        d = room.well_depth
        diffuser = Material(base_color=(0.9, 0.9, 0.9), roughness=1.0)
        for k, (a0, a1, b0, b1) in enumerate(room.openings):  # frosted glazing at the top of each well, facing down
            parts.append(Part(f"skylight_{k}", "wall", "rectangle",
                              (("t", (a0 + a1) / 2, (b0 + b1) / 2, h + d + 0.002), ("r", 1.0, 0.0, 0.0, 180.0), ("s", (a1 - a0) / 2 + 0.01, (b1 - b0) / 2 + 0.01, 1.0)),
                              diffuser, skylight=True))
        for k, (a0, a1, b0, b1) in enumerate(room.openings if d > 0 else ()):
            sub = Room(x=(a0, a1), y=(b0, b1), height=d)
            for wall in WALLS:  # shaft walls face into the shaft
                f = wall_frame(sub, wall)
                c = f["mid"] + np.array([0.0, 0.0, h + d / 2])
                rz = () if f["yaw"] == 0.0 else (("r", 0.0, 0.0, 1.0, f["yaw"]),)
                parts.append(Part(f"well_{k}_{wall}", "wall", "rectangle",
                                  (("t", *c.tolist()), *rz, ("r", 1.0, 0.0, 0.0, 90.0), ("s", f["length"] / 2 + 0.01, d / 2 + 0.01, 1.0)),
                                  room.ceiling_material))
    return parts


def _ceiling_cells(room: Room) -> list[tuple[float, float, float, float]]:
    """The ceiling minus its openings as rectangles (grid cells merged along x); extends 2 cm past the walls."""
    eps = 0.02
    (x0, x1), (y0, y1) = room.x, room.y
    xs = sorted({x0 - eps, x1 + eps, *[v for o in room.openings for v in o[:2]]})
    ys = sorted({y0 - eps, y1 + eps, *[v for o in room.openings for v in o[2:]]})
    cells = []
    for j in range(len(ys) - 1):
        run = None
        for i in range(len(xs) - 1):
            mx, my = (xs[i] + xs[i + 1]) / 2, (ys[j] + ys[j + 1]) / 2
            hole = any(a0 <= mx <= a1 and b0 <= my <= b1 for a0, a1, b0, b1 in room.openings)
            if not hole:
                run = (run[0], xs[i + 1]) if run else (xs[i], xs[i + 1])
            elif run:
                cells.append((run[0], run[1], ys[j], ys[j + 1]))
                run = None
        if run:
            cells.append((run[0], run[1], ys[j], ys[j + 1]))
    return cells


def _exhibit_part(name: str, e: Exhibit, base: np.ndarray) -> Part:
    t = ("t", *base.tolist())
    rz = () if e.yaw_deg == 0.0 else (("r", 0.0, 0.0, 1.0, e.yaw_deg),)
    if e.shape == "sphere":
        return Part(name, "other", "sphere", (("t", base[0], base[1], base[2] + e.radius), ("s", e.radius, e.radius, e.radius)), e.material)
    if e.shape == "box":
        return Part(name, "other", "cube", (("t", base[0], base[1], base[2] + e.height / 2), *rz, ("s", e.radius, e.radius, e.height / 2)), e.material)
    mesh = ("twisted", e.height, e.radius) if e.shape == "twisted" else (e.shape, e.shape_seed, e.radius, e.height)
    return Part(name, "other", "mesh", (t, *rz), e.material, mesh=mesh)


def _pedestal_parts(cfg: GalleryConfig, k: int, p: Pedestal, legacy: bool) -> list[Part]:
    cx, cy, ch = p.center[0], p.center[1], p.height
    parts = [Part("pedestal" if legacy else f"pedestal_{k}", "base", "cube",
                  (("t", cx, cy, ch / 2), ("s", p.half[0], p.half[1], ch / 2)), p.material)]
    if p.exhibit is not None:
        parts.append(_exhibit_part("sculpture" if legacy else f"exhibit_{k}", p.exhibit, np.array([cx, cy, ch])))
    if p.case_half > 0:
        a, hz = p.case_half, p.case_height
        glass = Material(base_color=(1.0, 1.0, 1.0), roughness=0.0, bsdf="thindielectric")
        panes = {
            "front": (("t", cx, cy - a, ch + hz / 2), ("r", 1.0, 0.0, 0.0, 90.0), ("s", a, hz / 2, 1.0)),
            "back": (("t", cx, cy + a, ch + hz / 2), ("r", 1.0, 0.0, 0.0, 90.0), ("s", a, hz / 2, 1.0)),
            "left": (("t", cx - a, cy, ch + hz / 2), ("r", 0.0, 1.0, 0.0, 90.0), ("s", hz / 2, a, 1.0)),
            "right": (("t", cx + a, cy, ch + hz / 2), ("r", 0.0, 1.0, 0.0, 90.0), ("s", hz / 2, a, 1.0)),
            "top": (("t", cx, cy, ch + hz), ("s", a, a, 1.0)),
        }
        for side, xf in panes.items():
            parts.append(Part(f"case_{side}" if legacy else f"case_{k}_{side}", "display", "rectangle", xf, glass, glass="case"))
    return parts


def _fixture_parts(k: int, f: Fixture) -> list[Part]:
    cx, cy = f.center
    along = np.array([1.0, 0.0]) if f.yaw_deg == 0.0 else np.array([0.0, 1.0])
    across = np.array([along[1], along[0]])

    def box(name, centre_uv, z, half_uvz):
        c = np.array([cx, cy]) + centre_uv[0] * along + centre_uv[1] * across
        hx = abs(half_uvz[0] * along[0]) + abs(half_uvz[1] * across[0])
        hy = abs(half_uvz[0] * along[1]) + abs(half_uvz[1] * across[1])
        return Part(name, "other", "cube", (("t", c[0], c[1], z), ("s", hx, hy, half_uvz[2])), f.material)

    if f.kind == "bench":
        length, depth, seat = f.size
        t = 0.05
        return [box(f"bench_{k}_seat", (0.0, 0.0), seat - t / 2, (length / 2, depth / 2, t / 2)),
                box(f"bench_{k}_leg_a", (-length / 2 + 0.1, 0.0), (seat - t) / 2, (0.03, depth / 2 - 0.02, (seat - t) / 2)),
                box(f"bench_{k}_leg_b", (length / 2 - 0.1, 0.0), (seat - t) / 2, (0.03, depth / 2 - 0.02, (seat - t) / 2))]
    w, ph, top = f.size
    return [box(f"sign_{k}_post", (0.0, 0.0), (top - ph) / 2, (0.025, 0.025, (top - ph) / 2)),
            box(f"sign_{k}_foot", (0.0, 0.0), 0.01, (0.18, 0.18, 0.01)),
            box(f"sign_{k}_panel", (0.0, 0.0), top - ph / 2, (w / 2, 0.015, ph / 2))]


def _lamp_parts(cfg: GalleryConfig) -> list[Part]:
    parts = []
    for k, lamp in enumerate(cfg.lighting.lamps):
        if lamp.kind != "area":
            continue
        area = lamp.size[0] * lamp.size[1]
        radiance = tuple(float(c * 4.0 * lamp.power / area) for c in lamp.color)  # E(2 m) ≈ L·A/d² = power
        parts.append(Part(f"lamp_{k}", "wall", "rectangle",
                          (("t", *lamp.position), ("r", 1.0, 0.0, 0.0, 180.0), ("s", lamp.size[0] / 2, lamp.size[1] / 2, 1.0)),
                          Material(base_color=(0.9, 0.9, 0.9), roughness=1.0), emission=radiance))
    return parts


def scene_parts(cfg: GalleryConfig) -> list[Part]:
    """Expand a config into primitives, in a fixed order (the sample's order and names for ``preset="sample"``)."""
    legacy = cfg.preset == "sample"
    parts = _room_parts(cfg)
    for k, p in enumerate(cfg.paintings):
        parts += _frame_parts(cfg, k, p, legacy)
    for k, p in enumerate(cfg.pedestals):
        parts += _pedestal_parts(cfg, k, p, legacy)
    for k, f in enumerate(cfg.fixtures):
        parts += _fixture_parts(k, f)
    return parts + _lamp_parts(cfg)


# --------------------------------------------------------------------------------------------------- obstacle boxes
def _free(box: np.ndarray, others: list[np.ndarray], gap: float) -> bool:
    return all(box[1, 0] + gap < o[0, 0] or o[1, 0] + gap < box[0, 0] or box[1, 1] + gap < o[0, 1] or o[1, 1] + gap < box[0, 1] for o in others)


def exhibit_box(p: Pedestal) -> np.ndarray:
    """float64 [2, 3] box of a pedestal with its exhibit and case."""
    top = p.height
    r = 0.0
    if p.exhibit is not None:
        e = p.exhibit
        eh = 2 * e.radius if e.shape == "sphere" else e.height
        r = e.radius * (1.25 if e.shape == "twisted" else (math.sqrt(2) if e.shape == "box" else 1.0))
        top = max(top, p.height + eh)
    if p.case_half > 0:
        top = max(top, p.height + p.case_height)
        r = max(r, p.case_half)
    hx, hy = max(p.half[0], r), max(p.half[1], r)
    return np.array([[p.center[0] - hx, p.center[1] - hy, 0.0], [p.center[0] + hx, p.center[1] + hy, top]])


def fixture_box(f: Fixture) -> np.ndarray:
    if f.kind == "bench":
        length, depth, seat = f.size
        hu, hv, top = length / 2, depth / 2, seat
    else:
        hu, hv, top = max(f.size[0] / 2, 0.18), 0.18, f.size[2]
    hx, hy = (hu, hv) if f.yaw_deg == 0.0 else (hv, hu)
    return np.array([[f.center[0] - hx, f.center[1] - hy, 0.0], [f.center[0] + hx, f.center[1] + hy, top]])


def obstacle_boxes(cfg: GalleryConfig) -> list[np.ndarray]:
    """Boxes [2, 3] of everything standing in the room (pedestals with exhibits and cases, fixtures)."""
    return [exhibit_box(p) for p in cfg.pedestals] + [fixture_box(f) for f in cfg.fixtures]


def painting_box(room: Room, p: Painting) -> np.ndarray:
    """World box [2, 3] of a painting with its frame (and plaque)."""
    u, z = p.center
    u0, u1 = u - p.size[0] / 2 - p.frame_width, u + p.size[0] / 2 + p.frame_width + (0.26 if p.plaque is not None else 0.0)
    h = p.size[1] / 2 + p.frame_width
    pts = np.array([wall_point(room, p.wall, uu, zz, d) for uu in (u0, u1) for zz in (z - h, z + h) for d in (0.0, p.frame_depth)])
    return np.stack([pts.min(0), pts.max(0)])


# ---------------------------------------------------------------------------------------------------------- cameras
def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenGL camera-to-world looking from ``eye`` at ``target`` (float64 [4, 4], no roll)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(back, right), back, eye
    return m


def sample_front_cameras(n: int, seed: int, target=(0.05, 0.55, 1.0)) -> np.ndarray:
    """The bundled sample's cameras: distance 2.5–3.5 m, azimuth ±60° about −y, elevation 5–35°, looking at points
    jittered ±0.2 m around ``target``. float64 [n, 4, 4]."""
    rng = np.random.default_rng(seed)
    out = np.zeros((n, 4, 4))
    for i in range(n):
        dist = rng.uniform(2.5, 3.5)
        az = math.radians(rng.uniform(-60.0, 60.0))
        el = math.radians(rng.uniform(5.0, 35.0))
        tgt = np.asarray(target) + rng.uniform(-0.2, 0.2, 3)
        eye = tgt + dist * np.array([math.sin(az) * math.cos(el), -math.cos(az) * math.cos(el), math.sin(el)])
        out[i] = look_at(eye, tgt)
    return out


def _ray_box(o: np.ndarray, d: np.ndarray, box: np.ndarray) -> float:
    """Entry distance of a ray into a box (inf if missed or behind)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (box[0] - o) / d
        t1 = (box[1] - o) / d
    tmin = np.nanmax(np.minimum(t0, t1))
    tmax = np.nanmin(np.maximum(t0, t1))
    return float(tmin) if tmax >= max(tmin, 0.0) and tmin > 0 else math.inf


def first_hit_distance(cfg: GalleryConfig, o: np.ndarray, d: np.ndarray) -> float:
    """Distance along a ray from inside the room to the room's walls/floor/ceiling or an obstacle box (approximate:
    boxes, no openings)."""
    room = cfg.room
    lo = np.array([room.x[0], room.y[0], 0.0])
    hi = np.array([room.x[1], room.y[1], room.height])
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, (hi - o) / d, np.where(d < 0, (lo - o) / d, np.inf))
    best = float(t.min())
    for b in obstacle_boxes(cfg) + [painting_box(room, p) for p in cfg.paintings]:
        best = min(best, _ray_box(o, d, b))
    return best


def camera_clearance(cfg: GalleryConfig, eye: np.ndarray) -> float:
    """Horizontal distance from a point to the nearest wall or obstacle footprint (negative inside one), metres;
    also bounded by the vertical distance to floor and ceiling."""
    room = cfg.room
    d = min(eye[0] - room.x[0], room.x[1] - eye[0], eye[1] - room.y[0], room.y[1] - eye[1], eye[2], room.height - eye[2])
    for b in obstacle_boxes(cfg):
        dx = max(b[0, 0] - eye[0], eye[0] - b[1, 0], 0.0)
        dy = max(b[0, 1] - eye[1], eye[1] - b[1, 1], 0.0)
        inside = dx == 0.0 and dy == 0.0
        dist = -min(eye[0] - b[0, 0], b[1, 0] - eye[0], eye[1] - b[0, 1], b[1, 1] - eye[1]) if inside else math.hypot(dx, dy)
        d = min(d, dist)
    return float(d)


CAMERA_CLEARANCE = 0.3
"""Every camera of a procedural gallery is at least this far (m) from walls, floor, ceiling and obstacle footprints."""


def _interest_points(cfg: GalleryConfig, rng: np.random.Generator) -> np.ndarray:
    room = cfg.room
    pts = [wall_point(room, p.wall, p.center[0], p.center[1]) for p in cfg.paintings]
    pts += [np.array([p.center[0], p.center[1], p.height + 0.2]) for p in cfg.pedestals]
    for _ in range(4):
        w = str(rng.choice(room.walls))
        L = wall_frame(room, w)["length"]
        pts.append(wall_point(room, w, rng.uniform(-L / 2, L / 2), rng.uniform(0.5, min(2.5, room.height))))
    pts.append(np.array([np.mean(room.x), np.mean(room.y), 1.0]))
    return np.array(pts)


def gallery_cameras(cfg: GalleryConfig, n: int, split: str) -> tuple[np.ndarray, list[str]]:
    """``n`` camera-to-world matrices (float64 [n, 4, 4], OpenGL) for a split, and each view's kind.

    ``sample_front``: :func:`sample_front_cameras` with seed ``2·seed + 1`` (train) / ``2·seed + 2`` (test), as the
    sample. ``room``: a mixture (``cfg.camera.mix``) of *walk* views (positions along a random loop around the room
    at eye height, looking at a painting, an exhibit or a wall point, or in a free direction, pitch −25°..10°), *arc*
    views (1.2–3 m in front of a painting, ±50° off its normal, looking at it) and *close-ups* (0.35–1.1 m from an
    exhibit's pedestal, looking at the exhibit). Every camera keeps :data:`CAMERA_CLEARANCE` from walls and
    obstacles and sees at least 0.8 m (walks: 40 % of the room's width, at least 1 m) of free space along its axis. Splits draw from their own
    streams, so test views are distinct from train views but follow the same distribution.
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    if cfg.camera.kind == "sample_front":
        s = {"train": 1, "test": 2}.get(split, 3)
        return sample_front_cameras(n, cfg.seed * 2 + s), ["front"] * n
    rng = np.random.default_rng([cfg.seed, 0xCA3E, {"train": 1, "test": 2, "val": 3, "preview": 4}.get(split, 5)])
    room = cfg.room
    cx, cy = np.mean(room.x), np.mean(room.y)
    ax, ay = (room.x[1] - room.x[0]) / 2, (room.y[1] - room.y[0]) / 2
    loop = (rng.uniform(0.35, 0.75), rng.uniform(0.35, 0.75), rng.uniform(0, 2 * math.pi))
    interest = _interest_points(cfg, rng)
    mix = np.array(cfg.camera.mix, np.float64)
    if not cfg.paintings:
        mix[1] = 0.0
    if not cfg.pedestals:
        mix[2] = 0.0
    mix /= mix.sum()
    lo_h, hi_h = cfg.camera.eye_height
    walk_need = max(1.0, 0.4 * min(2 * ax, 2 * ay))  # walks look across the room, not at a wall from 1 m
    out, kinds = [], []
    for _ in range(n):
        kind = str(rng.choice(["walk", "arc", "closeup"], p=mix))
        for attempt in range(400):
            if attempt == 300:
                kind = "walk"
            if kind == "walk":
                t = rng.uniform(0, 2 * math.pi)
                eye = np.array([cx + loop[0] * ax * math.cos(t + loop[2]), cy + loop[1] * ay * math.sin(t + loop[2]), rng.uniform(lo_h, hi_h)])
                eye[:2] += rng.normal(0, 0.3, 2)
                if rng.uniform() < 0.6:
                    tgt = interest[int(rng.integers(len(interest)))] + rng.normal(0, 0.15, 3)
                    fwd = tgt - eye
                    if np.linalg.norm(fwd[:2]) < 0.5:
                        continue
                    pitch = math.degrees(math.atan2(fwd[2], np.linalg.norm(fwd[:2])))
                    if not -35 < pitch < 25:
                        continue
                else:
                    yaw, pitch = rng.uniform(0, 2 * math.pi), math.radians(rng.uniform(-25, 10))
                    tgt = eye + np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), math.sin(pitch)])
                need = walk_need
            elif kind == "arc":
                p = cfg.paintings[int(rng.integers(len(cfg.paintings)))]
                f = wall_frame(room, p.wall)
                centre = wall_point(room, p.wall, p.center[0], p.center[1])
                a, dist = math.radians(rng.uniform(-50, 50)), rng.uniform(1.2, 3.0)
                dirn = math.cos(a) * f["normal"] + math.sin(a) * f["right"]
                eye = centre + dist * dirn
                eye[2] = rng.uniform(lo_h, hi_h)
                tgt = centre + rng.uniform(-0.15, 0.15) * np.array([p.size[0] * f["right"][0], p.size[0] * f["right"][1], p.size[1]])
                need = 0.8
            else:
                p = cfg.pedestals[int(rng.integers(len(cfg.pedestals)))]
                b = exhibit_box(p)
                ctr = np.array([p.center[0], p.center[1], (p.height + b[1, 2]) / 2])
                a = rng.uniform(0, 2 * math.pi)
                r = max(b[1, 0] - p.center[0], b[1, 1] - p.center[1]) * math.sqrt(2) + rng.uniform(CAMERA_CLEARANCE + 0.05, 1.1)
                eye = np.array([ctr[0] + r * math.cos(a), ctr[1] + r * math.sin(a), np.clip(ctr[2] + rng.uniform(0.1, 0.6), 1.0, hi_h)])
                tgt = ctr + rng.normal(0, 0.03, 3)
                need = 0.3
            if camera_clearance(cfg, eye) < CAMERA_CLEARANCE:
                continue
            c2w = look_at(eye, tgt)
            fwd = -c2w[:3, 2]
            if abs(fwd[2]) > 0.95 or first_hit_distance(cfg, eye, fwd) < need:
                continue
            break
        else:
            raise RuntimeError(f"gallery seed {cfg.seed}: no valid {kind} camera in 400 tries (room {room.x} x {room.y})")
        out.append(c2w)
        kinds.append(kind)
    return (np.stack(out) if out else np.zeros((0, 4, 4))), kinds


def probe_point(cfg: GalleryConfig) -> np.ndarray:
    """Where the ground-truth SH light is measured: the room centre at 1.6 m (eye height), or the nearest point
    on a 0.25 m grid at that height with 0.5 m clearance; the sample: (0.05, −1.5, 1.6), the middle of its camera
    region."""
    if cfg.preset == "sample":
        return np.array([0.05, -1.5, 1.6])
    room = cfg.room
    c = np.array([np.mean(room.x), np.mean(room.y), 1.6])
    if camera_clearance(cfg, c) >= 0.5:
        return c
    best = None
    for x in np.arange(room.x[0] + 0.5, room.x[1] - 0.49, 0.25):
        for y in np.arange(room.y[0] + 0.5, room.y[1] - 0.49, 0.25):
            p = np.array([x, y, 1.6])
            if camera_clearance(cfg, p) >= 0.5 and (best is None or np.linalg.norm(p - c) < np.linalg.norm(best - c)):
                best = p
    return best if best is not None else c


# ----------------------------------------------------------------------------------------------------------- checks
def check_config(cfg: GalleryConfig) -> None:
    """Raise ``ValueError`` naming the first violated constraint of a procedural gallery."""
    room = cfg.room
    if cfg.preset != "procedural":
        return
    W, D, H = room.x[1] - room.x[0], room.y[1] - room.y[0], room.height
    if not (4.0 <= W <= 12.0 and 4.0 <= D <= 10.0 and 2.6 <= H <= 4.5):
        raise ValueError(f"room size {W:.2f} x {D:.2f} x {H:.2f} m outside 4-12 x 4-10 x 2.6-4.5")
    if set(room.walls) != set(WALLS) or len(room.wall_materials) != 4:
        raise ValueError(f"a procedural room is closed: walls {room.walls}")
    if len(room.openings) > 3 or (room.openings and not room.ceiling):
        raise ValueError(f"openings {room.openings} need a ceiling and are at most 3")
    for o in room.openings:
        if not (room.x[0] < o[0] < o[1] < room.x[1] and room.y[0] < o[2] < o[3] < room.y[1]):
            raise ValueError(f"opening {o} outside the ceiling")
    if not 1 <= len(cfg.paintings) <= 5:
        raise ValueError(f"{len(cfg.paintings)} paintings (1-5)")
    for k, p in enumerate(cfg.paintings):
        L = wall_frame(room, p.wall)["length"]
        hw, hh = p.size[0] / 2 + p.frame_width, p.size[1] / 2 + p.frame_width
        if p.wall not in room.walls or abs(p.center[0]) + hw > L / 2 or p.center[1] - hh < 0.3 or p.center[1] + hh > H:
            raise ValueError(f"painting {k} ({p.wall}, centre {p.center}, size {p.size}) is not on its wall")
        if not 0.5 <= p.canvas.roughness <= 0.95 or p.canvas.metallic != 0.0:
            raise ValueError(f"painting {k}: roughness {p.canvas.roughness} outside [0.5, 0.95] or metallic")
        if p.frame == "gilt" and p.frame_material.metallic != 1.0 or p.frame == "wood" and p.frame_material.metallic != 0.0:
            raise ValueError(f"painting {k}: {p.frame} frame with metallic {p.frame_material.metallic}")
        if p.canvas_inset >= p.frame_depth:
            raise ValueError(f"painting {k}: canvas in front of its frame")
    if len(cfg.pedestals) > 3:
        raise ValueError(f"{len(cfg.pedestals)} pedestals (0-3)")
    boxes = obstacle_boxes(cfg)
    for k, b in enumerate(boxes):
        if b[0, 0] < room.x[0] or b[1, 0] > room.x[1] or b[0, 1] < room.y[0] or b[1, 1] > room.y[1] or b[1, 2] > H:
            raise ValueError(f"object {k} box {b.tolist()} leaves the room")
        for j in range(k):
            if not _free(b, [boxes[j]], 0.0):
                raise ValueError(f"objects {j} and {k} overlap")
    if len(cfg.lighting.lamps) > 4:
        raise ValueError(f"{len(cfg.lighting.lamps)} lamps (0-4)")
    env_reaches = (not room.ceiling) or bool(room.openings)
    if not env_reaches and not cfg.lighting.lamps:
        raise ValueError("a closed room without openings needs lamps")
    for k, lamp in enumerate(cfg.lighting.lamps):
        p = np.asarray(lamp.position)
        if not (room.x[0] < p[0] < room.x[1] and room.y[0] < p[1] < room.y[1] and 0 < p[2] < H):
            raise ValueError(f"lamp {k} at {lamp.position} outside the room")


def check_cameras(cfg: GalleryConfig, cameras: np.ndarray) -> None:
    """Raise ``ValueError`` if a camera of a procedural gallery is outside the room, within
    :data:`CAMERA_CLEARANCE` of a wall or an object, or not a rigid no-roll pose."""
    if cfg.preset != "procedural":
        return
    for i, c2w in enumerate(np.asarray(cameras)):
        R = c2w[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or abs(np.linalg.det(R) - 1) > 1e-6:
            raise ValueError(f"camera {i} is not a rotation")
        clear = camera_clearance(cfg, c2w[:3, 3])
        if clear < CAMERA_CLEARANCE - 1e-9:
            raise ValueError(f"camera {i} at {c2w[:3, 3].round(3).tolist()} has clearance {clear:.3f} m < {CAMERA_CLEARANCE}")
