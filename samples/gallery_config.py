"""The gallery config: frozen, JSON-serialisable dataclasses (see ``procedural.py`` for what a seed draws)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import types
import typing
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]

CLASSES = {"painting": 0, "frame": 1, "display": 2, "base": 3, "wall": 4, "floor": 5, "other": 6}
BACKGROUND = 255
WALLS = ("north", "east", "south", "west")
PROBES = ("probulator_pisa_256x128.hdr", "probulator_ennis_256x128.hdr", "probulator_grace_new_256x128.hdr",
          "probulator_wells_256x128.hdr")
SMOOTH_PROBES = ("probulator_pisa_256x128.hdr", "probulator_wells_256x128.hdr")
"""Probes whose light is spread (half the energy in 12 % / 5 % of the sphere); grace (0.01 %) and ennis (1.4 %) have
small intense lights that leave an open-top room's path-traced images ~10 dB noisier at equal samples, so open-top
rooms draw from these two. Skylit rooms use all four (through diffusers only the upward irradiance matters)."""
GENERATOR_VERSION = "gallery-gen-2"
"""Bumped whenever a change to the generator or the renderer changes the output for the same config (the gallery
cache re-renders then)."""


# ------------------------------------------------------------------------------------------------------ config types
@dataclass(frozen=True)
class Material:
    """A surface material (Mitsuba ``principled``, or a thin glass pane)."""

    base_color: Vec3 = (0.8, 0.8, 0.8)
    """Linear RGB base colour (used when ``texture`` is empty)."""
    roughness: float = 0.5
    metallic: float = 0.0
    texture: str = ""
    """Procedural base-colour texture: ``""`` (none), ``canvas`` (args: seed, style, aspect), ``floor`` (args: kind,
    seed, r, g, b sRGB tone), ``wall`` (args: pattern, seed, r, g, b sRGB ground; ``gallery_assets.wall_texture``),
    ``sample_painting`` / ``sample_planks`` / ``sample_stone`` (args: seed), ``stone``
    (args: seed)."""
    texture_args: tuple = ()
    uv_scale: Vec2 = (1.0, 1.0)
    """Texture repeats across the surface's uv square."""
    bsdf: Literal["principled", "thindielectric"] = "principled"
    ior: float = 1.5
    """Index of refraction of a ``thindielectric`` pane."""


@dataclass(frozen=True)
class Room:
    """The room box, its walls, ceiling and surfaces."""

    x: Vec2 = (-3.0, 3.0)
    y: Vec2 = (-3.5, 1.0)
    height: float = 2.6
    walls: tuple[str, ...] = ("north",)
    """Which walls exist (a closed room has all four)."""
    wall_materials: tuple[Material, ...] = (Material(base_color=(0.80, 0.78, 0.74), roughness=0.9),)
    """One per entry of ``walls``."""
    floor: Material = Material(roughness=0.45, texture="sample_planks", texture_args=(0,), uv_scale=(3.0, 2.25))
    ceiling: bool = False
    """A ceiling at z = height (with ``openings``); False: open top."""
    ceiling_material: Material = Material(base_color=(0.8, 0.8, 0.8), roughness=0.9)
    openings: tuple[tuple[float, float, float, float], ...] = ()
    """Skylights: ceiling holes (x0, x1, y0, y1)."""
    well_depth: float = 0.0
    """Height of light wells (shaft walls, labelled wall) between the ceiling and the diffusers. Drawn rooms keep 0
    (laylights flush with the ceiling): a diffuser at the top of a well is seen through the well's mouth only, and
    that visibility cost 6 dB of noise at 256 spp (31.5 vs 37.5 dB two-render PSNR on a test view)."""


@dataclass(frozen=True)
class Painting:
    """A framed canvas on a wall."""

    wall: str = "north"
    center: Vec2 = (-0.6, 1.45)
    """(u, z) of the canvas centre on its wall."""
    size: Vec2 = (1.1, 0.8)
    """Canvas width and height, metres."""
    canvas: Material = Material(roughness=0.6, texture="sample_painting", texture_args=(0,))
    frame: Literal["gilt", "wood", "glass"] = "gilt"
    """``gilt``: metallic frame; ``wood``: dielectric frame; ``glass``: a thin frame and a glass pane in front."""
    frame_material: Material = Material(base_color=(1.0, 0.71, 0.29), roughness=0.3, metallic=1.0)
    frame_width: float = 0.06
    frame_depth: float = 0.05
    canvas_inset: float = 0.015
    """The canvas plane sits ``canvas_inset`` in front of the wall (the frame's front is ``frame_depth`` in front)."""
    plaque: Material | None = None
    """A small label plaque right of the frame (class ``other``), or None."""


@dataclass(frozen=True)
class Exhibit:
    """An object on a pedestal (class ``other``)."""

    shape: Literal["twisted", "vase", "bowl", "sphere", "box"] = "twisted"
    radius: float = 0.12
    height: float = 0.42
    material: Material = Material(base_color=(0.92, 0.90, 0.86), roughness=0.2, metallic=1.0)
    shape_seed: int = 0
    yaw_deg: float = 0.0


@dataclass(frozen=True)
class Pedestal:
    """A plinth (class ``base``) with an optional exhibit and glass case."""

    center: Vec2 = (0.75, 0.4)
    half: Vec2 = (0.25, 0.25)
    height: float = 0.95
    material: Material = Material(roughness=0.6, texture="sample_stone", texture_args=(0,))
    exhibit: Exhibit | None = Exhibit()
    case_half: float = 0.23
    """Half-width of the glass case on the pedestal top (0: no case)."""
    case_height: float = 0.52


