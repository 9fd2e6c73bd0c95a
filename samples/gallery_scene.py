"""The Mitsuba side of the gallery renderer: scene construction from a :class:`procedural.GalleryConfig`, the
ground-truth ray tracing (labels, depth, normals, materials, the glass rule) and the environment helpers.

``render_gallery.py`` drives it (its docstring states the conventions and the ground-truth rules); everything here is
re-exported there. Mitsuba is imported lazily through :func:`import_mitsuba` (``llvm_*`` variants need libLLVM 19).
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

_REPO = Path(__file__).resolve().parents[1]
if str(_REPO) not in sys.path:
    sys.path.insert(0, str(_REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from toolkit._checks import ConfigError, DarsError  # noqa: E402

from gallery_assets import (  # noqa: E402
    bowl_profile,
    canvas_texture,
    floor_texture,
    lathe_mesh,
    painting_texture,
    plank_texture,
    sky_environment,
    stone_texture,
    twisted_sculpture_mesh,
    vase_profile,
    wall_texture,
    write_ply,
)
from procedural import (  # noqa: E402
    BACKGROUND,
    CLASSES,
    GalleryConfig,
    Material,
    Part,
    exhibit_box,
    painting_box,
    sample_front_cameras,
    scene_parts,
    wall_frame,
    wall_point,
)

LIBLLVM19 = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
def shared_data_dir(name: str, variable: str) -> Path:
    """A folder of the shared external data, read in place: ``$<variable>``, ``$DARS_SHARED_DATA/<name>``,
    ``../shared/data/<name>`` beside the clone, else ``/work/shared/data/<name>``."""
    if os.environ.get(variable):
        return Path(os.environ[variable])
    if os.environ.get("DARS_SHARED_DATA"):
        return Path(os.environ["DARS_SHARED_DATA"]) / name
    beside = _REPO.parent / "shared" / "data" / name
    return beside if beside.is_dir() else Path("/work/shared/data") / name


ENVMAPS = shared_data_dir("envmaps", "DARS_ENVMAPS")
"""Where the HDR probes are read from (never copied into the repo): ``$DARS_ENVMAPS``, ``$DARS_SHARED_DATA/envmaps``,
``../shared/data/envmaps`` beside the clone, else ``/work/shared/data/envmaps``."""
DEFAULT_ENV = str(ENVMAPS / "probulator_pisa_256x128.hdr")


@dataclass(frozen=True)
class Environment:
    """An environment light: a SPEC lat-long radiance map plus its placement."""

    latlong: np.ndarray
    """float32 [H, W, 3] linear radiance, SPEC lat-long (tint and scale applied)."""
    rotate_z_deg: float = 0.0
    """Rotation of the map about world +z (right-handed)."""
    source: str = ""
    """Where it came from (file name or ``sky:<seed>``)."""


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


def sample_cameras(n: int, seed: int, target=(0.05, 0.55, 1.0)) -> np.ndarray:
    """The bundled sample's camera distribution (:func:`procedural.sample_front_cameras`): float64 [n, 4, 4]."""
    return sample_front_cameras(n, seed, target)


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


def environment_of(cfg: GalleryConfig, scale: float = 1.0) -> Environment:
    """The config's probe (read from :data:`ENVMAPS`), tinted, rotated, scaled by ``scale``."""
    lt = cfg.lighting
    path = ENVMAPS / lt.probe
    if not path.is_file():
        raise ConfigError(f"HDR probe {path} not found: set DARS_ENVMAPS to the folder holding {lt.probe}")
    return load_environment(str(path), lt.rotate_deg, lt.tint, scale)


# ------------------------------------------------------------------------------------------------------ scene build
@dataclass
class _Built:
    scene: Any
    shapes: list  # mitsuba shape objects, in the order of `info`
    info: list  # per shape: dict(name, cls, label, base_color (tuple or texture), roughness, metallic, glass, metal)
    meta: dict
    ids: dict = field(default_factory=dict)  # llvm: shape registry id -> index in `shapes`


