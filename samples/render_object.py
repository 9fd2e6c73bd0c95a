"""Path-trace an object capture with full ground truth (Mitsuba 3): a reference mesh under an HDR probe, RGBA photos.

The object set that the galleries lack: a real shape (``../shared/data/meshes``: spot, bob, the Stanford bunny, the
armadillo) on a transparent background, lit by one of the probes in ``../shared/data/envmaps`` at a random rotation,
seen from cameras spread over a sphere around it, like NeRF's synthetic scenes. Every view carries the same
ground truth as a gallery (depth, world normals, albedo, roughness, metallic, labels, metal mask; the rules of
``gallery_scene.GT_RULES``), so an object's normals and albedo can be scored, not just its photos.

* **Shape**: the mesh, turned from its file's +y up to our +z up, centred, scaled to a bounding sphere of radius 1
  (``ObjectOptions.radius``), turned by a random yaw.
* **Material**: Mitsuba's ``principled`` BSDF. Spot and bob carry their own texture as ``base_color``; the bunny and
  the armadillo get a plain colour drawn from the seed. Roughness is drawn in [0.25, 0.8]; a quarter of the seeds
  make the object metal (metallic 1, the label's metal mask set).
* **Light**: the probe (drawn from the seed unless ``--env``), rotated about +z by a random angle, exposed so that
  the object's pixels average 0.45 in sRGB. ``"sh"`` in the JSON is that probe's SH as used (it is the object's
  light: nothing else is in the scene).
* **Photos**: RGBA PNGs, straight (not premultiplied) colour, alpha the share of a pixel's samples that hit the
  object. The probe is hidden (alpha 0 around the object), as in NeRF's synthetic scenes.
* **Cameras**: looking at the centre from directions drawn over the sphere (elevation −20° to 75°), at a distance
  where the bounding sphere spans ~85 % of the 40° field of view; the test views are drawn separately.

Usage::

    .venv/bin/python samples/render_object.py --mesh spot --seed 0 --out /tmp/objects/spot_s0
    .venv/bin/python samples/render_object.py --mesh all --seed 0 --out /tmp/objects      # one directory per mesh

The meshes' licences are theirs (``../shared/data/meshes``); renders go outside the repository.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

_REPO = Path(__file__).resolve().parents[1]
if str(_REPO) not in sys.path:
    sys.path.insert(0, str(_REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from toolkit._checks import ConfigError  # noqa: E402

from gallery_config import BACKGROUND, CLASSES  # noqa: E402
from gallery_scene import (  # noqa: E402
    ENVMAPS,
    GT_RULES,
    _Built,
    _mitsuba_env_bitmap,
    c2w_to_mitsuba,
    environment_as_used,
    focal_from_fov,
    import_mitsuba,
    load_environment,
    render_gt,
    shared_data_dir,
)

MESH_ROOT = shared_data_dir("meshes", "DARS_MESHES")
"""Where the reference meshes are read from (never copied into the repo): ``$DARS_MESHES``,
``$DARS_SHARED_DATA/meshes``, ``../shared/data/meshes`` beside the clone, else ``/work/shared/data/meshes``."""
MESHES: dict[str, tuple[str, str | None]] = {
    "spot": ("spot/spot.obj", "spot/spot_texture.png"),
    "bob": ("bob/bob_tri.obj", "bob/bob_diffuse.png"),
    "bunny": ("stanford_bunny/bun_zipper.ply", None),
    "armadillo": ("armadillo/armadillo.obj", None),
}
"""Mesh name → (file, texture) under :data:`MESH_ROOT`."""
PROBES = ("ennis", "grace_new", "pisa", "wells")


@dataclass(frozen=True)
class ObjectOptions:
    """What to render: image size, views, samples per pixel, ground-truth subsamples, field of view, bounding radius."""

    size: int = 128
    n_train: int = 100
    n_test: int = 20
    spp: int = 144
    gt_subsamples: int = 3
    fov_x_deg: float = 40.0
    radius: float = 1.0
    fill: float = 0.85
    """Share of the field of view the bounding sphere spans."""
    target_mean_srgb: float = 0.45
    env: str | None = None
    """Probe name (``ennis``, ``grace_new``, ``pisa``, ``wells``); None: drawn from the seed."""
    max_depth: int = 8
    progress: bool = True


@dataclass(frozen=True)
class ObjectDraw:
    """What the seed draws for one mesh."""

    mesh: str
    seed: int
    yaw_deg: float
    color: tuple[float, float, float] | None
    roughness: float
    metallic: float
    env: str
    env_rotate_deg: float


def draw(mesh: str, seed: int, env: str | None = None) -> ObjectDraw:
    """The material and the light of ``mesh`` under ``seed`` (deterministic)."""
    if mesh not in MESHES:
        raise ConfigError(f"unknown mesh {mesh!r}: choose one of {sorted(MESHES)}")
    rng = np.random.default_rng([seed, sorted(MESHES).index(mesh)])
    yaw = float(rng.uniform(0, 360))
    hue = rng.uniform(0, 1)
    sat, val = rng.uniform(0.15, 0.6), rng.uniform(0.35, 0.85)
    rgb = np.clip(val * (1 - sat * (0.5 + 0.5 * np.cos(2 * math.pi * (hue - np.array([0.0, 1 / 3, 2 / 3]))))), 0.02, 0.95)
    rough = float(rng.uniform(0.25, 0.8))
    metallic = 1.0 if rng.uniform() < 0.25 else 0.0
    probe = env or PROBES[int(rng.integers(len(PROBES)))]
    if probe not in PROBES:
        raise ConfigError(f"unknown probe {probe!r}: choose one of {list(PROBES)}")
    return ObjectDraw(mesh, seed, yaw, None if MESHES[mesh][1] else tuple(float(c) for c in rgb), rough, metallic, probe,
                      float(rng.uniform(0, 360)))


def orbit_cameras(n: int, seed: int, radius: float, fov_x: float, fill: float) -> np.ndarray:
    """OpenGL camera-to-world [n, 4, 4] looking at the origin from directions spread over elevations −20°..75°
    (a golden-angle spiral with a random phase), at the distance where a sphere of ``radius`` spans ``fill`` of the
    field of view."""
    rng = np.random.default_rng(seed)
    dist = radius / math.sin(0.5 * fov_x * fill)
    lo, hi = math.sin(math.radians(-20)), math.sin(math.radians(75))
    phase = rng.uniform(0, 2 * math.pi)
    out = np.zeros((n, 4, 4))
    for i in range(n):
        z = lo + (hi - lo) * (i + rng.uniform(0.2, 0.8)) / n
        phi = phase + i * math.pi * (3 - math.sqrt(5))
        d = np.array([math.sqrt(1 - z * z) * math.cos(phi), math.sqrt(1 - z * z) * math.sin(phi), z])
        eye = d * dist
        back = d  # the camera looks along -back
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        up = np.cross(back, right)
        out[i, :3, 0], out[i, :3, 1], out[i, :3, 2], out[i, :3, 3] = right, up, back, eye
        out[i, 3, 3] = 1.0
    return out


def _mesh_transform(mi, path: Path, radius: float, yaw_deg: float):
    """to_world of a mesh: +y up → +z up, bounding-box centre at the origin, half-diagonal ``radius``, yaw about z."""
    kind = "ply" if path.suffix == ".ply" else "obj"
    shape = mi.load_dict({"type": kind, "filename": str(path)})
    bb = shape.bbox()
    lo, hi = np.array(bb.min, np.float64), np.array(bb.max, np.float64)
    c, r = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2
    T = mi.ScalarTransform4f
    return kind, T().rotate([0, 0, 1], yaw_deg).rotate([1, 0, 0], 90).scale([radius / r] * 3).translate((-c).tolist())


def _mesh_path(mesh: str) -> Path:
    path = MESH_ROOT / MESHES[mesh][0]
    if not path.is_file():
        raise ConfigError(f"mesh {path} not found: set DARS_MESHES to the folder holding {sorted(MESHES)}")
    return path


def build_object(mi, d: ObjectDraw, env_latlong: np.ndarray, opts: ObjectOptions, placement=None) -> _Built:
    """The Mitsuba scene of one object under its probe, with the per-shape information ``render_gt`` reads.
    ``placement``: ``_mesh_transform``'s (kind, to_world) when the caller has it (else the mesh is read for its box)."""
    path, tex = _mesh_path(d.mesh), MESHES[d.mesh][1]
    kind, xform = placement or _mesh_transform(mi, path, opts.radius, d.yaw_deg)
    if tex:
        base: Any = mi.load_dict({"type": "bitmap", "filename": str(MESH_ROOT / tex)})
        base_spec: Any = base
    else:
        base = tuple(d.color)
        base_spec = {"type": "rgb", "value": list(base)}
    bsdf = {"type": "principled", "base_color": base_spec, "roughness": d.roughness, "metallic": d.metallic}
    T = mi.ScalarTransform4f
    scene = mi.load_dict({
        "type": "scene",
        "env": {"type": "envmap", "bitmap": mi.Bitmap(_mitsuba_env_bitmap(env_latlong)),
                "to_world": T().rotate([0, 0, 1], d.env_rotate_deg).rotate([1, 0, 0], 90)},
        "object": {"type": kind, "filename": str(path), "to_world": xform, "bsdf": bsdf},
    }, optimize=False)
    shape = scene.shapes()[0]
    info = [{"name": "object", "cls": "other", "label": CLASSES["other"], "base_color": base, "glass": "",
             "roughness": d.roughness, "metallic": d.metallic, "metal": d.metallic >= 0.5}]
    ids = {}
    if not mi.variant().startswith("scalar"):
        import drjit as dr

        ids[int(np.array(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape)))[0])] = 0
    return _Built(scene=scene, shapes=[shape], info=info, meta={"object": d.mesh}, ids=ids)


