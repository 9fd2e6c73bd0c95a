"""Path-trace the synthetic gallery-corner sample (Mitsuba 3) with full ground truth.

A back wall and a planked floor (world +z up, metres), a procedural painting (roughness 0.8, metallic 0) in a gold
metal frame on the wall, and a stone pedestal carrying a twisted metal sculpture inside a glass case. Materials are
Mitsuba's ``principled`` BSDF; the glass panes use ``thindielectric`` (an ideal smooth thin pane, i.e. the
``principledthin`` limit with zero roughness and no diffuse lobe). The only light is an HDR environment (``envmap``),
so its SH projection is the ground-truth lighting.

Conventions (SPEC): cameras are OpenGL camera-to-world (x right, y up, looking −z); Mitsuba's sensor looks +z with x
to the left, so ``to_world = c2w @ diag(−1, 1, −1, 1)`` (:func:`c2w_to_mitsuba`). Pinhole, square pixels, principal
point at the image centre, pixel centres at ``(col+½, row+½)``.

Ground truth (per view):

* ``radiance``: path-traced linear radiance, box pixel filter (each pixel averages its own footprint).
* ``depth`` (along −z_cam, metres), ``semantic``, ``metal``: one ray through each pixel centre (no blending, so every
  depth is a real surface point and labels are hard).
* ``normal`` (world, facing the camera), ``albedo`` (linear principled ``base_color``), ``roughness``, ``metallic``:
  anti-aliased with 4x4 stratified rays per pixel, averaged over the rays that hit geometry.
* Glass rule: the case panes are clear (≈92 % transmission), so the image shows what lies behind them. Depth, normal
  and material maps describe the first opaque surface behind the glass (what the pixel shows, so photometric and
  geometric supervision agree); the label is the sculpture's where that surface is the sculpture (an annotator labels
  the exhibit) and ``display`` (2) elsewhere inside the case's silhouette. The case geometry is in the JSON
  (``scene.case_box``). Rays that miss everything: label 255, depth 0, maps 0.

The environment "as used" is what Mitsuba evaluates: the input map (SPEC lat-long, bilinear between pixel centres) is
resampled onto Mitsuba's texel grid (rows at ``θ = π·row/(H−1)``) and placed with ``to_world = rotate_z(env_rotate) ·
rotate_x(90°)``; ``env.hdr`` is the loaded emitter queried at SPEC lat-long pixel centres (input resolution), and
``"sh"`` is the :func:`toolkit.sh.fit_sh_probe` projection of a 2x denser query of the same emitter. Exposure: the
environment is scaled so the images' mean sRGB is ≈ 0.42 (bisection on a low-resolution preview; exact because the
environment is the only light); the factor is ``render.exposure`` and is already in ``env.hdr``, ``"sh"`` and the images.

Noise: 400 spp with the ``multijitter`` sampler; two renders with different seeds agree at ≈ 41–42 dB PSNR on the 8-bit
sRGB PNGs (``--noise-check N`` measures it).

Usage::

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 \\
    .venv/bin/python samples/render_gallery.py --out samples/gallery --size 128 --n-train 80 --n-test 20
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

_REPO = Path(__file__).resolve().parents[1]
if str(_REPO) not in sys.path:
    sys.path.insert(0, str(_REPO))

from toolkit._checks import ConfigError, DarsError  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gallery_assets import (  # noqa: E402
    painting_texture,
    plank_texture,
    sky_environment,
    stone_texture,
    twisted_sculpture_mesh,
    write_ply,
)

LIBLLVM19 = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
DEFAULT_ENV = "/work/shared/data/envmaps/probulator_pisa_256x128.hdr"

CLASSES = {"painting": 0, "frame": 1, "display": 2, "base": 3, "wall": 4, "floor": 5, "other": 6}
BACKGROUND = 255


# ------------------------------------------------------------------------------------------------------ configuration
@dataclass(frozen=True)
class GalleryConfig:
    """Geometry and materials of the gallery corner (metres, world +z up; the wall faces −y)."""

    seed: int = 0
    """Seed of the procedural textures (painting strokes, planks, stone)."""
    wall_y: float = 1.0
    """The back wall is the plane y = wall_y, x ∈ [−3, 3], z ∈ [0, wall_height]."""
    wall_height: float = 2.6
    floor_extent: tuple[float, float, float, float] = (-3.0, 3.0, -3.5, 1.0)
    """Floor rectangle (xmin, xmax, ymin, ymax) at z = 0."""
    painting_center: tuple[float, float] = (-0.6, 1.45)
    """(x, z) of the canvas centre."""
    painting_size: tuple[float, float] = (1.1, 0.8)
    """Canvas width and height."""
    frame_width: float = 0.06
    frame_depth: float = 0.05
    canvas_inset: float = 0.015
    """Canvas plane sits at y = wall_y − canvas_inset (inside the frame, whose front is at wall_y − frame_depth)."""
    pedestal_center: tuple[float, float] = (0.75, 0.4)
    pedestal_half: float = 0.25
    pedestal_height: float = 0.95
    case_half: float = 0.23
    case_height: float = 0.52
    sculpture_height: float = 0.42
    sculpture_radius: float = 0.12
    wall_color: tuple[float, float, float] = (0.80, 0.78, 0.74)
    frame_color: tuple[float, float, float] = (1.0, 0.71, 0.29)
    sculpture_color: tuple[float, float, float] = (0.92, 0.90, 0.86)
    materials: dict[str, dict[str, Any]] = field(
        default_factory=lambda: {
            "painting": {"roughness": 0.8, "metallic": 0.0, "base_color": "texture (procedural brush strokes)"},
            "frame": {"roughness": 0.3, "metallic": 1.0},
            "display": {"bsdf": "thindielectric", "ior": 1.5, "roughness": 0.0, "metallic": 0.0, "base_color": [1.0, 1.0, 1.0]},
            "base": {"roughness": 0.6, "metallic": 0.0, "base_color": "texture (stone)"},
            "wall": {"roughness": 0.9, "metallic": 0.0},
            "floor": {"roughness": 0.45, "metallic": 0.0, "base_color": "texture (planks)"},
            "other": {"roughness": 0.2, "metallic": 1.0},
        }
    )


@dataclass(frozen=True)
class Environment:
    """An environment light: a SPEC lat-long radiance map plus its placement."""

    latlong: np.ndarray
    """float32 [H, W, 3] linear radiance, SPEC lat-long (tint and scale applied)."""
    rotate_z_deg: float = 0.0
    """Rotation of the map about world +z (right-handed)."""
    source: str = ""
    """Where it came from (file name or ``sky:<seed>``)."""


@dataclass(frozen=True)
class RenderSettings:
    """Path-tracing options of :func:`render_views`."""

    spp: int = 400
    seed: int = 0
    max_depth: int = 8
    sampler: str = "multijitter"
    """Mitsuba sampler plugin (``independent``, ``stratified``, ``multijitter``, ``ldsampler``...)."""
    variant: str | None = None
    """Mitsuba variant; ``None``: ``llvm_ad_rgb`` when libLLVM 19 exists, else ``scalar_rgb``."""
    gt: bool = True
    """Also trace the ground-truth maps."""
    gt_subsamples: int = 4
    """Stratified rays per pixel axis for the anti-aliased maps."""
    progress: bool = True


# ------------------------------------------------------------------------------------------------------ mitsuba setup
def llvm_available() -> bool:
    """True when the LLVM 19 shared library the ``llvm_*`` variants need is present (else they abort Python)."""
    path = os.environ.get("DRJIT_LIBLLVM_PATH", LIBLLVM19)
    return Path(path).is_file() and "19" in Path(path).name


def default_variant() -> str:
    return "llvm_ad_rgb" if llvm_available() else "scalar_rgb"


def import_mitsuba(variant: str | None = None):
    """Import Mitsuba, select ``variant`` (checking libLLVM for ``llvm_*``) and return ``(mi, dr, variant)``."""
    variant = variant or default_variant()
    if variant.startswith("llvm"):
        if not llvm_available():
            raise ConfigError(f"variant {variant!r} needs libLLVM 19 ({LIBLLVM19}); install libllvm19 or use --variant scalar_rgb")
        os.environ.setdefault("DRJIT_LIBLLVM_PATH", LIBLLVM19)
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as e:
        raise ConfigError("rendering the sample needs mitsuba: pip install 'dars-toolkit[render]' (mitsuba==3.9.1)") from e
    mi.set_variant(variant)
    return mi, dr, variant


def c2w_to_mitsuba(c2w: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world (x right, y up, looks −z) → Mitsuba sensor ``to_world`` (x left, y up, looks +z).

    Args:
        c2w: float [4, 4].

    Returns:
        float64 [4, 4] ``c2w @ diag(−1, 1, −1, 1)``.
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.shape != (4, 4):
        raise DarsError(f"c2w must be 4x4, got shape {list(c2w.shape)}")
    return c2w @ np.diag([-1.0, 1.0, -1.0, 1.0])


def focal_from_fov(fov_x_rad: float, width: int) -> float:
    """Focal length in pixels for a horizontal field of view."""
    return 0.5 * width / math.tan(0.5 * fov_x_rad)


def pixel_rays(c2w: np.ndarray, fov_x_rad: float, size: int, offsets: Sequence[tuple[float, float]] = ((0.5, 0.5),)):
    """World rays through pixel positions ``(col + ox, row + oy)`` (toolkit convention, ``z_cam = −1``).

    Returns:
        origins float64 [S, H, W, 3], unit directions [S, H, W, 3], and the camera-axis scale ``1/|d_cam|``
        [S, H, W] (depth along −z_cam = t · scale) for the S offsets.
    """
    f = focal_from_fov(fov_x_rad, size)
    c = size / 2.0
    rows, cols = np.meshgrid(np.arange(size, dtype=np.float64), np.arange(size, dtype=np.float64), indexing="ij")
    dirs, scales = [], []
    for ox, oy in offsets:
        x = (cols + ox - c) / f
        y = -(rows + oy - c) / f
        d_cam = np.stack([x, y, -np.ones_like(x)], -1)
        norm = np.linalg.norm(d_cam, axis=-1)
        dirs.append((d_cam / norm[..., None]) @ c2w[:3, :3].T)
        scales.append(1.0 / norm)
    dirs = np.stack(dirs)
    origins = np.broadcast_to(c2w[:3, 3], dirs.shape).copy()
    return origins, dirs, np.stack(scales)


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenGL camera-to-world looking from ``eye`` at ``target`` (float64 [4, 4])."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    true_up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, true_up, back, eye
    return m


def sample_cameras(n: int, seed: int, target=(0.05, 0.55, 1.0)) -> np.ndarray:
    """``n`` camera-to-world matrices in front of the scene: distance 2.5–3.5 m, azimuth ±60° about −y,
    elevation 5–35°, looking at points jittered ±0.2 m around ``target``. Returns float64 [n, 4, 4]."""
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


def load_environment(env: str, rotate_deg: float = 0.0, tint=(1.0, 1.0, 1.0), scale: float = 1.0, seed: int = 0) -> Environment:
    """``env`` is an ``.hdr``/``.exr`` SPEC lat-long map or ``sky``; tint and scale are multiplied in."""
    from toolkit.sh import read_envmap

    if env == "sky":
        img, src = sky_environment(seed), f"sky:{seed}"
    else:
        img, src = read_envmap(env), Path(env).name
    img = img * np.asarray(tint, np.float32)[None, None] * np.float32(scale)
    return Environment(latlong=np.ascontiguousarray(img, np.float32), rotate_z_deg=float(rotate_deg), source=src)


def _mitsuba_env_bitmap(latlong: np.ndarray) -> np.ndarray:
    """Resample a SPEC lat-long map onto Mitsuba's envmap texel grid at twice the resolution.

    Mitsuba places texel (i, j) of an Hm x Wm bitmap at θ = π·i/(Hm−1) and φ = 2π(j+½)/Wm (checked against the
    emitter in tests), so texel values are our map bilinearly interpolated at those directions.
    """
    import torch

    from toolkit.sh import lookup_latlong

    H, W = latlong.shape[:2]
    Hm, Wm = 2 * H, 2 * W
    theta = np.arange(Hm) * math.pi / (Hm - 1)
    phi = (np.arange(Wm) + 0.5) * 2 * math.pi / Wm
    T, P = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(T) * np.sin(P), np.sin(T) * np.cos(P), np.cos(T)], -1)
    out = lookup_latlong(torch.as_tensor(latlong, dtype=torch.float64), torch.as_tensor(d)).numpy()
    return np.ascontiguousarray(out.astype(np.float32))


# ------------------------------------------------------------------------------------------------------ scene build
@dataclass
class _Built:
    scene: Any
    shapes: list  # mitsuba shape objects, in the order of `info`
    info: list  # per shape: dict(name, cls, base_color (tuple or texture), roughness, metallic)
    meta: dict


def build_scene(mi, cfg: GalleryConfig, env: Environment, workdir: Path) -> _Built:
    """Create the Mitsuba scene; returns it with per-shape class and material information."""
    T = mi.ScalarTransform4f
    m = cfg.materials
    wy, px, pz = cfg.wall_y, cfg.painting_center[0], cfg.painting_center[1]
    pw, ph = cfg.painting_size[0] / 2, cfg.painting_size[1] / 2
    fw, fd = cfg.frame_width, cfg.frame_depth
    cx, cy, ch = cfg.pedestal_center[0], cfg.pedestal_center[1], cfg.pedestal_height
    tex_paint = mi.load_dict({"type": "bitmap", "bitmap": mi.Bitmap(painting_texture(cfg.seed)), "raw": True})
    tex_floor = mi.load_dict(
        {"type": "bitmap", "bitmap": mi.Bitmap(plank_texture(cfg.seed)), "raw": True,
         "to_uv": T().scale([(cfg.floor_extent[1] - cfg.floor_extent[0]) / 2.0, (cfg.floor_extent[3] - cfg.floor_extent[2]) / 2.0, 1.0])}
    )
    tex_stone = mi.load_dict({"type": "bitmap", "bitmap": mi.Bitmap(stone_texture(cfg.seed)), "raw": True})

    def principled(base, name):
        return {"type": "principled", "base_color": base if not isinstance(base, tuple) else {"type": "rgb", "value": list(base)},
                "roughness": m[name]["roughness"], "metallic": m[name]["metallic"]}

    entries: list[tuple[str, str, dict, Any]] = []  # (id, class, dict, base_color)
    fx0, fx1, fy0, fy1 = cfg.floor_extent
    entries.append(("wall", "wall", {"type": "rectangle", "to_world": T().translate([0, wy, cfg.wall_height / 2]).rotate([1, 0, 0], 90).scale([3.0, cfg.wall_height / 2, 1]),
                                     "bsdf": principled(cfg.wall_color, "wall")}, cfg.wall_color))
    entries.append(("floor", "floor", {"type": "rectangle", "to_world": T().translate([(fx0 + fx1) / 2, (fy0 + fy1) / 2, 0]).scale([(fx1 - fx0) / 2, (fy1 - fy0) / 2, 1]),
                                       "bsdf": principled(tex_floor, "floor")}, tex_floor))
    canvas_y = wy - cfg.canvas_inset
    entries.append(("painting", "painting", {"type": "rectangle", "to_world": T().translate([px, canvas_y, pz]).rotate([1, 0, 0], 90).scale([pw, ph, 1]),
                                             "bsdf": principled(tex_paint, "painting")}, tex_paint))
    bars = {
        "frame_top": ([px, wy - fd / 2, pz + ph + fw / 2], [pw + fw, fd / 2, fw / 2]),
        "frame_bottom": ([px, wy - fd / 2, pz - ph - fw / 2], [pw + fw, fd / 2, fw / 2]),
        "frame_left": ([px - pw - fw / 2, wy - fd / 2, pz], [fw / 2, fd / 2, ph]),
        "frame_right": ([px + pw + fw / 2, wy - fd / 2, pz], [fw / 2, fd / 2, ph]),
    }
    for name, (c, h) in bars.items():
        entries.append((name, "frame", {"type": "cube", "to_world": T().translate(c).scale(h), "bsdf": principled(cfg.frame_color, "frame")}, cfg.frame_color))
    entries.append(("pedestal", "base", {"type": "cube", "to_world": T().translate([cx, cy, ch / 2]).scale([cfg.pedestal_half, cfg.pedestal_half, ch / 2]),
                                         "bsdf": principled(tex_stone, "base")}, tex_stone))
    verts, faces, normals = twisted_sculpture_mesh(cfg.sculpture_height, cfg.sculpture_radius)
    ply = workdir / "sculpture.ply"
    write_ply(ply, verts, faces, normals)
    entries.append(("sculpture", "other", {"type": "ply", "filename": str(ply), "to_world": T().translate([cx, cy, ch]),
                                           "bsdf": principled(cfg.sculpture_color, "other")}, cfg.sculpture_color))
    a, hz = cfg.case_half, cfg.case_height
    glass = {"type": "thindielectric", "int_ior": m["display"]["ior"], "ext_ior": 1.0}
    panes = {
        "case_front": T().translate([cx, cy - a, ch + hz / 2]).rotate([1, 0, 0], 90).scale([a, hz / 2, 1]),
        "case_back": T().translate([cx, cy + a, ch + hz / 2]).rotate([1, 0, 0], 90).scale([a, hz / 2, 1]),
        "case_left": T().translate([cx - a, cy, ch + hz / 2]).rotate([0, 1, 0], 90).scale([hz / 2, a, 1]),
        "case_right": T().translate([cx + a, cy, ch + hz / 2]).rotate([0, 1, 0], 90).scale([hz / 2, a, 1]),
        "case_top": T().translate([cx, cy, ch + hz]).scale([a, a, 1]),
    }
    for name, tw in panes.items():
        entries.append((name, "display", {"type": "rectangle", "to_world": tw, "bsdf": glass}, (1.0, 1.0, 1.0)))

    env_bitmap = _mitsuba_env_bitmap(env.latlong)
    scene_dict: dict[str, Any] = {
        "type": "scene",
        "env": {"type": "envmap", "bitmap": mi.Bitmap(env_bitmap), "to_world": T().rotate([0, 0, 1], env.rotate_z_deg).rotate([1, 0, 0], 90)},
    }
    for name, _, d, _ in entries:
        scene_dict[name] = d
    scene = mi.load_dict(scene_dict, optimize=False)  # keep one shape per entry (no mesh merging)
    by_id = {s.id(): s for s in scene.shapes()}
    shapes, info = [], []
    for name, cls, _, base in entries:
        mat = m[cls]
        shapes.append(by_id[name])
        info.append({"name": name, "cls": cls, "label": CLASSES[cls], "base_color": base,
                     "roughness": float(mat["roughness"]), "metallic": float(mat["metallic"])})
    corners = [[px - pw, canvas_y, pz - ph], [px + pw, canvas_y, pz - ph], [px + pw, canvas_y, pz + ph], [px - pw, canvas_y, pz + ph]]
    meta = {
        "painting_corners": corners,
        "painting_plane": {"point": [px, canvas_y, pz], "normal": [0.0, -1.0, 0.0]},
        "frame_box": [[px - pw - fw, wy - fd, pz - ph - fw], [px + pw + fw, wy, pz + ph + fw]],
        "pedestal_box": [[cx - cfg.pedestal_half, cy - cfg.pedestal_half, 0.0], [cx + cfg.pedestal_half, cy + cfg.pedestal_half, ch]],
        "case_box": [[cx - a, cy - a, ch], [cx + a, cy + a, ch + hz]],
        "sculpture_center": [cx, cy, ch + cfg.sculpture_height / 2],
        "sculpture_box": [(verts.min(0) + [cx, cy, ch]).tolist(), (verts.max(0) + [cx, cy, ch]).tolist()],
        "wall_plane": {"point": [0.0, wy, 0.0], "normal": [0.0, -1.0, 0.0]},
        "floor_plane": {"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]},
    }
    return _Built(scene=scene, shapes=shapes, info=info, meta=meta)


# ------------------------------------------------------------------------------------------------ ground-truth tracing
def _trace(mi, dr, built: _Built, origins: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
    """First hits of rays: distance t, shape index (−1 = miss), shading normal, point, base colour."""
    n = origins.shape[0]
    out = {"t": np.full(n, np.inf), "shape": np.full(n, -1, np.int32), "normal": np.zeros((n, 3)), "base": np.zeros((n, 3))}
    if mi.variant().startswith("scalar"):
        index = {s.id(): k for k, s in enumerate(built.shapes)}
        for i in range(n):
            si = built.scene.ray_intersect(mi.Ray3f(mi.Point3f(*origins[i]), mi.Vector3f(*dirs[i])))
            if not si.is_valid():
                continue
            k = index[si.shape.id()]
            out["t"][i], out["shape"][i] = si.t, k
            out["normal"][i] = np.array(si.sh_frame.n)
            base = built.info[k]["base_color"]
            out["base"][i] = base if isinstance(base, tuple) else np.array(base.eval(si))
        return out
    ray = mi.Ray3f(mi.Point3f(*(origins[:, j] for j in range(3))), mi.Vector3f(*(dirs[:, j] for j in range(3))))
    si = built.scene.ray_intersect(ray)
    valid = np.array(si.is_valid())
    out["t"] = np.where(valid, np.array(si.t), np.inf)
    out["normal"] = np.array(si.sh_frame.n).T.copy()
    for k, (s, inf) in enumerate(zip(built.shapes, built.info)):
        mask = np.array(si.shape == mi.ShapePtr(s)) & valid
        if not mask.any():
            continue
        out["shape"][mask] = k
        base = inf["base_color"]
        out["base"][mask] = base if isinstance(base, tuple) else np.array(base.eval(si)).T[mask]
    out["normal"][out["shape"] < 0] = 0.0
    return out


def _trace_gt(mi, dr, built: _Built, origins: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
    """First hits with the glass rule: look through the (clear) case panes to the first opaque surface.

    ``label`` is that surface's class, except that a ray which crossed the case and does not land on the sculpture is
    labelled ``display``. A ray that crosses the case and then escapes keeps the first pane's values.
    """
    hit = _trace(mi, dr, built, origins, dirs)
    cls = np.array([inf["cls"] for inf in built.info] + ["none"])
    labels = np.array([inf["label"] for inf in built.info] + [BACKGROUND], np.uint8)
    hit["label"] = labels[hit["shape"]]
    todo = np.nonzero(cls[hit["shape"]] == "display")[0]
    o = origins[todo] + dirs[todo] * (hit["t"][todo, None] + 1e-4)
    t_acc = hit["t"][todo].copy()
    for _ in range(6):
        if todo.size == 0:
            break
        nxt = _trace(mi, dr, built, o, dirs[todo])
        t_acc = t_acc + 1e-4 + nxt["t"]
        glass_again = cls[nxt["shape"]] == "display"
        done = ~glass_again & (nxt["shape"] >= 0)
        idx = todo[done]
        for key in ("normal", "base", "shape"):
            hit[key][idx] = nxt[key][done]
        hit["t"][idx] = t_acc[done]
        hit["label"][idx] = np.where(cls[nxt["shape"][done]] == "other", CLASSES["other"], CLASSES["display"])
        keep = glass_again
        todo, o, t_acc = todo[keep], o[keep] + dirs[todo[keep]] * (nxt["t"][keep, None] + 1e-4), t_acc[keep]
    flip = np.sum(hit["normal"] * dirs, -1) > 0  # normals face the camera
    hit["normal"][flip] *= -1
    return hit


def render_gt(mi, dr, built: _Built, c2w: np.ndarray, fov_x: float, size: int, subsamples: int = 4) -> dict[str, np.ndarray]:
    """Ground-truth maps of one view (see the module docstring for the rules)."""
    o, d, scale = pixel_rays(c2w, fov_x, size)
    centre = _trace_gt(mi, dr, built, o[0].reshape(-1, 3), d[0].reshape(-1, 3))
    rough = np.array([inf["roughness"] for inf in built.info] + [0.0])
    metal = np.array([inf["metallic"] for inf in built.info] + [0.0])
    sem = centre["label"].reshape(size, size)
    depth = np.where(centre["shape"] >= 0, centre["t"] * scale[0].reshape(-1), 0.0).reshape(size, size)
    offs = [((i + 0.5) / subsamples, (j + 0.5) / subsamples) for j in range(subsamples) for i in range(subsamples)]
    o, d, _ = pixel_rays(c2w, fov_x, size, offs)
    sub = _trace_gt(mi, dr, built, o.reshape(-1, 3), d.reshape(-1, 3))
    S = len(offs)
    hitm = (sub["shape"] >= 0).reshape(S, size, size)
    cnt = np.maximum(hitm.sum(0), 1)[..., None]
    avg = lambda a: (a.reshape(S, size, size, -1) * hitm[..., None]).sum(0) / cnt  # noqa: E731
    normal = avg(sub["normal"])
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    return {
        "depth": depth.astype(np.float32),
        "semantic": sem,
        "metal": np.where(np.isin(sem, [CLASSES["frame"], CLASSES["other"]]), 255, 0).astype(np.uint8),
        "normal": normal.astype(np.float32),
        "albedo": avg(sub["base"]).astype(np.float32),
        "roughness": avg(rough[sub["shape"]][:, None])[..., 0].astype(np.float32),
        "metallic": avg(metal[sub["shape"]][:, None])[..., 0].astype(np.float32),
    }


def environment_as_used(mi, dr, built: _Built, H: int, W: int) -> np.ndarray:
    """Query the loaded Mitsuba environment emitter at SPEC lat-long pixel centres: float32 [H, W, 3]."""
    from toolkit.sh import latlong_directions

    d = latlong_directions(H, W).numpy().astype(np.float64).reshape(-1, 3)
    em = built.scene.environment()
    if mi.variant().startswith("scalar"):
        vals = np.zeros_like(d)
        for i in range(d.shape[0]):
            si = dr.zeros(mi.SurfaceInteraction3f)
            si.wi = mi.Vector3f(*(-d[i]))
            vals[i] = np.array(em.eval(si))
    else:
        si = dr.zeros(mi.SurfaceInteraction3f, d.shape[0])
        si.wi = -mi.Vector3f(d[:, 0], d[:, 1], d[:, 2])
        vals = np.array(em.eval(si)).T
    return vals.reshape(H, W, 3).astype(np.float32)


# ------------------------------------------------------------------------------------------------------- the stage
def render_views(
    scene_cfg: GalleryConfig,
    cameras: np.ndarray,
    env: Environment,
    size: int,
    spp: int,
    fov_x: float = math.radians(45.0),
    settings: RenderSettings | None = None,
    workdir: str | Path | None = None,
) -> dict[str, Any]:
    """Path-trace views of the gallery under an environment, with ground-truth maps.

    Args:
        scene_cfg: geometry and materials.
        cameras: float [N, 4, 4] OpenGL camera-to-world matrices.
        env: environment light (SPEC lat-long map, world placement).
        size: square image size in pixels.
        spp: samples per pixel (overrides ``settings.spp``).
        fov_x: horizontal field of view, radians.
        settings: seed, max depth, variant, whether to trace GT maps.
        workdir: where to put the temporary sculpture mesh (default: a temporary directory).

    Returns:
        dict with ``radiance`` float32 [N, H, W, 3] linear; with ``settings.gt``: ``depth`` [N, H, W] metres along −z_cam
        (0 = miss), ``normal`` [N, H, W, 3] world, ``albedo`` [N, H, W, 3] linear, ``roughness``, ``metallic``
        [N, H, W], ``semantic``, ``metal`` uint8 [N, H, W]; plus ``variant``, ``scene_meta``, ``seconds``.
    """
    import tempfile

    from tqdm import tqdm

    settings = settings or RenderSettings()
    cameras = np.asarray(cameras, dtype=np.float64).reshape(-1, 4, 4)
    if size < 1 or spp < 1:
        raise ConfigError(f"size={size} and spp={spp} must be positive")
    mi, dr, variant = import_mitsuba(settings.variant)
    t0 = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        built = build_scene(mi, scene_cfg, env, Path(workdir) if workdir else Path(tmp))
    sensor = mi.load_dict({
        "type": "perspective", "fov": math.degrees(fov_x), "fov_axis": "x",
        "to_world": mi.ScalarTransform4f(c2w_to_mitsuba(cameras[0]).tolist()),
        "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        "sampler": {"type": settings.sampler, "sample_count": spp},
    })
    integrator = mi.load_dict({"type": "path", "max_depth": settings.max_depth, "hide_emitters": False})
    params = mi.traverse(sensor)
    out: dict[str, Any] = {"radiance": np.zeros((len(cameras), size, size, 3), np.float32)}
    gt_keys = {"depth": (np.float32, ()), "normal": (np.float32, (3,)), "albedo": (np.float32, (3,)), "roughness": (np.float32, ()),
               "metallic": (np.float32, ()), "semantic": (np.uint8, ()), "metal": (np.uint8, ())}
    if settings.gt:
        for k, (dt, tail) in gt_keys.items():
            out[k] = np.zeros((len(cameras), size, size) + tail, dt)
    for i in tqdm(range(len(cameras)), desc=f"render ({variant}, {spp} spp)", disable=not settings.progress, file=sys.stderr):
        params["to_world"] = mi.Transform4f(c2w_to_mitsuba(cameras[i]).tolist()) if not variant.startswith("scalar") else mi.ScalarTransform4f(c2w_to_mitsuba(cameras[i]).tolist())
        params.update()
        img = mi.render(built.scene, sensor=sensor, integrator=integrator, spp=spp, seed=settings.seed * 100003 + i)
        out["radiance"][i] = np.array(img)[..., :3]
        if settings.gt:
            for k, v in render_gt(mi, dr, built, cameras[i], fov_x, size, settings.gt_subsamples).items():
                out[k][i] = v
    out["variant"] = variant
    out["scene_meta"] = built.meta
    out["seconds"] = time.time() - t0
    out["_built"] = built
    out["_mi"] = (mi, dr)
    return out


# ------------------------------------------------------------------------------------------------------- file output
def _auto_exposure(radiance: np.ndarray, target: float = 0.42) -> float:
    """Scale k with mean(sRGB(clip(k·radiance))) = target (bisection; the environment is the only light)."""
    from toolkit.io import linear_to_srgb

    lo, hi = 1e-3, 1e3
    for _ in range(60):
        mid = math.sqrt(lo * hi)
        if float(linear_to_srgb(np.clip(radiance * mid, 0, 1)).mean()) < target:
            lo = mid
        else:
            hi = mid
    return math.sqrt(lo * hi)


def _write_png(path: Path, image_hwc: np.ndarray, bits: int = 8) -> None:
    """Like :func:`toolkit.io.write_png` (same value mapping) but with maximum zlib compression (smaller sample)."""
    import cv2

    from toolkit.io import atomic_write

    img = np.asarray(image_hwc)
    if img.dtype.kind == "f":
        img = (np.clip(np.nan_to_num(img), 0.0, 1.0) * (255 if bits == 8 else 65535) + 0.5).astype(np.uint8 if bits == 8 else np.uint16)
    if img.ndim == 3 and img.shape[2] == 3:
        img = img[..., ::-1]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise OSError(f"could not encode PNG for {path}")
    with atomic_write(path) as f:
        f.write(buf.tobytes())


def write_split(out_dir: Path, split: str, res: dict[str, Any], cameras: np.ndarray, header: dict[str, Any]) -> None:
    """Write one split's images and ``transforms_<split>.json``."""
    from toolkit.io import linear_to_srgb, write_hdr, write_json

    write_png = _write_png

    frames = []
    for i in range(len(cameras)):
        stem = f"{split}/r_{i:03d}"
        rad = res["radiance"][i]
        write_png(out_dir / f"{stem}.png", linear_to_srgb(np.clip(rad, 0, 1)))
        write_hdr(out_dir / f"{stem}.hdr", rad)
        depth_mm = np.clip(np.round(res["depth"][i] * 1000.0), 0, 65535).astype(np.uint16)
        write_png(out_dir / f"{stem}_depth.png", depth_mm)
        n = res["normal"][i]
        enc = np.where(np.linalg.norm(n, axis=-1, keepdims=True) > 0.5, (n + 1.0) / 2.0, 0.0)
        write_png(out_dir / f"{stem}_normal.png", enc)
        write_png(out_dir / f"{stem}_albedo.png", res["albedo"][i])
        write_png(out_dir / f"{stem}_roughness.png", res["roughness"][i])
        write_png(out_dir / f"{stem}_metallic.png", res["metallic"][i])
        write_png(out_dir / f"{stem}_semantic.png", res["semantic"][i])
        write_png(out_dir / f"{stem}_metal.png", res["metal"][i])
        frames.append({
            "file_path": f"{stem}.png", "transform_matrix": cameras[i].tolist(), "radiance_path": f"{stem}.hdr",
            "depth_file_path": f"{stem}_depth.png", "normal_path": f"{stem}_normal.png", "albedo_path": f"{stem}_albedo.png",
            "roughness_path": f"{stem}_roughness.png", "metallic_path": f"{stem}_metallic.png",
            "semantic_path": f"{stem}_semantic.png", "metal_path": f"{stem}_metal.png",
        })
    write_json(out_dir / f"transforms_{split}.json", {**header, "frames": frames})