def _texture_image(mat: Material, cache: dict) -> np.ndarray:
    key = (mat.texture, tuple(mat.texture_args))
    if key not in cache:
        a = mat.texture_args
        if mat.texture == "sample_painting":
            cache[key] = painting_texture(int(a[0]))
        elif mat.texture == "sample_planks":
            cache[key] = plank_texture(int(a[0]))
        elif mat.texture in ("sample_stone", "stone"):
            cache[key] = stone_texture(int(a[0]))
        elif mat.texture == "canvas":
            cache[key] = canvas_texture(int(a[0]), str(a[1]), float(a[2]))
        elif mat.texture == "floor":
            cache[key] = floor_texture(str(a[0]), int(a[1]), (float(a[2]), float(a[3]), float(a[4])))
        elif mat.texture == "wall":
            cache[key] = wall_texture(str(a[0]), int(a[1]), (float(a[2]), float(a[3]), float(a[4])))
        else:
            raise ConfigError(f"unknown texture {mat.texture!r}")
    return cache[key]


def _mesh_data(mesh: tuple):
    kind = mesh[0]
    if kind == "twisted":
        return twisted_sculpture_mesh(float(mesh[1]), float(mesh[2]))
    rng = np.random.default_rng(int(mesh[1]))
    prof = vase_profile if kind == "vase" else bowl_profile
    return lathe_mesh(*prof(rng, float(mesh[2]), float(mesh[3])))


def _mi_transform(mi, ops) -> Any:
    t = mi.ScalarTransform4f()
    for op in ops:
        if op[0] == "t":
            t = t.translate([op[1], op[2], op[3]])
        elif op[0] == "s":
            t = t.scale([op[1], op[2], op[3]])
        else:
            t = t.rotate([op[1], op[2], op[3]], op[4])
    return t


def _lamp_emitters(mi, cfg: GalleryConfig, scale: float) -> dict[str, dict]:
    """Mitsuba ``spot`` / ``point`` emitters of the config's lamps (intensity ``4·power·scale·colour`` W/sr, so the
    irradiance 2 m away on the axis is ``power·scale``)."""
    out = {}
    for k, lamp in enumerate(cfg.lighting.lamps):
        inten = {"type": "rgb", "value": [float(4.0 * lamp.power * scale * c) for c in lamp.color]}
        if lamp.kind == "point":
            out[f"lamp_{k}"] = {"type": "point", "position": list(lamp.position), "intensity": inten}
        elif lamp.kind == "spot":
            up = [0.0, 0.0, 1.0] if abs(np.subtract(lamp.target, lamp.position)[2]) < 0.99 * np.linalg.norm(np.subtract(lamp.target, lamp.position)) else [0.0, 1.0, 0.0]
            out[f"lamp_{k}"] = {"type": "spot", "to_world": mi.ScalarTransform4f().look_at(origin=list(lamp.position), target=list(lamp.target), up=up),
                                "intensity": inten, "beam_width": float(lamp.beam_deg), "cutoff_angle": float(lamp.cutoff_deg)}
    return out


def daylight_radiance(env: Environment) -> np.ndarray:
    """Radiance of a lossless Lambertian skylight diffuser under a probe: ``E_up / π`` with ``E_up`` the probe's
    irradiance on an upward-facing surface (SPEC lat-long quadrature; a rotation about z does not change it).
    float64 [3]."""
    import torch

    from toolkit.sh import latlong_directions, latlong_solid_angles

    H, W = env.latlong.shape[:2]
    cos = latlong_directions(H, W, dtype=torch.float64).numpy()[..., 2]
    w = latlong_solid_angles(H, W, dtype=torch.float64).numpy() * np.clip(cos, 0.0, None)
    return (env.latlong.astype(np.float64) * w[..., None]).sum((0, 1)) / math.pi


def env_emitter_visible(cfg: GalleryConfig) -> bool:
    """Whether the probe itself is in the scene (seen through the open top, or the sample's open corner); in a
    closed room daylight only enters through the skylight diffusers."""
    return cfg.preset == "sample" or not cfg.room.ceiling