def _render_rgba(mi, built: _Built, cameras: np.ndarray, size: int, fov_x: float, spp: int, max_depth: int, seed: int,
                 progress: bool, desc: str) -> np.ndarray:
    """float32 [N, H, W, 4]: linear premultiplied radiance (the probe hidden) and coverage."""
    from tqdm import tqdm

    sensor = mi.load_dict({
        "type": "perspective", "fov": math.degrees(fov_x), "fov_axis": "x",
        "to_world": mi.ScalarTransform4f(c2w_to_mitsuba(cameras[0]).tolist()),
        "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}, "pixel_format": "rgba"},
        "sampler": {"type": "multijitter", "sample_count": spp},
    })
    integrator = mi.load_dict({"type": "path", "max_depth": max_depth, "hide_emitters": True})
    params = mi.traverse(sensor)
    T = mi.ScalarTransform4f if mi.variant().startswith("scalar") else mi.Transform4f
    out = np.zeros((len(cameras), size, size, 4), np.float32)
    for i in tqdm(range(len(cameras)), desc=desc, disable=not progress, file=sys.stderr):
        params["to_world"] = T(c2w_to_mitsuba(cameras[i]).tolist())
        params.update()
        out[i] = np.array(mi.render(built.scene, sensor=sensor, integrator=integrator, spp=spp, seed=seed * 1009 + i))[..., :4]
    return out