def noise_psnr(cfg: GalleryConfig, cameras: np.ndarray, env: Environment, size: int, fov_x: float, settings: RenderSettings) -> tuple[float, float]:
    """PSNR (dB) between two renders with different seeds, on 8-bit sRGB, and seconds per view of one render."""
    from dataclasses import replace

    from toolkit.io import linear_to_srgb

    t0 = time.time()
    a = render_views(cfg, cameras, env, size, settings.spp, fov_x, replace(settings, gt=False, seed=settings.seed + 1000))["radiance"]
    secs = (time.time() - t0) / len(cameras)
    b = render_views(cfg, cameras, env, size, settings.spp, fov_x, replace(settings, gt=False, seed=settings.seed + 2000))["radiance"]
    q = lambda x: np.round(linear_to_srgb(np.clip(x, 0, 1)) * 255.0)  # noqa: E731
    mse = float(((q(a) - q(b)) ** 2).mean())
    return (10.0 * math.log10(255.0**2 / mse) if mse > 0 else float("inf")), secs


def main(argv: Sequence[str] | None = None) -> int:
    import argparse

    import torch

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="output directory")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--n-train", type=int, default=80)
    ap.add_argument("--n-test", type=int, default=20)
    ap.add_argument("--spp", type=int, default=400, help="samples per pixel (multijitter: use a square, e.g. 400)")
    ap.add_argument("--sampler", default="multijitter", help="mitsuba sampler plugin (default: multijitter)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fov", type=float, default=45.0, help="horizontal field of view, degrees")
    ap.add_argument("--env", default=DEFAULT_ENV, help="SPEC lat-long .hdr/.exr, or 'sky' (random smooth SH sky)")
    ap.add_argument("--env-rotate", type=float, default=0.0, metavar="DEG", help="rotate the environment about +z")
    ap.add_argument("--env-tint", type=float, nargs=3, default=(1.0, 1.0, 1.0), metavar=("R", "G", "B"))
    ap.add_argument("--env-scale", type=float, default=1.0, help="radiance scale on top of the automatic exposure")
    ap.add_argument("--exposure", type=float, default=None, help="fixed exposure instead of the automatic one (mean sRGB 0.42)")
    ap.add_argument("--variant", default=None, help="mitsuba variant (default: llvm_ad_rgb if libLLVM 19 exists, else scalar_rgb)")
    ap.add_argument("--max-depth", type=int, default=8)
    ap.add_argument("--force", action="store_true", help="overwrite an existing rendering in --out")
    ap.add_argument("--noise-check", type=int, default=0, metavar="N",
                    help="render N test views twice with different seeds, print the PSNR of the 8-bit sRGB images, and exit")
    args = ap.parse_args(argv)

    from toolkit.io import write_hdr
    from toolkit.sh import fit_sh_probe

    out_dir = Path(args.out)
    if (out_dir / "transforms_train.json").exists() and not args.force:
        print(f"error: {out_dir} already holds a rendering; pass --force to overwrite it", file=sys.stderr)
        return 2
    variant = args.variant or default_variant()
    print(f"mitsuba variant: {variant}", file=sys.stderr)
    try:
        env = load_environment(args.env, args.env_rotate, tuple(args.env_tint), args.env_scale, args.seed)
    except DarsError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    cfg = GalleryConfig(seed=args.seed)
    fov = math.radians(args.fov)
    train_cams = sample_cameras(args.n_train, args.seed * 2 + 1)
    test_cams = sample_cameras(args.n_test, args.seed * 2 + 2)
    exposure = args.exposure
    if exposure is None:
        prev = render_views(cfg, train_cams[: min(8, len(train_cams))], env, 48, 16,
                            fov, RenderSettings(seed=args.seed + 7, variant=variant, gt=False, progress=False))
        exposure = _auto_exposure(prev["radiance"])
        print(f"automatic exposure: x{exposure:.4f}", file=sys.stderr)
    env = Environment(latlong=env.latlong * np.float32(exposure), rotate_z_deg=env.rotate_z_deg, source=env.source)
    settings = RenderSettings(spp=args.spp, seed=args.seed, max_depth=args.max_depth, variant=variant, sampler=args.sampler)
    if args.noise_check:
        psnr, secs = noise_psnr(cfg, test_cams[: args.noise_check], env, args.size, fov, settings)
        print(json.dumps({"noise_psnr_db": psnr, "views": args.noise_check, "spp": args.spp, "sampler": args.sampler,
                          "seconds_per_view": secs}))
        return 0
    t0 = time.time()
    res = {s: render_views(cfg, cams, env, args.size, args.spp, fov, settings) for s, cams in (("train", train_cams), ("test", test_cams))}
    seconds = time.time() - t0
    mi, dr = res["train"]["_mi"]
    H, W = env.latlong.shape[:2]
    dense = environment_as_used(mi, dr, res["train"]["_built"], 2 * H, 2 * W)
    sh = fit_sh_probe(torch.as_tensor(dense, dtype=torch.float64)).to_list()  # GT: dense query of the emitter
    out_dir.mkdir(parents=True, exist_ok=True)
    write_hdr(out_dir / "env.hdr", environment_as_used(mi, dr, res["train"]["_built"], H, W))
    f = focal_from_fov(fov, args.size)
    meta = res["train"]["scene_meta"]
    fx0, fx1, fy0, fy1 = cfg.floor_extent
    header = {
        "camera_angle_x": fov, "fl_x": f, "fl_y": f, "cx": args.size / 2.0, "cy": args.size / 2.0, "w": args.size, "h": args.size,
        # padded so the wall (y = fy1) and the floor (z = 0) lie inside the box, not on its faces: a surface on a
        # face competes with the background model for the rays that leave the box there
        "aabb": [[fx0 - 0.1, fy0 - 0.1, -0.1], [fx1 + 0.1, fy1 + 0.25, cfg.wall_height + 0.2]],
        "sh": sh, "envmap": "env.hdr", "depth_unit_scale_factor": 0.001,
        "render": {
            "renderer": "mitsuba", "mitsuba_version": mi.__version__, "variant": variant, "spp": args.spp, "seed": args.seed,
            "integrator": f"path (max_depth {args.max_depth})", "sampler": args.sampler, "pixel_filter": "box",
            "env": env.source, "env_rotate_deg": args.env_rotate, "env_tint": list(args.env_tint), "env_scale": args.env_scale,
            "exposure": exposure, "fov_x_deg": args.fov, "seconds": round(seconds, 1),
            "gt_rules": "depth/semantic/metal: one ray through the pixel centre; normal/albedo/roughness/metallic: mean of 4x4 "
                        "stratified rays that hit; glass case: maps describe the first opaque surface seen through the clear panes, "
                        "labelled 6 (other) if it is the sculpture, else 2 (display); normals world-space facing the camera, "
                        "encoded (n+1)/2, 0 where nothing was hit; albedo is the linear principled base_color",
        },
        "scene": {"classes": CLASSES, "background_label": BACKGROUND, "materials": {
            **{k: dict(v) for k, v in cfg.materials.items()},
            "wall": {**cfg.materials["wall"], "base_color": list(cfg.wall_color)},
            "frame": {**cfg.materials["frame"], "base_color": list(cfg.frame_color)},
            "other": {**cfg.materials["other"], "base_color": list(cfg.sculpture_color)},
        }, **meta, "config": {k: v for k, v in asdict(cfg).items() if k != "materials"}},
    }
    for split in ("train", "test"):
        write_split(out_dir, split, res[split], train_cams if split == "train" else test_cams, header)
    print(f"wrote {args.n_train} + {args.n_test} views to {out_dir} in {seconds:.1f} s ({variant}, {args.spp} spp)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