def daylight_reaches(cfg: GalleryConfig) -> bool:
    return env_emitter_visible(cfg) or bool(cfg.room.openings)


def build_scene(mi, cfg: GalleryConfig, env: Environment | None, workdir: Path, lamp_scale: float = 1.0,
                textures: dict | None = None, env_emitter: bool | None = None) -> _Built:
    """Create the Mitsuba scene of a config; returns it with per-shape class and material information.

    Args:
        cfg: the gallery.
        env: the environment (its map already scaled by the exposure), or None for no daylight. It is the scene's
            ``env`` emitter where :func:`env_emitter_visible` (or ``env_emitter=True``) and sets the skylight
            diffusers' radiance (:func:`daylight_radiance`).
        workdir: where the exhibit meshes are written (PLY).
        lamp_scale: multiplies every lamp (0: lamps off; area-lamp panels stay as unlit shapes).
        textures: cache of texture images shared between builds of one gallery.
        env_emitter: force the ``env`` emitter on or off.
    """
    T = mi.ScalarTransform4f
    textures = {} if textures is None else textures
    parts = scene_parts(cfg)
    scene_dict: dict[str, Any] = {"type": "scene"}
    sky = daylight_radiance(env) if env is not None else None
    if env is not None and (env_emitter_visible(cfg) if env_emitter is None else env_emitter):
        scene_dict["env"] = {"type": "envmap", "bitmap": mi.Bitmap(_mitsuba_env_bitmap(env.latlong)),
                             "to_world": T().rotate([0, 0, 1], env.rotate_z_deg).rotate([1, 0, 0], 90)}
    bases = []
    for part in parts:
        mat = part.material
        if mat.bsdf == "thindielectric":
            bsdf = {"type": "thindielectric", "int_ior": mat.ior, "ext_ior": 1.0}
            base: Any = tuple(float(c) for c in mat.base_color)
        else:
            if mat.texture:
                tex = {"type": "bitmap", "bitmap": mi.Bitmap(_texture_image(mat, textures)), "raw": True}
                if tuple(mat.uv_scale) != (1.0, 1.0):
                    tex["to_uv"] = T().scale([mat.uv_scale[0], mat.uv_scale[1], 1.0])
                base = mi.load_dict(tex)
            else:
                base = tuple(float(c) for c in mat.base_color)
            bsdf = {"type": "principled", "base_color": base if not isinstance(base, tuple) else {"type": "rgb", "value": list(base)},
                    "roughness": mat.roughness, "metallic": mat.metallic}
        d: dict[str, Any] = {"type": part.shape, "to_world": _mi_transform(mi, part.xform), "bsdf": bsdf}
        if part.shape == "mesh":
            verts, faces, normals = _mesh_data(part.mesh)
            ply = Path(workdir) / f"{part.name}.ply"
            write_ply(ply, verts, faces, normals)
            d = {"type": "ply", "filename": str(ply), "to_world": d["to_world"], "bsdf": bsdf}
        if (part.emission is not None and lamp_scale > 0) or (part.skylight and sky is not None):
            radiance = [float(c * lamp_scale) for c in part.emission] if part.emission is not None else [float(c) for c in sky]
            d["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": radiance}}
        scene_dict[part.name] = d
        bases.append(base)
    if lamp_scale > 0:
        scene_dict.update(_lamp_emitters(mi, cfg, lamp_scale))
    scene = mi.load_dict(scene_dict, optimize=False)  # keep one shape per entry (no mesh merging)
    by_id = {s.id(): s for s in scene.shapes()}
    shapes, info = [], []
    for part, base in zip(parts, bases):
        shapes.append(by_id[part.name])
        info.append({"name": part.name, "cls": part.cls, "label": CLASSES[part.cls], "base_color": base, "glass": part.glass,
                     "roughness": float(part.material.roughness), "metallic": float(part.material.metallic), "metal": part.metal})
    ids = {}
    if not mi.variant().startswith("scalar"):
        import drjit as dr

        for k, s in enumerate(shapes):
            ids[int(np.array(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s)))[0])] = k
    return _Built(scene=scene, shapes=shapes, info=info, meta=scene_meta(cfg, parts), ids=ids)