def _exposure(rgba: np.ndarray, target: float) -> float:
    """Scale k with the mean sRGB of the object's pixels (coverage > 0.5, colour un-premultiplied) at ``target``."""
    from toolkit.io import linear_to_srgb

    cov = rgba[..., 3]
    m = cov > 0.5
    if not m.any():
        raise ConfigError("the object is in none of the preview views: check the mesh and --radius")
    rgb = rgba[..., :3][m] / cov[m][:, None]
    lo, hi = 1e-6, 1e6
    for _ in range(80):
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if float(linear_to_srgb(np.clip(rgb * mid, 0, 1)).mean()) < target else (lo, mid)
    return math.sqrt(lo * hi)


def render_object(mesh: str, seed: int, out_dir: str | Path, opts: ObjectOptions = ObjectOptions(),
                  variant: str | None = None) -> dict[str, Any]:
    """Render one object capture into ``out_dir`` (``transforms_{train,test}.json``, RGBA PNGs, ground-truth maps),
    loadable by :func:`toolkit.scene.load_scene`. Returns a summary (seconds, exposure, the draw)."""
    import render_gallery as rg
    import torch

    from toolkit.io import write_hdr, write_json
    from toolkit.sh import fit_sh_probe

    t0 = time.time()
    d = draw(mesh, seed, opts.env)
    mi, dr, variant = import_mitsuba(variant)
    mi.set_log_level(mi.LogLevel.Error)  # the meshes' PLY/OBJ loaders warn about attributes we do not use
    fov = math.radians(opts.fov_x_deg)
    env0 = load_environment(str(ENVMAPS / f"probulator_{d.env}_256x128.hdr"))
    cams = {"train": orbit_cameras(opts.n_train, seed * 2 + 0, opts.radius, fov, opts.fill),
            "test": orbit_cameras(opts.n_test, seed * 2 + 1, opts.radius, fov, opts.fill)}
    placement = _mesh_transform(mi, _mesh_path(mesh), opts.radius, d.yaw_deg)  # the mesh's box, read once
    preview = _render_rgba(mi, build_object(mi, d, env0.latlong, opts, placement), cams["train"][:: max(1, opts.n_train // 8)],
                           48, fov, 16, opts.max_depth, seed, False, "")
    k = _exposure(preview, opts.target_mean_srgb)
    latlong = env0.latlong * np.float32(k)
    built = build_object(mi, d, latlong, opts, placement)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    H, W = latlong.shape[:2]
    sh = fit_sh_probe(torch.as_tensor(environment_as_used(mi, dr, built, 2 * H, 2 * W), dtype=torch.float64)).to_list()
    write_hdr(out_dir / "env.hdr", environment_as_used(mi, dr, built, H, W))
    f = focal_from_fov(fov, opts.size)
    header = {"camera_angle_x": fov, "fl_x": f, "fl_y": f, "cx": opts.size / 2.0, "cy": opts.size / 2.0, "w": opts.size, "h": opts.size,
              "sh": sh, "envmap": "env.hdr", "depth_unit_scale_factor": 0.001,
              "render": {"renderer": "mitsuba", "mitsuba_version": mi.__version__, "variant": variant, "profile": "object",
                         "integrator": f"path (max_depth {opts.max_depth}, probe hidden)", "spp": opts.spp, "pixel_filter": "box",
                         "draw": asdict(d), "options": asdict(opts), "exposure": k,
                         "sh_definition": "SPEC SH of the probe as used (rotation and exposure applied); nothing else lights the object",
                         "gt_rules": GT_RULES.format(n=opts.gt_subsamples), "image": "RGBA, straight alpha = coverage; probe hidden"},
              "scene": {"classes": CLASSES, "background_label": BACKGROUND, "object": d.mesh}}
    seconds = {"preview": round(time.time() - t0, 1)}
    for split, c in cams.items():
        if not len(c):
            continue
        t1 = time.time()
        rgba = _render_rgba(mi, built, c, opts.size, fov, opts.spp, opts.max_depth, seed + (7 if split == "test" else 0),
                            opts.progress, f"{mesh} seed {seed} {split}")
        gt = [render_gt(mi, dr, built, c[i], fov, opts.size, opts.gt_subsamples) for i in range(len(c))]
        res = {key: np.stack([g[key] for g in gt]) for key in gt[0]}
        cov = rgba[..., 3:4]
        res["radiance"] = np.where(cov > 1e-4, rgba[..., :3] / np.maximum(cov, 1e-4), 0.0).astype(np.float32)
        res["alpha"] = np.clip(cov[..., 0], 0.0, 1.0)
        rg.write_split(out_dir, split, res, c, header, image_format="rgba", write_hdr_files=False)
        seconds[split] = round(time.time() - t1, 1)
    summary = {"mesh": mesh, "seed": seed, "draw": asdict(d), "exposure": k, "seconds": seconds, "variant": variant,
               "views": {s: len(c) for s, c in cams.items()}}
    write_json(out_dir / "render_summary.json", summary)
    return summary


VALIDATION = tuple((m, 0) for m in sorted(MESHES))
"""The object validation set: every mesh at seed 0 (no code path is tuned to one)."""
OBJECT_VERSION = 1
"""Bumped when a render of the same draw and options changes (invalidates the cache)."""


def cache_dir(mesh: str, seed: int, root: str | Path | None = None) -> Path:
    """Where an object capture is cached: ``<root>/objects/<mesh>_s<seed>``, ``root`` by default the galleries'
    cache base (``$DARS_CACHE``, else ``~/.cache/dars``)."""
    from galleries import dars_cache

    return (Path(root).expanduser() if root else dars_cache()) / "objects" / f"{mesh}_s{int(seed)}"


def cache_stamp(mesh: str, seed: int, opts: ObjectOptions = ObjectOptions()) -> dict[str, Any]:
    """What determines a cached capture (version, draw, options) and its sha256 (``hash``, 16 hex digits)."""
    import hashlib
    import json

    stamp = {"version": OBJECT_VERSION, "draw": asdict(draw(mesh, seed, opts.env)), "options": asdict(replace(opts, progress=True))}
    return {"hash": hashlib.sha256(json.dumps(stamp, sort_keys=True).encode()).hexdigest()[:16], **stamp}


def ensure_object(mesh: str, seed: int, opts: ObjectOptions = ObjectOptions(), root: str | Path | None = None,
                  variant: str | None = None) -> Path:
    """The cached capture of ``mesh`` at ``seed``, rendered first (into a temporary folder, then renamed) when missing
    or made by other options."""
    import json

    from galleries import _lock, render_in_place_of

    stamp = cache_stamp(mesh, seed, opts)
    out = cache_dir(mesh, seed, root)
    with _lock(out.parent / f".lock-{out.name}"):
        try:
            if json.loads((out / "stamp.json").read_text()).get("hash") == stamp["hash"]:
                return out
        except (OSError, ValueError):
            pass

        def render(tmp: Path) -> dict:
            render_object(mesh, seed, tmp, opts, variant)
            return stamp

        render_in_place_of(out, render)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mesh", default="all", help=f"one of {sorted(MESHES)}, a comma-separated list, or all (default)")
    ap.add_argument("--seed", type=int, default=0, help="draws the material, the probe, its rotation and the cameras")
    ap.add_argument("--out", required=True, help="output directory (with several meshes: one subdirectory <mesh>_s<seed> each)")
    ap.add_argument("--size", type=int, default=ObjectOptions.size)
    ap.add_argument("--n-train", type=int, default=ObjectOptions.n_train)
    ap.add_argument("--n-test", type=int, default=ObjectOptions.n_test)
    ap.add_argument("--spp", type=int, default=ObjectOptions.spp)
    ap.add_argument("--env", choices=PROBES, default=None, help="the probe (default: drawn from the seed)")
    ap.add_argument("--variant", default=None, help="Mitsuba variant (default llvm_ad_rgb where libLLVM 19 is present)")
    a = ap.parse_args(argv)
    meshes = sorted(MESHES) if a.mesh == "all" else [m.strip() for m in a.mesh.split(",")]
    opts = ObjectOptions(size=a.size, n_train=a.n_train, n_test=a.n_test, spp=a.spp, env=a.env)
    try:
        for m in meshes:
            out = Path(a.out) / f"{m}_s{a.seed}" if len(meshes) > 1 or a.mesh == "all" else Path(a.out)
            s = render_object(m, a.seed, out, opts, a.variant)
            print(f"{m} seed {a.seed}: {out}  probe {s['draw']['env']}  metallic {s['draw']['metallic']:.0f}  "
                  f"roughness {s['draw']['roughness']:.2f}  {sum(v for v in s['seconds'].values()):.0f} s")
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
