"""Procedural galleries: a seed draws a whole closed gallery room as a frozen, JSON-serialisable config.

Pure numpy (no Mitsuba here): :func:`random_gallery` draws a :class:`GalleryConfig`; :func:`scene_parts` expands a
config into primitive parts (rectangles, boxes, spheres, meshes with a semantic class and a material) that
``render_gallery.py`` turns into a Mitsuba scene; :func:`gallery_cameras` draws camera paths inside the room;
:func:`check_config` and :func:`check_cameras` state the constraints every seed obeys (tests call them).
``GalleryConfig()`` / :meth:`GalleryConfig.sample` is the bundled sample ``samples/gallery`` (an open corner: one
wall and a floor), expressed in the same structure.

World frame (SPEC): metres, +z up. The room is the box ``x ∈ room.x, y ∈ room.y, z ∈ [0, room.height]``; walls are
named by the side they stand on: ``north`` (y = y1, faces −y), ``south`` (y = y0), ``east`` (x = x1), ``west``
(x = x0). A wall point is given as ``(u, z)``: ``u`` metres from the wall's midpoint along its "right" axis as seen
from inside the room (north: +x, east: −y, south: −x, west: +y).

What a seed varies (see :func:`random_gallery`): room size, proportions and offset; walls (off-white, grey, dark or
saturated paint, an accent wall), floor (planks, stone slabs, concrete, carpet), ceiling (closed with 0–3 frosted
skylights, or open top); 1–5 paintings (4 canvas styles, roughness U(0.5, 0.95)) on random walls with gilt
(metallic 1), wood or glass-covered frames, wall plaques; 0–3 pedestals (stone, wood, painted) with a metal or
ceramic exhibit (twisted sculpture, vase, bowl, sphere, box), sometimes in a glass case; a bench and a sign stand;
the HDR probe, its rotation and tint, 0–4 lamps (spots on paintings, points, ceiling panels), the lamps' share of
the light and the target exposure; the camera's field of view; RGB or RGBA (alpha 255) PNGs. With
``random_gallery(seed, wall_patterns=p)`` (the ``walls`` render profile) a room's walls are papered (floral, damask,
stripes, dots), bricked, boarded or plastered with chance ``p``; ``p = 0`` (every other profile) leaves each seed's
room as it always was.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gallery_config import *  # noqa: E402,F401,F403  (the config types are part of this module's API)
from gallery_config import (  # noqa: E402
    PROBES, SMOOTH_PROBES, WALLS, CameraPlan, Exhibit, Fixture, GalleryConfig, Lamp, Lighting, Material, Painting,
    Pedestal, Room, Vec2,
)
from gallery_geometry import *  # noqa: E402,F401,F403
from gallery_geometry import _free, exhibit_box, fixture_box, wall_frame, wall_point  # noqa: E402

# ------------------------------------------------------------------------------------------------- random galleries
def _srgb_to_linear(c) -> tuple[float, float, float]:
    c = np.asarray(c, np.float64)
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    return tuple(float(v) for v in lin)


def _hsv(h: float, s: float, v: float) -> tuple[float, float, float]:
    import colorsys

    return _srgb_to_linear(colorsys.hsv_to_rgb(h % 1.0, s, v))


def _kelvin_rgb(kelvin: float) -> tuple[float, float, float]:
    """Approximate linear RGB of a black body (Tanner Helland's fit in sRGB), unit luminance."""
    t = kelvin / 100.0
    r = 255.0 if t <= 66 else 329.698727446 * (t - 60) ** -0.1332047592
    g = 99.4708025861 * math.log(t) - 161.1195681661 if t <= 66 else 288.1221695283 * (t - 60) ** -0.0755148492
    b = 255.0 if t >= 66 else (0.0 if t <= 19 else 138.5177312231 * math.log(t - 10) - 305.0447927307)
    lin = np.array(_srgb_to_linear(np.clip([r / 255, g / 255, b / 255], 0, 1)))
    lum = float(lin @ [0.2126, 0.7152, 0.0722])
    return tuple(float(v) for v in lin / lum)


def _wall_material(rng: np.random.Generator) -> Material:
    kind = rng.choice(["offwhite", "grey", "dark", "saturated"], p=[0.45, 0.15, 0.2, 0.2])
    if kind == "offwhite":
        c = _hsv(rng.uniform(0.05, 0.16), rng.uniform(0.0, 0.12), rng.uniform(0.75, 0.93))
    elif kind == "grey":
        c = _hsv(rng.uniform(0, 1), rng.uniform(0.0, 0.05), rng.uniform(0.35, 0.7))
    elif kind == "dark":
        c = _hsv(rng.uniform(0, 1), rng.uniform(0.2, 0.7), rng.uniform(0.1, 0.3))
    else:
        c = _hsv(rng.uniform(0, 1), rng.uniform(0.4, 0.8), rng.uniform(0.35, 0.7))
    return Material(base_color=c, roughness=float(rng.uniform(0.5, 0.95)))


def _floor_material(rng: np.random.Generator, room_x: Vec2, room_y: Vec2) -> Material:
    kind = str(rng.choice(["planks", "stone", "concrete", "carpet"], p=[0.35, 0.25, 0.2, 0.2]))
    if kind == "planks":
        tone, rough = np.array([0.50, 0.33, 0.20]) * rng.uniform(0.6, 1.4) + rng.uniform(-0.04, 0.04, 3), rng.uniform(0.3, 0.6)
    elif kind == "stone":
        tone, rough = np.array(_hsv(rng.uniform(0.05, 0.15), rng.uniform(0.02, 0.2), rng.uniform(0.4, 0.85))) ** (1 / 2.2), rng.uniform(0.3, 0.7)
    elif kind == "concrete":
        tone, rough = np.full(3, rng.uniform(0.35, 0.65)) + rng.uniform(-0.02, 0.02, 3), rng.uniform(0.5, 0.85)
    else:
        tone, rough = np.array(_hsv(rng.uniform(0, 1), rng.uniform(0.2, 0.7), rng.uniform(0.2, 0.6))) ** (1 / 2.2), rng.uniform(0.85, 1.0)
    tone = np.clip(tone, 0.03, 0.95)
    scale = ((room_x[1] - room_x[0]) / 2.0, (room_y[1] - room_y[0]) / 2.0)  # a 2 m tile
    return Material(roughness=float(rough), texture="floor", texture_args=(kind, int(rng.integers(1 << 30)), *[float(v) for v in tone]),
                    uv_scale=scale)


_METALS = {"gold": (1.0, 0.71, 0.29), "silver": (0.95, 0.93, 0.88), "copper": (0.95, 0.64, 0.54), "bronze": (0.71, 0.45, 0.26),
           "steel": (0.56, 0.57, 0.58)}


def _metal(rng: np.random.Generator, lo: float = 0.05, hi: float = 0.45) -> Material:
    name = str(rng.choice(list(_METALS)))
    tint = rng.uniform(0.92, 1.0, 3)
    return Material(base_color=tuple(float(c * t) for c, t in zip(_METALS[name], tint)), roughness=float(rng.uniform(lo, hi)), metallic=1.0)


def _ceramic(rng: np.random.Generator) -> Material:
    rough = rng.uniform(0.05, 0.35) if rng.uniform() < 0.6 else rng.uniform(0.5, 0.9)
    return Material(base_color=_hsv(rng.uniform(0, 1), rng.uniform(0.0, 0.8), rng.uniform(0.2, 0.92)), roughness=float(rough))


def _draw_room(rng: np.random.Generator) -> Room:
    W, D, H = rng.uniform(4.0, 12.0), rng.uniform(4.0, 10.0), rng.uniform(2.6, 4.5)
    ox, oy = rng.uniform(-2.0, 2.0, 2)
    x, y = (float(ox - W / 2), float(ox + W / 2)), (float(oy - D / 2), float(oy + D / 2))
    base = _wall_material(rng)
    mats = [base] * 4
    if rng.uniform() < 0.25:
        mats[int(rng.integers(4))] = _wall_material(rng)
    ceiling = bool(rng.uniform() > 0.2)
    openings: list[tuple[float, float, float, float]] = []
    if ceiling:
        n_open = int(rng.choice([0, 1, 2, 3], p=[0.15, 0.35, 0.3, 0.2]))
        for _ in range(60):
            if len(openings) >= n_open:
                break
            w = rng.uniform(0.8, min(2.5, W / 2))
            d = rng.uniform(0.8, min(2.5, D / 2))
            a0 = rng.uniform(x[0] + 0.4, x[1] - 0.4 - w)
            b0 = rng.uniform(y[0] + 0.4, y[1] - 0.4 - d)
            o = (float(a0), float(a0 + w), float(b0), float(b0 + d))
            if all(o[1] + 0.3 < q[0] or q[1] + 0.3 < o[0] or o[3] + 0.3 < q[2] or q[3] + 0.3 < o[2] for q in openings):
                openings.append(o)
    ceil_mat = Material(base_color=_hsv(rng.uniform(0.05, 0.15), rng.uniform(0.0, 0.08), rng.uniform(0.7, 0.92)), roughness=float(rng.uniform(0.8, 0.95)))
    return Room(x=x, y=y, height=float(H), walls=WALLS, wall_materials=tuple(mats), floor=_floor_material(rng, x, y), ceiling=ceiling,
                ceiling_material=ceil_mat, openings=tuple(openings), well_depth=0.0)


def _draw_paintings(rng: np.random.Generator, room: Room) -> tuple[Painting, ...]:
    n = int(rng.integers(1, 6))
    placed: list[Painting] = []
    lengths = np.array([wall_frame(room, w)["length"] for w in room.walls])
    for _ in range(200):
        if len(placed) >= n:
            break
        wall = str(rng.choice(room.walls, p=lengths / lengths.sum()))
        L = wall_frame(room, wall)["length"]
        kind = str(rng.choice(["gilt", "wood", "glass"], p=[0.4, 0.35, 0.25]))
        if kind == "gilt":
            fw, fd, fmat = rng.uniform(0.05, 0.12), rng.uniform(0.04, 0.08), _metal(rng, 0.15, 0.45)
        elif kind == "wood":
            fw, fd = rng.uniform(0.03, 0.08), rng.uniform(0.03, 0.06)
            fmat = Material(base_color=_hsv(rng.uniform(0.02, 0.1), rng.uniform(0.3, 0.8), rng.uniform(0.1, 0.6)), roughness=float(rng.uniform(0.35, 0.7)))
        else:
            fw, fd = rng.uniform(0.015, 0.04), rng.uniform(0.025, 0.04)
            fmat = _metal(rng, 0.2, 0.4) if rng.uniform() < 0.3 else Material(
                base_color=_hsv(0.0, 0.0, float(rng.choice([0.05, 0.9]))), roughness=float(rng.uniform(0.3, 0.8)))
        w = rng.uniform(0.4, min(1.8, 0.6 * L))
        h = min(w * rng.uniform(0.6, 1.4), 1.6, room.height - 1.2)
        zlo, zhi = max(0.75 + h / 2 + fw, 1.2), min(room.height - 0.3 - h / 2 - fw, 1.9)
        if zhi < zlo:
            continue
        plaque = None
        if rng.uniform() < 0.3:
            plaque = _metal(rng, 0.2, 0.5) if rng.uniform() < 0.4 else Material(base_color=_hsv(0.0, 0.0, float(rng.choice([0.05, 0.85]))), roughness=0.6)
        extra = 0.3 if plaque is not None else 0.0
        half = w / 2 + fw
        if L / 2 - 0.3 - half - extra < -L / 2 + 0.3 + half:
            continue
        u = rng.uniform(-L / 2 + 0.3 + half, L / 2 - 0.3 - half - extra)
        clash = any(q.wall == wall and abs(q.center[0] - u) < half + q.size[0] / 2 + q.frame_width + 0.3 + max(extra, 0.3 if q.plaque else 0.0)
                    for q in placed)
        if clash:
            continue
        style = str(rng.choice(["strokes", "bands", "blocks", "portrait"]))
        canvas = Material(roughness=float(rng.uniform(0.5, 0.95)), texture="canvas", texture_args=(int(rng.integers(1 << 30)), style, float(h / w)))
        placed.append(Painting(wall=wall, center=(float(u), float(rng.uniform(zlo, zhi))), size=(float(w), float(h)), canvas=canvas, frame=kind,
                               frame_material=fmat, frame_width=float(fw), frame_depth=float(fd),
                               canvas_inset=float(rng.uniform(0.01, 0.5 * fd)), plaque=plaque))
    return tuple(placed)


def _draw_exhibit(rng: np.random.Generator, max_r: float) -> Exhibit:
    shape = str(rng.choice(["twisted", "vase", "bowl", "sphere", "box"], p=[0.25, 0.25, 0.2, 0.15, 0.15]))
    metal = rng.uniform() < 0.5
    mat = _metal(rng) if metal else _ceramic(rng)
    r = float(rng.uniform(0.5, 0.85) * max_r)
    h = {"twisted": rng.uniform(0.3, 0.55), "vase": rng.uniform(0.25, 0.5), "bowl": rng.uniform(0.3, 0.6) * r,
         "sphere": 2 * r, "box": rng.uniform(0.15, 0.4)}[shape]
    if shape == "twisted":
        r = min(r, max_r / 1.25)
    if shape == "box":
        r = min(r, max_r / math.sqrt(2))
    return Exhibit(shape=shape, radius=r, height=float(h), material=mat, shape_seed=int(rng.integers(1 << 30)), yaw_deg=float(rng.uniform(0, 360)))


def _draw_pedestals(rng: np.random.Generator, room: Room) -> tuple[Pedestal, ...]:
    n = int(rng.choice([0, 1, 2, 3], p=[0.15, 0.35, 0.3, 0.2]))
    case_k = int(rng.integers(n)) if n and rng.uniform() < 0.4 else -1
    out: list[Pedestal] = []
    boxes: list[np.ndarray] = []
    for _ in range(100):
        if len(out) >= n:
            break
        k = len(out)
        half = (float(rng.uniform(0.18, 0.35)), float(rng.uniform(0.18, 0.35)))
        height = float(rng.uniform(0.6, 1.1))
        ex = _draw_exhibit(rng, min(half) * 0.9)
        case_half, case_height = 0.0, 0.0
        if k == case_k:
            case_half = float(ex.radius * (1.25 if ex.shape in ("twisted", "box") else 1.0) + rng.uniform(0.04, 0.1))
            half = (max(half[0], case_half + 0.02), max(half[1], case_half + 0.02))
            case_height = float((2 * ex.radius if ex.shape == "sphere" else ex.height) + rng.uniform(0.05, 0.2))
        m = 0.7 + max(half)
        if room.x[1] - room.x[0] < 2 * m or room.y[1] - room.y[0] < 2 * m:
            continue
        c = (float(rng.uniform(room.x[0] + m, room.x[1] - m)), float(rng.uniform(room.y[0] + m, room.y[1] - m)))
        kind = str(rng.choice(["stone", "wood", "painted"], p=[0.4, 0.25, 0.35]))
        if kind == "stone":
            mat = Material(roughness=float(rng.uniform(0.4, 0.8)), texture="stone", texture_args=(int(rng.integers(1 << 30)),))
        elif kind == "wood":
            tone = np.array([0.50, 0.33, 0.20]) * rng.uniform(0.6, 1.3)
            mat = Material(roughness=float(rng.uniform(0.35, 0.7)), texture="floor",
                           texture_args=("planks", int(rng.integers(1 << 30)), *[float(v) for v in np.clip(tone, 0, 1)]), uv_scale=(0.5, 0.5))
        else:
            mat = Material(base_color=_hsv(rng.uniform(0, 1), rng.uniform(0, 0.4), float(rng.choice([rng.uniform(0.05, 0.2), rng.uniform(0.6, 0.92)]))),
                           roughness=float(rng.uniform(0.4, 0.9)))
        p = Pedestal(center=c, half=half, height=height, material=mat, exhibit=ex, case_half=case_half, case_height=case_height)
        box = exhibit_box(p)
        if box[1, 2] > room.height - 0.3 or not _free(box, boxes, 1.2):
            continue
        out.append(p)
        boxes.append(box)
    return tuple(out)


def _draw_fixtures(rng: np.random.Generator, room: Room, pedestals: tuple[Pedestal, ...]) -> tuple[Fixture, ...]:
    out: list[Fixture] = []
    boxes = [exhibit_box(p) for p in pedestals]
    wants = [k for k, p in (("bench", 0.35), ("sign", 0.25)) if rng.uniform() < p]
    for kind in wants:
        for _ in range(50):
            yaw = float(rng.choice([0.0, 90.0]))
            if kind == "bench":
                size = (float(rng.uniform(1.2, 2.0)), float(rng.uniform(0.35, 0.5)), float(rng.uniform(0.4, 0.5)))
                mat = _metal(rng, 0.3, 0.6) if rng.uniform() < 0.3 else Material(
                    base_color=_hsv(rng.uniform(0.02, 0.1), rng.uniform(0.2, 0.8), rng.uniform(0.1, 0.6)), roughness=float(rng.uniform(0.4, 0.8)))
            else:
                size = (float(rng.uniform(0.3, 0.5)), float(rng.uniform(0.2, 0.35)), float(rng.uniform(1.0, 1.4)))
                mat = Material(base_color=_hsv(rng.uniform(0, 1), rng.uniform(0, 0.6), float(rng.choice([0.08, 0.85]))), roughness=float(rng.uniform(0.3, 0.8)))
            m = 1.0 + size[0] / 2
            if room.x[1] - room.x[0] < 2 * m or room.y[1] - room.y[0] < 2 * m:
                break
            c = (float(rng.uniform(room.x[0] + m, room.x[1] - m)), float(rng.uniform(room.y[0] + m, room.y[1] - m)))
            f = Fixture(kind=kind, center=c, yaw_deg=yaw, size=size, material=mat)
            box = fixture_box(f)
            if _free(box, boxes, 0.9):
                out.append(f)
                boxes.append(box)
                break
    return tuple(out)


def _draw_lighting(rng: np.random.Generator, room: Room, paintings: tuple[Painting, ...]) -> Lighting:
    env_reaches = (not room.ceiling) or bool(room.openings)
    n = int(rng.choice([0, 1, 2, 3, 4], p=[0.3, 0.25, 0.2, 0.15, 0.1])) if env_reaches else int(rng.integers(2, 5))
    H = room.height
    top = min(H, 3.6) - rng.uniform(0.25, 0.45)
    lamps = []
    for _ in range(n):
        kinds = ["spot"] * bool(paintings) + ["point"] + ["area"] * room.ceiling
        weights = np.array([{"spot": 0.45, "point": 0.25, "area": 0.3}[k] for k in kinds])
        kind = str(rng.choice(kinds, p=weights / weights.sum()))
        color = _kelvin_rgb(rng.uniform(2700, 6500))
        power = float(rng.uniform(0.5, 1.5))
        if kind == "spot":
            p = paintings[int(rng.integers(len(paintings)))]
            tgt = wall_point(room, p.wall, p.center[0] + rng.uniform(-0.1, 0.1) * p.size[0], p.center[1] + rng.uniform(-0.1, 0.1) * p.size[1])
            pos = tgt + wall_frame(room, p.wall)["normal"] * rng.uniform(1.0, 2.0)
            pos[2] = top
            beam = float(rng.uniform(12.0, 25.0))
            lamps.append(Lamp(kind="spot", position=tuple(float(v) for v in pos), target=tuple(float(v) for v in tgt), color=color, power=power,
                              beam_deg=beam, cutoff_deg=beam + float(rng.uniform(5.0, 15.0))))
        elif kind == "point":
            pos = (float(rng.uniform(room.x[0] + 0.8, room.x[1] - 0.8)), float(rng.uniform(room.y[0] + 0.8, room.y[1] - 0.8)), float(top))
            lamps.append(Lamp(kind="point", position=pos, color=color, power=power))
        else:
            for _ in range(30):
                sx, sy = float(rng.uniform(0.3, 0.8)), float(rng.uniform(0.3, 0.8))
                cx = float(rng.uniform(room.x[0] + 0.5 + sx / 2, room.x[1] - 0.5 - sx / 2))
                cy = float(rng.uniform(room.y[0] + 0.5 + sy / 2, room.y[1] - 0.5 - sy / 2))
                if all(cx + sx / 2 + 0.1 < a0 or a1 < cx - sx / 2 - 0.1 or cy + sy / 2 + 0.1 < b0 or b1 < cy - sy / 2 - 0.1 for a0, a1, b0, b1 in room.openings):
                    lamps.append(Lamp(kind="area", position=(cx, cy, float(H - 0.01)), size=(sx, sy), color=color, power=power))
                    break
    tint = np.exp(rng.normal(0.0, 0.1, 3))
    tint /= tint.mean()
    share = 0.0 if not lamps else (1.0 if not env_reaches else float(rng.uniform(0.4, 0.9)))
    probe = str(rng.choice(PROBES if room.ceiling else SMOOTH_PROBES))
    return Lighting(probe=probe, rotate_deg=float(rng.uniform(0, 360)), tint=tuple(float(v) for v in tint), lamps=tuple(lamps),
                    lamp_share=share, target_mean_srgb=float(rng.uniform(0.3, 0.5)))


def _pattern_walls(rng: np.random.Generator, room: Room, p: float) -> Room:
    """With probability ``p``, paper the room (all four walls, or one accent wall) with a pattern of
    ``gallery_assets.WALL_PATTERNS`` on the wall's own paint as its ground, in square tiles of 0.3-1.2 m."""
    from gallery_assets import WALL_PATTERNS
    from toolkit.io import linear_to_srgb

    if not rng.uniform() < p:
        return room
    kind = str(rng.choice(WALL_PATTERNS))
    tile = float(rng.uniform(0.6, 1.2) if kind in ("brick", "panels") else rng.uniform(0.3, 1.0))
    tex_seed = int(rng.integers(1 << 30))
    accent = int(rng.integers(4)) if rng.uniform() < 0.35 else None
    mats = list(room.wall_materials)
    for k, (wall, mat) in enumerate(zip(room.walls, room.wall_materials)):
        if accent is not None and k != accent:
            continue
        length = wall_frame(room, wall)["length"]
        height = room.height + (room.well_depth if room.ceiling else 0.0)
        ground = linear_to_srgb(np.clip(np.asarray(mat.base_color, np.float64), 0.0, 1.0))
        mats[k] = Material(roughness=mat.roughness, texture="wall", texture_args=(kind, tex_seed, *(float(v) for v in ground)),
                           uv_scale=(float(length / tile), float(height / tile)))
    return dataclasses.replace(room, wall_materials=tuple(mats))


def random_gallery(seed: int, wall_patterns: float = 0.0) -> GalleryConfig:
    """Draw a closed gallery room from ``seed`` (deterministic: the same seed gives the same config on any machine
    with the same numpy). Each component has its own random stream, so e.g. the lamps do not move the paintings.

    ``wall_patterns``: the chance that the room's walls are papered, bricked or boarded (:func:`_pattern_walls`)
    rather than painted. 0 (the default: the validation galleries) draws nothing from that stream, so a seed's room is
    the same as before the option existed."""
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if not 0.0 <= wall_patterns <= 1.0:
        raise ValueError(f"wall_patterns is a probability in [0, 1], got {wall_patterns!r}")
    stream = lambda k: np.random.default_rng([int(seed), 0x6A11E, k])  # noqa: E731
    room = _draw_room(stream(1))
    if wall_patterns > 0:
        room = _pattern_walls(stream(7), room, wall_patterns)
    paintings = _draw_paintings(stream(2), room)
    pedestals = _draw_pedestals(stream(3), room)
    fixtures = _draw_fixtures(stream(4), room, pedestals)
    lighting = _draw_lighting(stream(5), room, paintings)
    r6 = stream(6)
    camera = CameraPlan(kind="room", fov_x_deg=float(r6.uniform(45.0, 65.0)))
    fmt = "rgba" if r6.uniform() < 0.3 else "rgb"
    return GalleryConfig(seed=int(seed), preset="procedural", room=room, paintings=paintings, pedestals=pedestals, fixtures=fixtures,
                         lighting=lighting, camera=camera, image_format=fmt)


__all__ = [
    "CLASSES", "BACKGROUND", "WALLS", "PROBES", "SMOOTH_PROBES", "GENERATOR_VERSION", "Material", "Room", "Painting", "Exhibit", "Pedestal", "Fixture",
    "Lamp", "Lighting", "CameraPlan", "GalleryConfig", "Part", "random_gallery", "scene_parts", "gallery_cameras", "sample_front_cameras",
    "look_at", "wall_frame", "wall_point", "obstacle_boxes", "probe_point", "check_config", "check_cameras", "xform_matrix",
]