@dataclass(frozen=True)
class Fixture:
    """Other furniture (class ``other``): a bench or a sign stand, axis-aligned."""

    kind: Literal["bench", "sign"] = "bench"
    center: Vec2 = (0.0, 0.0)
    yaw_deg: float = 0.0
    """0 or 90: the bench's length (the sign's face) runs along x, or along y."""
    size: Vec3 = (1.5, 0.45, 0.45)
    """bench: (length, depth, seat height); sign: (panel width, panel height, top height)."""
    material: Material = Material()


@dataclass(frozen=True)
class Lamp:
    """A lamp. ``power``: irradiance (pre-exposure) at 2 m on the lamp's axis."""

    kind: Literal["spot", "point", "area"] = "point"
    position: Vec3 = (0.0, 0.0, 2.5)
    target: Vec3 = (0.0, 0.0, 0.0)
    """Spot: where the axis points."""
    size: Vec2 = (0.4, 0.4)
    """Area: panel size (a rectangle 1 cm under the ceiling, facing down)."""
    color: Vec3 = (1.0, 1.0, 1.0)
    """Linear RGB with unit luminance."""
    power: float = 1.0
    beam_deg: float = 20.0
    cutoff_deg: float = 30.0


@dataclass(frozen=True)
class Lighting:
    """The environment probe plus lamps, and the exposure rule."""

    probe: str = "probulator_pisa_256x128.hdr"
    """File name in the envmaps directory (``DARS_ENVMAPS`` or ``/work/shared/data/envmaps``)."""
    rotate_deg: float = 0.0
    tint: Vec3 = (1.0, 1.0, 1.0)
    lamps: tuple[Lamp, ...] = ()
    lamp_share: float = 0.0
    """Fraction of the mean image radiance the lamps contribute (the environment the rest)."""
    target_mean_srgb: float = 0.42
    """Exposure: everything is scaled so the mean sRGB of the images is this."""


@dataclass(frozen=True)
class CameraPlan:
    """How views are drawn (the number of views comes from the render profile)."""

    kind: Literal["sample_front", "room"] = "sample_front"
    """``sample_front``: the sample's cameras (2.5–3.5 m in front of the corner); ``room``: walks, arcs, close-ups."""
    fov_x_deg: float = 45.0
    eye_height: Vec2 = (1.3, 1.8)
    mix: Vec3 = (0.5, 0.3, 0.2)
    """Fractions of walk, arc (in front of paintings) and close-up (exhibits) views."""


@dataclass(frozen=True)
class GalleryConfig:
    """Everything a gallery render needs. ``GalleryConfig()`` is the bundled sample; :func:`random_gallery` draws
    new ones. JSON round trip: :meth:`to_dict` / :meth:`from_dict`."""

    seed: int = 0
    preset: Literal["sample", "procedural"] = "sample"
    room: Room = Room()
    paintings: tuple[Painting, ...] = (Painting(),)
    pedestals: tuple[Pedestal, ...] = (Pedestal(),)
    fixtures: tuple[Fixture, ...] = ()
    lighting: Lighting = Lighting()
    camera: CameraPlan = CameraPlan()
    image_format: Literal["rgb", "rgba"] = "rgb"
    """``rgba``: PNGs with an alpha channel that is 255 everywhere (as some capture tools write)."""

    @staticmethod
    def sample(seed: int = 0) -> "GalleryConfig":
        """The bundled sample ``samples/gallery`` (seed 0: its scene, lighting and cameras); another ``seed`` redraws
        its textures and cameras, as ``render_gallery.py --preset sample --seed N`` always did."""
        c = GalleryConfig()
        if seed == 0:
            return c
        tex = lambda m: dataclasses.replace(m, texture_args=(int(seed),))  # noqa: E731
        return dataclasses.replace(
            c, seed=int(seed), room=dataclasses.replace(c.room, floor=tex(c.room.floor)),
            paintings=(dataclasses.replace(c.paintings[0], canvas=tex(c.paintings[0].canvas)),),
            pedestals=(dataclasses.replace(c.pedestals[0], material=tex(c.pedestals[0].material)),))

    def to_dict(self) -> dict[str, Any]:
        return _to_jsonable(dataclasses.asdict(self))

    @staticmethod
    def from_dict(d: dict[str, Any]) -> "GalleryConfig":
        return _from_jsonable(GalleryConfig, d)

    def digest(self) -> str:
        """sha256 of the canonical JSON (12 hex digits)."""
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()[:12]


def _to_jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_to_jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    return x


def _deep_tuple(x: Any) -> Any:
    return tuple(_deep_tuple(v) for v in x) if isinstance(x, (list, tuple)) else x


def _from_jsonable(tp: Any, v: Any) -> Any:
    """Rebuild a (nested) frozen dataclass from its JSON form, using the type hints."""
    if v is None:
        return None
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return _from_jsonable(args[0], v)
    if dataclasses.is_dataclass(tp):
        hints = typing.get_type_hints(tp)
        return tp(**{f.name: _from_jsonable(hints[f.name], v[f.name]) for f in dataclasses.fields(tp) if f.name in v})
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_from_jsonable(args[0], e) for e in v)
        if args:
            return tuple(_from_jsonable(a, e) for a, e in zip(args, v))
        return _deep_tuple(v)
    if tp is tuple:
        return _deep_tuple(v)
    if tp is float:
        return float(v)
    if tp is int:
        return int(v)
    return v