def scene_meta(cfg: GalleryConfig, parts: list[Part] | None = None) -> dict[str, Any]:
    """Geometry of the gallery for the JSON: paintings (corners, plane, frame box), pedestals (box, case, exhibit),
    walls, floor, ceiling openings; the sample keeps its old single-object keys too."""
    room = cfg.room
    paintings = []
    for p in cfg.paintings:
        f = wall_frame(room, p.wall)
        u, z = p.center
        pw, ph = p.size[0] / 2, p.size[1] / 2
        corners = [wall_point(room, p.wall, u + su * pw, z + sz * ph, p.canvas_inset).tolist() for su, sz in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        fb = painting_box(room, p) if p.plaque is None else painting_box(room, replace(p, plaque=None))
        paintings.append({"wall": p.wall, "corners": corners, "plane": {"point": wall_point(room, p.wall, u, z, p.canvas_inset).tolist(),
                          "normal": f["normal"].tolist()}, "frame": p.frame, "frame_box": fb.tolist(), "roughness": p.canvas.roughness,
                          "glass_cover": p.frame == "glass"})
    pedestals = []
    for p in cfg.pedestals:
        e = p.exhibit
        entry = {"box": [[p.center[0] - p.half[0], p.center[1] - p.half[1], 0.0], [p.center[0] + p.half[0], p.center[1] + p.half[1], p.height]],
                 "with_exhibit_box": exhibit_box(p).tolist()}
        if e is not None:
            eh = 2 * e.radius if e.shape == "sphere" else e.height
            entry["exhibit"] = {"shape": e.shape, "center": [p.center[0], p.center[1], p.height + eh / 2], "metal": e.material.metallic >= 0.5}
        if p.case_half > 0:
            a = p.case_half
            entry["case_box"] = [[p.center[0] - a, p.center[1] - a, p.height], [p.center[0] + a, p.center[1] + a, p.height + p.case_height]]
        pedestals.append(entry)
    walls = {w: {"point": wall_frame(room, w)["mid"].tolist(), "normal": wall_frame(room, w)["normal"].tolist()} for w in room.walls}
    meta: dict[str, Any] = {"room_box": [[room.x[0], room.y[0], 0.0], [room.x[1], room.y[1], room.height]], "walls": walls,
                            "floor_plane": {"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]},
                            "ceiling": room.ceiling, "openings": [list(o) for o in room.openings], "paintings": paintings, "pedestals": pedestals}
    if cfg.preset == "sample":  # the sample's original keys (tests and tools read them)
        p, q = paintings[0], cfg.pedestals[0]
        t = twisted_sculpture_mesh(q.exhibit.height, q.exhibit.radius)[0]
        base = np.array([q.center[0], q.center[1], q.height])
        meta.update({
            "painting_corners": p["corners"], "painting_plane": p["plane"], "frame_box": p["frame_box"],
            "pedestal_box": pedestals[0]["box"], "case_box": pedestals[0]["case_box"],
            "sculpture_center": [q.center[0], q.center[1], q.height + q.exhibit.height / 2],
            "sculpture_box": [(t.min(0) + base).tolist(), (t.max(0) + base).tolist()],
            "wall_plane": {"point": [0.0, room.y[1], 0.0], "normal": [0.0, -1.0, 0.0]},
        })
    return meta


# ------------------------------------------------------------------------------------------------ ground-truth tracing
def _trace(mi, dr, built: _Built, origins: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
    """First hits of rays: distance t, shape index (−1 = miss), shading normal, base colour."""
    n = origins.shape[0]
    out = {"t": np.full(n, np.inf), "shape": np.full(n, -1, np.int32), "normal": np.zeros((n, 3)), "base": np.zeros((n, 3))}
    if n == 0:
        return out
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
    reg = np.array(dr.reinterpret_array(mi.UInt32, si.shape))
    lut = np.full(max(built.ids) + 2 if built.ids else 1, -1, np.int32)
    for rid, k in built.ids.items():
        lut[rid] = k
    shape = np.where(valid & (reg < len(lut)), lut[np.minimum(reg, len(lut) - 1)], -1)
    out["shape"] = shape.astype(np.int32)
    for k, inf in enumerate(built.info):
        base = inf["base_color"]
        mask = shape == k
        if not mask.any():
            continue
        out["base"][mask] = base if isinstance(base, tuple) else np.array(base.eval(si)).T[mask]
    out["normal"][out["shape"] < 0] = 0.0
    return out


def _trace_gt(mi, dr, built: _Built, origins: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
    """First hits with the glass rule: look through clear panes (case panes, painting covers) to the first opaque
    surface. Its label is kept, except that a ray which crossed a display case and does not land on an exhibit
    (class other) is labelled ``display``. A ray that crosses glass and then escapes keeps the first pane's values."""
    hit = _trace(mi, dr, built, origins, dirs)
    glass = np.array([inf["glass"] for inf in built.info] + [""])
    labels = np.array([inf["label"] for inf in built.info] + [BACKGROUND], np.uint8)
    cls = np.array([inf["cls"] for inf in built.info] + ["none"])
    hit["label"] = labels[hit["shape"]]
    crossed_case = glass[hit["shape"]] == "case"
    todo = np.nonzero(glass[hit["shape"]] != "")[0]
    o = origins[todo] + dirs[todo] * (hit["t"][todo, None] + 1e-4)
    t_acc = hit["t"][todo].copy()
    for _ in range(8):
        if todo.size == 0:
            break
        nxt = _trace(mi, dr, built, o, dirs[todo])
        t_acc = t_acc + 1e-4 + nxt["t"]
        glass_again = glass[nxt["shape"]] != ""
        crossed_case[todo[glass[nxt["shape"]] == "case"]] = True
        done = ~glass_again & (nxt["shape"] >= 0)
        idx = todo[done]
        for key in ("normal", "base", "shape"):
            hit[key][idx] = nxt[key][done]
        hit["t"][idx] = t_acc[done]
        lab = labels[nxt["shape"][done]]
        hit["label"][idx] = np.where(crossed_case[idx] & (cls[nxt["shape"][done]] != "other"), CLASSES["display"], lab)
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
    is_metal = np.array([inf["metal"] for inf in built.info] + [False])
    sem = centre["label"].reshape(size, size)
    depth = np.where(centre["shape"] >= 0, centre["t"] * scale[0].reshape(-1), 0.0).reshape(size, size)
    metal_mask = is_metal[centre["shape"]].reshape(size, size) & np.isin(sem, [CLASSES["frame"], CLASSES["base"], CLASSES["other"]])
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
        "metal": np.where(metal_mask, 255, 0).astype(np.uint8),
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


GT_RULES = ("depth/semantic/metal: one ray through the pixel centre; normal/albedo/roughness/metallic: mean of {n}x{n} stratified rays "
            "that hit; glass (case panes, painting covers): maps describe the first opaque surface seen through the clear pane; through "
            "a display case the label is 6 (other) on an exhibit, else 2 (display); behind a painting's cover the canvas's 0; "
            "ceiling, skylight wells and diffusers and ceiling lamp panels are labelled 4 (wall); exhibits, benches, signs and "
            "plaques 6 (other); "
            "metal = metallic >= 0.5 and label frame/base/other; normals world-space facing the camera, encoded (n+1)/2, 0 where "
            "nothing was hit; albedo is the linear principled base_color; 255 / depth 0 / maps 0 where a ray escapes (sky)")


def _auto_exposure(radiance: np.ndarray, target: float = 0.42) -> float:
    """Scale k with mean(sRGB(clip(k·radiance))) = target (bisection)."""
    from toolkit.io import linear_to_srgb

    lo, hi = 1e-6, 1e6
    for _ in range(80):
        mid = math.sqrt(lo * hi)
        if float(linear_to_srgb(np.clip(radiance * mid, 0, 1)).mean()) < target:
            lo = mid
        else:
            hi = mid
    return math.sqrt(lo * hi)
