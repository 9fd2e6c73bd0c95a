"""Path-trace galleries with full ground truth (Mitsuba 3): the bundled sample, and procedural galleries by seed.

Two kinds of scene share one renderer:

* ``--preset sample`` (:meth:`GalleryConfig.sample`, the default): the bundled ``samples/gallery`` — a back wall and
  a planked floor (an open corner), a procedural painting (roughness 0.6) in a gold frame, a stone pedestal with a
  twisted metal sculpture in a glass case, lit only by an HDR environment. ``make sample`` re-renders it with the
  ``sample`` profile (80 + 20 views, 400 spp, the hand-set ``aabb``); its ``"sh"`` is the environment's SH.
* ``--seed N`` (:func:`procedural.random_gallery`): a closed gallery room drawn from the seed — size, walls, floor,
  a ceiling with 0–3 skylights or an open top, 1–5 framed paintings (gilt, wood, glass-covered), pedestals with metal
  and ceramic exhibits, display cases, benches and signs, daylight from an HDR probe plus 0–4 lamps, camera
  walks/arcs/close-ups inside the room (see ``samples/procedural.py``). Profiles: ``validation`` (128 px, 100 + 20
  views, passes of 64 spp until two renders would agree at ≥ 38 dB, at most 1024 spp) and ``prior`` (160 px,
  10 + 2 views, 2 x 24 spp) for network training. ``samples/galleries.py`` caches them by seed.

Daylight: through an open top the probe is seen and lights the room directly (open-top rooms draw the two probes
whose light is spread, :data:`procedural.SMOOTH_PROBES`). Skylights are frosted, as museum skylights are (direct
sun is kept off the art): each is a laylight, a Lambertian diffuser flush with the ceiling whose radiance is the probe's
upward irradiance / π (:func:`daylight_radiance`, recorded as ``render.skylight_radiance``). Clear skylights were
tried and dropped: a path tracer finds the sky through a small opening so rarely that 512 spp left the views at
15–20 dB (two-render PSNR), where laylights and lamps give 36–38 dB at 256 spp. Every emitter is picked for
next-event estimation with the same probability (Mitsuba's default): picking in proportion to flux starved the spots
that light a painting (its views fell from 42 to 30 dB at 256 spp).

Conventions (SPEC): cameras are OpenGL camera-to-world (x right, y up, looking −z); Mitsuba's sensor looks +z with x
to the left, so ``to_world = c2w @ diag(−1, 1, −1, 1)`` (:func:`c2w_to_mitsuba`). Pinhole, square pixels, principal
point at the image centre, pixel centres at ``(col+½, row+½)``. World +z up, metres.

Materials: Mitsuba's ``principled`` BSDF; glass (case panes, painting covers) is ``thindielectric`` (an ideal smooth
thin pane). The sample uses the ``path`` integrator as it was rendered; procedural galleries use ``volpath``, whose
shadow rays pass through the panes' null-transmission lobe (Fresnel-weighted), so lamps light exhibits in cases and
paintings under glass (``path`` treats panes as opaque for next-event estimation).

Ground truth (per view, one file per map, keys as in SPEC / nerfstudio):

* ``radiance`` (``*.hdr``): path-traced linear radiance, box pixel filter; the PNG is its sRGB (clipped at 1).
* ``depth`` (along −z_cam, metres, 16-bit PNG in mm), ``semantic`` (uint8: 0 painting, 1 frame, 2 display, 3 base,
  4 wall, 5 floor, 6 other, 255 nothing hit = sky through an opening or the open top), ``metal`` (255 where the
  surface is the metal subclass — metallic ≥ 0.5 — of frame, base or other): one ray through each pixel centre (hard
  labels; every depth is a real surface point).
* ``normal`` (world, facing the camera, encoded (n+1)/2, 0 where nothing was hit), ``albedo`` (linear principled
  ``base_color``), ``roughness``, ``metallic``: anti-aliased, the mean of ``gt_subsamples²`` stratified rays per
  pixel over the rays that hit geometry.
* Classes: the ceiling, skylight wells and diffusers, ceiling lamp panels and walls are ``wall`` (4) — there is no
  ceiling class and, like a wall, the ceiling with what is set into it is room structure that a room prior should
  treat as such; exhibits, benches, sign stands and wall plaques are ``other`` (6); pedestals ``base`` (3); a
  painting's glass cover is part of the painting (0).
* Glass rule: panes are clear (≈ 92 % transmission), so the image shows what lies behind them. Depth, normal and
  material maps describe the first opaque surface behind the glass (what the pixel shows, so photometric and
  geometric supervision agree). Behind a painting's cover the label is the canvas's (0). Through a display case the
  label is ``other`` (6) where that surface is an exhibit (an annotator labels the exhibit) and ``display`` (2)
  elsewhere inside the case's silhouette. A ray that crosses glass and escapes keeps the first pane's values.

Scene-level light ground truth (JSON): for a closed room the environment probe is not the scene's light, so
``"sh"`` is the SPEC SH projection (incident radiance, world +z up, [9, 3], :func:`toolkit.sh.fit_sh_probe`
conventions) of the incident radiance at one point — the room centre at eye height 1.6 m
(:func:`procedural.probe_point`, stored as ``render.sh_point``): a cube map (6 perspective 90° views of
``probe_face`` px, ``probe_spp`` spp, same integrator) projected with exact per-pixel solid angles, plus the point and
spot lamps added analytically (a delta lamp contributes ``E·Y(ω)`` with ``E`` the irradiance Mitsuba's own emitter
query gives at the point, 0 when occluded; a cube map cannot see them). ``light.hdr`` (``"envmap"``) is that
panorama as a SPEC lat-long map with the delta lamps splatted into their pixels; ``"sh_env"`` is the probe's own SH
at the exposure used (the :func:`environment_as_used` query projected, as the sample's ``"sh"``), and
``env.hdr`` (``"probe_envmap"``) that probe. The cube-map projection reproduces a probe's SH to 0.2 % of its DC term
when nothing occludes it (16 px faces; tested); in the sample's open corner the point SH differs from the probe's by
≤ 0.10 of the DC term, in the z and y bands (the floor replaces the lower hemisphere, the wall a slice of +y). For the sample preset ``"sh"`` keeps its old meaning (the environment's
SH — the corner is open and lit by nothing else) and the cube-map SH is stored as ``"sh_point"``.

Exposure: the sample scales the environment so the preview's mean sRGB is 0.42. A procedural gallery renders a
preview (8 train views, 48 px, 16 spp) with the environment alone and with the lamps alone, mixes them so the lamps
give ``lighting.lamp_share`` of the mean radiance, and scales both so the mean sRGB is ``lighting.target_mean_srgb``
(bisection; exact up to preview noise because rendering is linear in the emitters). The factors are in
``render.exposure`` and already in the images, ``"sh"``, ``"sh_env"`` and the HDR files.

Noise: a procedural view is rendered in passes of ``spp_per_pass`` samples with distinct seeds; the PSNR between
the mean of the even and the mean of the odd passes (8-bit sRGB) plus 3.01 dB estimates how well two full renders
with different seeds would agree (each half has twice the variance of the whole). With ``target_noise_db`` a view
gets more passes until the estimate reaches it (``max_passes`` caps it). Per-view spp and estimates are in the
frames, their summary in ``render.noise``; ``--noise-check N`` measures it directly with two full renders. The
sample: 400 spp ``multijitter``, two seeds agree at ≈ 41–42 dB.

Usage::

    export DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1
    .venv/bin/python samples/render_gallery.py --preset sample --out samples/gallery          # make sample
    .venv/bin/python samples/render_gallery.py --seed 7 --profile validation --out /tmp/g7
    .venv/bin/python samples/render_gallery.py --seed 7 --profile prior --out /tmp/g7p --box  # + a tight room aabb
    .venv/bin/python samples/render_gallery.py --seed 7 --print-config                        # the drawn config
"""

from __future__ import annotations

import json
import math
import sys
import time
import zlib
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Literal, Sequence

import numpy as np

_REPO = Path(__file__).resolve().parents[1]
if str(_REPO) not in sys.path:
    sys.path.insert(0, str(_REPO))

from toolkit._checks import ConfigError, DarsError  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gallery_scene import (  # noqa: E402,F401  (re-exported: tools and tests use render_gallery.<name>)
    DEFAULT_ENV,
    ENVMAPS,
    GT_RULES,
    LIBLLVM19,
    Environment,
    _auto_exposure,
    _Built,
    _mitsuba_env_bitmap,
    _trace,
    _trace_gt,
    build_scene,
    c2w_to_mitsuba,
    daylight_radiance,
    daylight_reaches,
    default_variant,
    env_emitter_visible,
    environment_as_used,
    environment_of,
    focal_from_fov,
    import_mitsuba,
    llvm_available,
    load_environment,
    pixel_rays,
    render_gt,
    sample_cameras,
    scene_meta,
)
from procedural import (  # noqa: E402,F401
    BACKGROUND,
    CLASSES,
    GENERATOR_VERSION,
    GalleryConfig,
    check_cameras,
    gallery_cameras,
    look_at,
    probe_point,
    random_gallery,
    sample_front_cameras,
)


# ------------------------------------------------------------------------------------------------------ configuration
@dataclass(frozen=True)
class RenderSettings:
    """Path-tracing options of :func:`render_views`."""

    spp: int = 400
    """Samples per pixel of one pass."""
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
    integrator: Literal["path", "volpath"] = "path"
    min_passes: int = 1
    """Passes of ``spp`` samples per view (with distinct seeds; their mean is the image)."""
    max_passes: int = 1
    target_noise_db: float | None = None
    """Add passes (in pairs) until the two-render agreement estimate reaches this, up to ``max_passes``."""
    seed_rule: Literal["sample", "hash"] = "sample"
    """``sample``: view i uses seed ``seed·100003 + i`` (as the bundled sample); ``hash``: a hash of (seed, split,
    view, pass), distinct across splits and passes."""


@dataclass(frozen=True)
class RenderOptions:
    """A render profile: image size, views, sampling and ground-truth options of :func:`render_gallery`."""

    profile: str = "validation"
    size: int = 128
    n_train: int = 100
    n_test: int = 20
    spp_per_pass: int = 64
    min_passes: int = 4
    max_passes: int = 16
    target_noise_db: float | None = 38.0
    """Two renders with different seeds should agree at this PSNR (8-bit sRGB); None: fixed ``min_passes``."""
    sampler: str = "multijitter"
    max_depth: int = 8
    gt_subsamples: int = 4
    probe_face: int = 64
    """Cube-map face size of the SH light probe."""
    probe_spp: int = 256
    box: bool = False
    """Write a tight ``aabb`` of the room into the JSON (default: none, as a real capture)."""
    seed: int = 0
    """Seed of the sampling noise (not of the gallery)."""
    variant: str | None = None
    write_hdr: bool = True
    progress: bool = True
    wall_patterns: float = 0.0
    """Chance that a procedural room's walls are papered, bricked or boarded (``procedural.random_gallery``); 0 keeps
    every seed's room as it was before the option (the validation galleries)."""


PROFILES: dict[str, RenderOptions] = {
    "validation": RenderOptions(),
    "prior": RenderOptions(profile="prior", size=160, n_train=10, n_test=2, spp_per_pass=24, min_passes=2, max_passes=2,
                           target_noise_db=None, gt_subsamples=2, probe_face=32, probe_spp=64),
    "sample": RenderOptions(profile="sample", size=128, n_train=80, n_test=20, spp_per_pass=400, min_passes=1, max_passes=1,
                            target_noise_db=None, box=True),
    "walls": RenderOptions(profile="walls", size=160, n_train=10, n_test=2, spp_per_pass=24, min_passes=2, max_passes=2,
                           target_noise_db=None, gt_subsamples=2, probe_face=32, probe_spp=64, wall_patterns=0.5),
    "light": RenderOptions(profile="light", size=64, n_train=8, n_test=0, spp_per_pass=16, min_passes=2, max_passes=2,
                           target_noise_db=None, gt_subsamples=1, probe_face=24, probe_spp=48),
    "tiny": RenderOptions(profile="tiny", size=24, n_train=2, n_test=1, spp_per_pass=4, min_passes=2, max_passes=2,
                          target_noise_db=None, gt_subsamples=2, probe_face=8, probe_spp=4, progress=False),
}
"""Named profiles. ``sample`` reproduces ``samples/gallery``; ``prior`` trains the segmenter and the light network;
``walls`` is ``prior`` with half the rooms' walls patterned (wallpaper, brick, boarding, plaster: the segmenter's
fine-tuning data, 2026-12-06); ``light`` is many small rooms for the light network (64 px, the network's input size; 8 views; no test split);
``tiny`` is for tests."""


# ------------------------------------------------------------------------------------------------------- the stage
def _pass_seed(settings: RenderSettings, split: str, view: int, p: int) -> int:
    if settings.seed_rule == "sample":
        return settings.seed * 100003 + view + 7919 * p
    return zlib.crc32(f"{settings.seed}:{split}:{view}:{p}".encode())


def _srgb8(x: np.ndarray) -> np.ndarray:
    from toolkit.io import linear_to_srgb

    return np.round(linear_to_srgb(np.clip(x, 0, 1)) * 255.0)


def psnr8(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB) between two linear images after 8-bit sRGB quantisation (inf if identical)."""
    mse = float(((_srgb8(a) - _srgb8(b)) ** 2).mean())
    return 10.0 * math.log10(255.0**2 / mse) if mse > 0 else float("inf")


def _render_built(mi, dr, built: _Built, cameras: np.ndarray, size: int, fov_x: float, settings: RenderSettings,
                  split: str = "", desc: str = "render") -> dict[str, Any]:
    from tqdm import tqdm

    variant = mi.variant()
    sensor = mi.load_dict({
        "type": "perspective", "fov": math.degrees(fov_x), "fov_axis": "x",
        "to_world": mi.ScalarTransform4f(c2w_to_mitsuba(cameras[0]).tolist()),
        "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        "sampler": {"type": settings.sampler, "sample_count": settings.spp},
    })
    integrator = mi.load_dict({"type": settings.integrator, "max_depth": settings.max_depth, "hide_emitters": False})
    params = mi.traverse(sensor)
    N = len(cameras)
    out: dict[str, Any] = {"radiance": np.zeros((N, size, size, 3), np.float32), "spp": np.zeros(N, np.int32),
                           "noise_db": np.full(N, np.nan), "seconds_radiance": 0.0, "seconds_gt": 0.0}
    gt_keys = {"depth": (np.float32, ()), "normal": (np.float32, (3,)), "albedo": (np.float32, (3,)), "roughness": (np.float32, ()),
               "metallic": (np.float32, ()), "semantic": (np.uint8, ()), "metal": (np.uint8, ())}
    if settings.gt:
        for k, (dt, tail) in gt_keys.items():
            out[k] = np.zeros((N, size, size) + tail, dt)
    T = mi.ScalarTransform4f if variant.startswith("scalar") else mi.Transform4f
    min_p, max_p = max(1, settings.min_passes), max(settings.min_passes, settings.max_passes, 1)
    for i in tqdm(range(N), desc=f"{desc} ({variant}, {settings.spp} spp/pass)", disable=not settings.progress, file=sys.stderr):
        t0 = time.time()
        params["to_world"] = T(c2w_to_mitsuba(cameras[i]).tolist())
        params.update()
        halves = [np.zeros((size, size, 3)), np.zeros((size, size, 3))]
        p = 0
        while True:
            img = mi.render(built.scene, sensor=sensor, integrator=integrator, spp=settings.spp, seed=_pass_seed(settings, split, i, p))
            halves[p % 2] += np.array(img)[..., :3]
            p += 1
            if p < min_p or p % 2 == 1 and p < max_p:
                continue
            if p >= 2 and p % 2 == 0:
                out["noise_db"][i] = psnr8(halves[0] / (p // 2), halves[1] / (p // 2)) + 10 * math.log10(2.0)
            if p >= max_p or settings.target_noise_db is None or out["noise_db"][i] >= settings.target_noise_db:
                break
        out["radiance"][i] = ((halves[0] + halves[1]) / p).astype(np.float32)
        out["spp"][i] = p * settings.spp
        t1 = time.time()
        out["seconds_radiance"] += t1 - t0
        if settings.gt:
            for k, v in render_gt(mi, dr, built, cameras[i], fov_x, size, settings.gt_subsamples).items():
                out[k][i] = v
            out["seconds_gt"] += time.time() - t1
    return out


def render_views(
    scene_cfg: GalleryConfig,
    cameras: np.ndarray,
    env: Environment | None,
    size: int,
    spp: int,
    fov_x: float = math.radians(45.0),
    settings: RenderSettings | None = None,
    workdir: str | Path | None = None,
    lamp_scale: float = 1.0,
    split: str = "",
) -> dict[str, Any]:
    """Path-trace views of a gallery, with ground-truth maps.

    Args:
        scene_cfg: the gallery (geometry, materials, lamps).
        cameras: float [N, 4, 4] OpenGL camera-to-world matrices.
        env: environment light (SPEC lat-long map, world placement), or None.
        size: square image size in pixels.
        spp: samples per pixel of one pass (overrides ``settings.spp``).
        fov_x: horizontal field of view, radians.
        settings: seed, passes, max depth, integrator, variant, whether to trace GT maps.
        workdir: where to put the exhibit meshes (default: a temporary directory).
        lamp_scale: multiplies the lamps (0: off).
        split: name mixed into the pass seeds (``seed_rule="hash"``).

    Returns:
        dict with ``radiance`` float32 [N, H, W, 3] linear, ``spp`` int [N], ``noise_db`` [N] (NaN with one pass);
        with ``settings.gt``: ``depth`` [N, H, W] metres along −z_cam (0 = miss), ``normal`` [N, H, W, 3] world,
        ``albedo`` [N, H, W, 3] linear, ``roughness``, ``metallic`` [N, H, W], ``semantic``, ``metal`` uint8
        [N, H, W]; plus ``variant``, ``scene_meta``, ``seconds``.
    """
    import tempfile

    settings = replace(settings or RenderSettings(), spp=spp)
    cameras = np.asarray(cameras, dtype=np.float64).reshape(-1, 4, 4)
    if size < 1 or spp < 1:
        raise ConfigError(f"size={size} and spp={spp} must be positive")
    mi, dr, variant = import_mitsuba(settings.variant)
    t0 = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        built = build_scene(mi, scene_cfg, env, Path(workdir) if workdir else Path(tmp), lamp_scale)
    out = _render_built(mi, dr, built, cameras, size, fov_x, settings, split)
    out["variant"] = variant
    out["scene_meta"] = built.meta
    out["seconds"] = time.time() - t0
    out["_built"] = built
    out["_mi"] = (mi, dr)
    return out


# ------------------------------------------------------------------------------------------------- light probe (SH)
CUBE_FACES = ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))


def cube_pixel_solid_angles(n: int) -> np.ndarray:
    """Exact solid angle of every pixel of an n x n cube-map face (90° field of view), float64 [n, n]; the six
    faces sum to 4π. Uses ``Ω(x, y) = atan(xy / sqrt(1 + x² + y²))`` at the pixel corners (face plane at unit
    distance, x, y ∈ [−1, 1])."""
    e = np.linspace(-1.0, 1.0, n + 1)
    X, Y = np.meshgrid(e, e, indexing="xy")
    F = np.arctan(X * Y / np.sqrt(1.0 + X * X + Y * Y))
    return np.abs(F[1:, 1:] - F[1:, :-1] - F[:-1, 1:] + F[:-1, :-1])


def cube_face_cameras(point: np.ndarray) -> np.ndarray:
    """Six OpenGL camera-to-world matrices at ``point`` looking along ±x, ±y, ±z (float64 [6, 4, 4])."""
    point = np.asarray(point, np.float64)
    return np.stack([look_at(point, point + np.asarray(d, np.float64), up=(0.0, 1.0, 0.0) if d[2] else (0.0, 0.0, 1.0)) for d in CUBE_FACES])


def _delta_lamps_at(mi, dr, built: _Built, point: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """(direction toward the lamp, irradiance rgb) of every point/spot emitter that sees ``point`` (Mitsuba's own
    emitter query: intensity, spot falloff and 1/d²; occlusion by a shadow ray)."""
    out = []
    scalar = mi.variant().startswith("scalar")
    for em in built.scene.emitters():
        if not mi.has_flag(em.flags(), mi.EmitterFlags.DeltaPosition):
            continue
        it = dr.zeros(mi.Interaction3f) if scalar else dr.zeros(mi.Interaction3f, 1)
        it.p = mi.Point3f(*[float(v) for v in point])
        ds, spec = em.sample_direction(it, mi.Point2f(0.5, 0.5))
        d = np.array(ds.d).reshape(-1)[:3]
        e = np.array(spec).reshape(-1)[:3]
        dist = float(np.array(ds.dist).reshape(-1)[0])
        ray = mi.Ray3f(mi.Point3f(*[float(v) for v in point]), mi.Vector3f(*[float(v) for v in d]))
        si = built.scene.ray_intersect(ray)
        t = float(np.array(si.t).reshape(-1)[0]) if bool(np.array(si.is_valid()).reshape(-1)[0]) else math.inf
        if t < dist * (1 - 1e-4) or not np.isfinite(e).all() or e.max() <= 0:
            continue
        out.append((d / np.linalg.norm(d), e))
    return out


def render_light_probe(mi, dr, built: _Built, point: np.ndarray, face: int, spp: int, settings: RenderSettings,
                       latlong_size: tuple[int, int] = (64, 128)) -> dict[str, Any]:
    """The incident radiance at ``point`` as SH (see the module docstring): cube map + delta lamps.

    Returns:
        dict with ``sh`` float64 [9, 3] (SPEC order, world frame), ``sh_cube`` (the cube map alone), ``latlong``
        float32 [H, W, 3] SPEC lat-long panorama (delta lamps splatted), ``delta_lamps`` (count), ``seconds``.
    """
    import torch

    from toolkit.sh import latlong_directions, latlong_solid_angles, sh_basis

    t0 = time.time()
    cams = cube_face_cameras(point)
    res = _render_built(mi, dr, built, cams, face, math.pi / 2, replace(settings, spp=spp, gt=False, min_passes=1, max_passes=1,
                                                                       target_noise_db=None, progress=False, seed_rule="hash"), "probe")
    _, dirs, _ = pixel_rays(np.eye(4), math.pi / 2, face)  # same for all faces up to the rotation
    omega = cube_pixel_solid_angles(face)
    sh = np.zeros((9, 3))
    all_d, all_l, all_w = [], [], []
    for k, c2w in enumerate(cams):
        d = (dirs[0].reshape(-1, 3) @ np.eye(3)) @ c2w[:3, :3].T
        Y = sh_basis(torch.as_tensor(d)).numpy()
        L = res["radiance"][k].reshape(-1, 3).astype(np.float64)
        w = omega.reshape(-1)
        sh += (Y * w[:, None]).T @ L
        all_d.append(d), all_l.append(L), all_w.append(w)  # noqa: E702
    sh_cube = sh.copy()
    lamps = _delta_lamps_at(mi, dr, built, point)
    for d, e in lamps:
        sh += sh_basis(torch.as_tensor(d[None])).numpy()[0][:, None] * e[None, :]
    # lat-long panorama: nearest cube texel per lat-long pixel centre, delta lamps splatted into their pixel
    H, W = latlong_size
    ll = latlong_directions(H, W, dtype=torch.float64).numpy().reshape(-1, 3)
    D = np.concatenate(all_d)
    Lall = np.concatenate(all_l)
    best = np.zeros(len(ll), np.int64)
    chunk = 4096
    for s in range(0, len(ll), chunk):
        best[s : s + chunk] = np.argmax(ll[s : s + chunk] @ D.T, axis=1)
    pano = Lall[best].reshape(H, W, 3)
    sa = latlong_solid_angles(H, W, dtype=torch.float64).numpy()
    for d, e in lamps:
        theta = math.acos(max(-1.0, min(1.0, d[2])))
        phi = math.atan2(d[0], d[1]) % (2 * math.pi)
        r, c = min(H - 1, int(theta / math.pi * H)), min(W - 1, int(phi / (2 * math.pi) * W))
        pano[r, c] += e / sa[r, c]
    return {"sh": sh, "sh_cube": sh_cube, "latlong": pano.astype(np.float32), "delta_lamps": len(lamps), "seconds": time.time() - t0}


# ------------------------------------------------------------------------------------------------------- file output
def _write_png(path: Path, image_hwc: np.ndarray, bits: int = 8) -> None:
    """Like :func:`toolkit.io.write_png` (same value mapping) but with maximum zlib compression (smaller files).
    RGBA images are written as such (alpha from the fourth channel)."""
    import cv2

    from toolkit.io import atomic_write

    img = np.asarray(image_hwc)
    if img.dtype.kind == "f":
        img = (np.clip(np.nan_to_num(img), 0.0, 1.0) * (255 if bits == 8 else 65535) + 0.5).astype(np.uint8 if bits == 8 else np.uint16)
    if img.ndim == 3 and img.shape[2] == 3:
        img = img[..., ::-1]
    elif img.ndim == 3 and img.shape[2] == 4:
        img = img[..., [2, 1, 0, 3]]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise OSError(f"could not encode PNG for {path}")
    with atomic_write(path) as f:
        f.write(buf.tobytes())


def write_split(out_dir: Path, split: str, res: dict[str, Any], cameras: np.ndarray, header: dict[str, Any],
                image_format: str = "rgb", write_hdr_files: bool = True, kinds: Sequence[str] | None = None) -> None:
    """Write one split's images, ground-truth maps and ``transforms_<split>.json``."""
    from toolkit.io import linear_to_srgb, write_hdr, write_json

    write_png = _write_png
    frames = []
    for i in range(len(cameras)):
        stem = f"{split}/r_{i:03d}"
        rad = res["radiance"][i]
        srgb = linear_to_srgb(np.clip(rad, 0, 1))
        if image_format == "rgba":  # alpha: res["alpha"] (straight colour) where given, else 255 everywhere
            alpha = res["alpha"][i][..., None] if "alpha" in res else np.ones_like(srgb[..., :1])
            srgb = np.concatenate([srgb, alpha], -1)
        write_png(out_dir / f"{stem}.png", srgb)
        frame: dict[str, Any] = {"file_path": f"{stem}.png", "transform_matrix": cameras[i].tolist()}
        if write_hdr_files:
            write_hdr(out_dir / f"{stem}.hdr", rad)
            frame["radiance_path"] = f"{stem}.hdr"
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
        frame.update({
            "depth_file_path": f"{stem}_depth.png", "normal_path": f"{stem}_normal.png", "albedo_path": f"{stem}_albedo.png",
            "roughness_path": f"{stem}_roughness.png", "metallic_path": f"{stem}_metallic.png",
            "semantic_path": f"{stem}_semantic.png", "metal_path": f"{stem}_metal.png",
        })
        if kinds is not None:
            frame["view_kind"] = kinds[i]
        if "spp" in res and not np.isnan(res["noise_db"][i]):
            frame["spp"] = int(res["spp"][i])
            frame["noise_psnr_db"] = round(float(res["noise_db"][i]), 2)
        frames.append(frame)
    write_json(out_dir / f"transforms_{split}.json", {**header, "frames": frames})


def noise_psnr(cfg: GalleryConfig, cameras: np.ndarray, env: Environment | None, size: int, fov_x: float, settings: RenderSettings,
               lamp_scale: float = 1.0) -> tuple[float, float]:
    """PSNR (dB) between two full renders with different seeds, on 8-bit sRGB, and seconds per view of one render."""
    t0 = time.time()
    a = render_views(cfg, cameras, env, size, settings.spp, fov_x, replace(settings, gt=False, seed=settings.seed + 1000), lamp_scale=lamp_scale)
    secs = (time.time() - t0) / len(cameras)
    b = render_views(cfg, cameras, env, size, settings.spp, fov_x, replace(settings, gt=False, seed=settings.seed + 2000), lamp_scale=lamp_scale)
    return psnr8(a["radiance"], b["radiance"]), secs


def settings_of(opts: RenderOptions, cfg: GalleryConfig, variant: str) -> RenderSettings:
    """The path-tracing settings of a profile for a gallery (the sample keeps its integrator and seed rule)."""
    sample = cfg.preset == "sample"
    return RenderSettings(spp=opts.spp_per_pass, seed=opts.seed, max_depth=opts.max_depth, sampler=opts.sampler, variant=variant,
                          gt_subsamples=opts.gt_subsamples, progress=opts.progress, integrator="path" if sample else "volpath",
                          min_passes=opts.min_passes, max_passes=opts.max_passes, target_noise_db=opts.target_noise_db,
                          seed_rule="sample" if sample else "hash")


def calibrate_exposure(mi, dr, cfg: GalleryConfig, env: Environment, cameras: np.ndarray, fov: float, settings: RenderSettings,
                       workdir: Path, textures: dict) -> dict[str, float]:
    """Emitter scales so the lamps give ``lamp_share`` of the mean radiance and the mean sRGB is the target.

    Returns:
        dict with ``env_scale`` (multiplies the probe map), ``lamp_scale`` (multiplies every lamp), the preview means,
        and the share and target actually used (lowered when more than :data:`MAX_CLIPPED` of the preview clips).
    """
    lt = cfg.lighting
    prev = replace(settings, spp=16, gt=False, progress=False, min_passes=1, max_passes=1, target_noise_db=None, seed=settings.seed + 7)
    cams = cameras[: min(8, len(cameras))]
    env_reaches = daylight_reaches(cfg)
    r_env = r_lamp = None
    if env_reaches:
        built = build_scene(mi, cfg, env, workdir, lamp_scale=0.0, textures=textures)
        r_env = _render_built(mi, dr, built, cams, 48, fov, prev, "preview")["radiance"]
    if lt.lamps:
        built = build_scene(mi, cfg, None, workdir, lamp_scale=1.0, textures=textures)
        r_lamp = _render_built(mi, dr, built, cams, 48, fov, prev, "preview")["radiance"]
    m_env = float(r_env.mean()) if r_env is not None else 0.0
    m_lamp = float(r_lamp.mean()) if r_lamp is not None else 0.0
    if m_env <= 1e-9 and m_lamp <= 1e-9:
        raise DarsError(f"gallery seed {cfg.seed}: the preview is black (no light reaches the cameras)")
    share = lt.lamp_share if (m_env > 1e-9 and m_lamp > 1e-9) else (1.0 if m_lamp > 1e-9 else 0.0)
    target = lt.target_mean_srgb
    for _ in range(12):  # keep lamp hot spots from blowing out: at most MAX_CLIPPED of the preview pixels clip
        a = (1.0 - share) / m_env if m_env > 1e-9 else 0.0
        b = share / m_lamp if m_lamp > 1e-9 else 0.0
        mix = (a * r_env if a else 0.0) + (b * r_lamp if b else 0.0)
        k = _auto_exposure(np.asarray(mix), target)
        clipped = float((np.asarray(mix) * k > 1.0).any(-1).mean())
        if clipped <= MAX_CLIPPED:
            break
        if 0.0 < share < 1.0 and share > 0.15:
            share *= 0.75
        else:
            target *= 0.9
    return {"env_scale": k * a, "lamp_scale": k * b, "preview_mean_env": m_env, "preview_mean_lamps": m_lamp, "lamp_share": share,
            "target_mean_srgb": target, "preview_clipped": clipped}


MAX_CLIPPED = 0.02
"""Largest fraction of preview pixels allowed to clip (any channel > 1): above it the lamps' share (then the target
exposure) is lowered, so spot-lit paintings keep their texture."""


def room_aabb(cfg: GalleryConfig) -> list[list[float]]:
    """A tight box of the room (walls, floor, ceiling) padded by 5 cm so the surfaces lie inside it; the sample's
    hand-set box for the sample."""
    room = cfg.room
    if cfg.preset == "sample":  # padded so the wall (y = y1) and the floor (z = 0) lie inside the box, not on its faces
        return [[room.x[0] - 0.1, room.y[0] - 0.1, -0.1], [room.x[1] + 0.1, room.y[1] + 0.25, room.height + 0.2]]
    top = room.height + (room.well_depth if room.ceiling else 0.0)
    return [[room.x[0] - 0.05, room.y[0] - 0.05, -0.05], [room.x[1] + 0.05, room.y[1] + 0.05, top + 0.05]]


def render_gallery(cfg: GalleryConfig, out_dir: str | Path, opts: RenderOptions = RenderOptions()) -> dict[str, Any]:
    """Render a gallery (views, ground truth, light probe) into ``out_dir`` (``transforms_{train,test}.json`` and
    images, loadable by :func:`toolkit.scene.load_scene`).

    Returns:
        summary dict: seconds per stage and in total, spp and noise statistics, exposure, SH.

    Raises:
        ConfigError: missing probe or Mitsuba; DarsError: a gallery whose cameras see no light.
    """
    import tempfile

    import torch

    from toolkit.io import linear_to_srgb, write_hdr
    from toolkit.sh import fit_sh_probe

    t_start = time.time()
    out_dir = Path(out_dir)
    mi, dr, variant = import_mitsuba(opts.variant)
    settings = settings_of(opts, cfg, variant)
    fov = math.radians(cfg.camera.fov_x_deg)
    cams, kinds = {}, {}
    for split, n in (("train", opts.n_train), ("test", opts.n_test)):
        cams[split], kinds[split] = gallery_cameras(cfg, n, split)
        check_cameras(cfg, cams[split])
    env0 = environment_of(cfg)
    seconds: dict[str, float] = {}
    textures: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        t0 = time.time()
        if cfg.preset == "sample":
            built0 = build_scene(mi, cfg, env0, work, textures=textures)
            prev = _render_built(mi, dr, built0, cams["train"][:8], 48, fov, replace(settings, spp=16, gt=False, progress=False, seed=opts.seed + 7))
            k = _auto_exposure(prev["radiance"], cfg.lighting.target_mean_srgb)
            expo = {"env_scale": k, "lamp_scale": 0.0}
        else:
            expo = calibrate_exposure(mi, dr, cfg, env0, cams["train"], fov, settings, work, textures)
        seconds["exposure"] = time.time() - t0
        env_reaches = daylight_reaches(cfg)
        env = Environment(latlong=env0.latlong * np.float32(expo["env_scale"]), rotate_z_deg=env0.rotate_z_deg, source=env0.source)
        built = build_scene(mi, cfg, env if env_reaches else None, work, lamp_scale=expo["lamp_scale"], textures=textures)
        res = {}
        for split in ("train", "test"):
            if len(cams[split]):
                res[split] = _render_built(mi, dr, built, cams[split], opts.size, fov, replace(settings, progress=opts.progress), split, f"seed {cfg.seed} {split}")
        seconds["radiance"] = sum(r["seconds_radiance"] for r in res.values())
        seconds["gt"] = sum(r["seconds_gt"] for r in res.values())
        point = probe_point(cfg)
        probe = render_light_probe(mi, dr, built, point, opts.probe_face, opts.probe_spp, settings)
        seconds["probe"] = probe["seconds"]
        # the probe as used (exposure applied), queried from a scene holding it (also for closed rooms)
        env_built = built if env_emitter_visible(cfg) else build_scene(mi, cfg, env, work, lamp_scale=0.0, textures=textures, env_emitter=True)
        H, W = env.latlong.shape[:2]
        sh_env = fit_sh_probe(torch.as_tensor(environment_as_used(mi, dr, env_built, 2 * H, 2 * W), dtype=torch.float64)).to_list()
        env_used = environment_as_used(mi, dr, env_built, H, W)
    t0 = time.time()
    out_dir.mkdir(parents=True, exist_ok=True)
    write_hdr(out_dir / "env.hdr", env_used)
    write_hdr(out_dir / "light.hdr", probe["latlong"])
    f = focal_from_fov(fov, opts.size)
    sh_point = [[float(v) for v in row] for row in probe["sh"]]
    all_spp = np.concatenate([r["spp"] for r in res.values()])
    all_noise = np.concatenate([r["noise_db"] for r in res.values()])
    mean_srgb = float(np.mean([linear_to_srgb(np.clip(r["radiance"], 0, 1)).mean() for r in res.values()]))
    noise = {"method": "per view: PSNR(mean of even passes, mean of odd passes) on 8-bit sRGB + 3.01 dB = estimated agreement of two full renders",
             "target_db": opts.target_noise_db, "spp_per_pass": opts.spp_per_pass,
             "spp_mean": float(all_spp.mean()), "spp_min": int(all_spp.min()), "spp_max": int(all_spp.max())}
    if np.isfinite(all_noise).any():
        fin = all_noise[np.isfinite(all_noise)]
        noise.update({"psnr_db_mean": round(float(fin.mean()), 2), "psnr_db_min": round(float(fin.min()), 2),
                      "psnr_db_p10": round(float(np.percentile(fin, 10)), 2)})
    lamps_used = []
    for lamp in cfg.lighting.lamps:
        d = asdict(lamp)
        d["power_used"] = lamp.power * expo["lamp_scale"]
        lamps_used.append(d)
    sample = cfg.preset == "sample"
    render_block = {
        "renderer": "mitsuba", "mitsuba_version": mi.__version__, "variant": variant, "profile": opts.profile,
        "generator": GENERATOR_VERSION, "config_digest": cfg.digest(), "gallery_seed": cfg.seed, "preset": cfg.preset,
        "integrator": f"{settings.integrator} (max_depth {opts.max_depth})", "sampler": opts.sampler, "pixel_filter": "box",
        "spp": int(all_spp.max()) if sample else None, "seed": opts.seed, "noise": noise,
        "env": env0.source, "env_rotate_deg": cfg.lighting.rotate_deg, "env_tint": list(cfg.lighting.tint), "env_reaches_room": env_reaches,
        "exposure": expo["env_scale"] if sample else expo, "lamps": lamps_used, "mean_srgb": round(mean_srgb, 4),
        "fov_x_deg": cfg.camera.fov_x_deg, "image_format": cfg.image_format, "gt_rules": GT_RULES.format(n=opts.gt_subsamples),
        "skylight_radiance": daylight_radiance(env).tolist() if cfg.room.openings else None,
        "sh_point": point.tolist(), "sh_probe": {"cube_face_px": opts.probe_face, "spp": opts.probe_spp, "delta_lamps": probe["delta_lamps"]},
        "sh_definition": ("environment SH: fit_sh_probe of the loaded emitter queried on a 2x dense SPEC lat-long grid (the sample is "
                          "an open corner lit only by it); sh_point: cube-map SH of the incident radiance at render.sh_point") if sample else
                         ("SPEC SH of the incident radiance at render.sh_point (room centre, eye height): cube map of the rendered scene "
                          "projected with exact pixel solid angles, plus point/spot lamps analytically; envmap light.hdr is that "
                          "panorama (lamps splatted). sh_env: the HDR probe's own SH at the exposure used (env.hdr); it lights the "
                          "room through the open top (seen directly) or through frosted skylights (diffusers of radiance "
                          "E_up / pi, E_up its irradiance on an upward-facing surface: render.skylight_radiance)"),
        "seconds": {k: round(v, 1) for k, v in seconds.items()},
    }
    if sample:
        render_block.update({"spp": opts.spp_per_pass, "env_scale": 1.0, "exposure": expo["env_scale"]})
    header: dict[str, Any] = {
        "camera_angle_x": fov, "fl_x": f, "fl_y": f, "cx": opts.size / 2.0, "cy": opts.size / 2.0, "w": opts.size, "h": opts.size,
        "sh": sh_env if sample else sh_point, "envmap": "env.hdr" if sample else "light.hdr", "depth_unit_scale_factor": 0.001,
    }
    if sample:
        header["sh_point"] = sh_point
    else:
        header.update({"sh_env": sh_env, "probe_envmap": "env.hdr"})
    if opts.box:
        header["aabb"] = room_aabb(cfg)
    header["render"] = render_block
    header["scene"] = {"classes": CLASSES, "background_label": BACKGROUND, **built.meta, "config": cfg.to_dict()}
    for split in ("train", "test"):
        if split in res:
            write_split(out_dir, split, res[split], cams[split], header, cfg.image_format, opts.write_hdr, kinds[split])
    seconds["write"] = time.time() - t0
    seconds["total"] = time.time() - t_start
    summary = {"seed": cfg.seed, "profile": opts.profile, "seconds": {k: round(v, 1) for k, v in seconds.items()}, "noise": noise,
               "exposure": expo, "mean_srgb": mean_srgb, "views": {s: len(c) for s, c in cams.items()}}
    from toolkit.io import write_json

    write_json(out_dir / "render_summary.json", summary)
    return summary


# --------------------------------------------------------------------------------------------------------------- CLI
def main(argv: Sequence[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", choices=["sample", "procedural"], default=None,
                    help="sample: the bundled sample (default without --seed); procedural: a gallery drawn from --seed (default with it)")
    ap.add_argument("--seed", type=int, default=None, help="gallery seed (procedural), or the sample's texture/camera seed")
    ap.add_argument("--out", help="output directory")
    ap.add_argument("--profile", choices=sorted(PROFILES), default=None,
                    help="render profile (default: sample for --preset sample, validation for --seed)")
    ap.add_argument("--size", type=int, default=None)
    ap.add_argument("--n-train", type=int, default=None)
    ap.add_argument("--n-test", type=int, default=None)
    ap.add_argument("--spp", type=int, default=None, help="samples per pixel of one pass")
    ap.add_argument("--passes", type=int, nargs=2, default=None, metavar=("MIN", "MAX"), help="passes per view")
    ap.add_argument("--target-noise", type=float, default=None, metavar="DB", help="add passes until two renders would agree at DB")
    ap.add_argument("--sampler", default=None, help="mitsuba sampler plugin (default: multijitter)")
    ap.add_argument("--render-seed", type=int, default=None, help="seed of the sampling noise")
    ap.add_argument("--box", action="store_true", help="write a tight aabb of the room into the JSON")
    ap.add_argument("--variant", default=None, help="mitsuba variant (default: llvm_ad_rgb if libLLVM 19 exists, else scalar_rgb)")
    ap.add_argument("--force", action="store_true", help="overwrite an existing rendering in --out")
    ap.add_argument("--print-config", action="store_true", help="print the gallery's config as JSON and exit")
    ap.add_argument("--noise-check", type=int, default=0, metavar="N",
                    help="render N test views twice (full passes, different seeds), print the PSNR of the 8-bit sRGB images, and exit")
    args = ap.parse_args(argv)

    preset = args.preset or ("procedural" if args.seed is not None else "sample")
    if preset == "procedural" and args.seed is None:
        ap.error("--preset procedural needs --seed")
    prof = PROFILES[args.profile] if args.profile else None
    cfg = (random_gallery(args.seed, wall_patterns=prof.wall_patterns if prof else 0.0) if preset == "procedural"
           else GalleryConfig.sample(args.seed or 0))
    if args.print_config:
        print(json.dumps(cfg.to_dict(), indent=1))
        return 0
    if not args.out:
        ap.error("--out is required")
    opts = PROFILES[args.profile or ("sample" if cfg.preset == "sample" else "validation")]
    over = {"size": args.size, "n_train": args.n_train, "n_test": args.n_test, "spp_per_pass": args.spp, "sampler": args.sampler,
            "seed": args.render_seed, "variant": args.variant}
    opts = replace(opts, **{k: v for k, v in over.items() if v is not None})
    if args.passes:
        opts = replace(opts, min_passes=args.passes[0], max_passes=args.passes[1])
    if args.target_noise is not None:
        opts = replace(opts, target_noise_db=args.target_noise)
    if args.box:
        opts = replace(opts, box=True)
    out_dir = Path(args.out)
    if (out_dir / "transforms_train.json").exists() and not args.force and not args.noise_check:
        print(f"error: {out_dir} already holds a rendering; pass --force to overwrite it", file=sys.stderr)
        return 2
    try:
        if args.noise_check:
            return _noise_check(cfg, opts, args.noise_check)
        summary = render_gallery(cfg, out_dir, opts)
    except DarsError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps(summary), file=sys.stdout)
    print(f"wrote {opts.n_train} + {opts.n_test} views of {'the sample' if cfg.preset == 'sample' else f'gallery seed {cfg.seed}'} to "
          f"{out_dir} in {summary['seconds']['total']:.1f} s ({opts.profile})", file=sys.stderr)
    return 0


def _noise_check(cfg: GalleryConfig, opts: RenderOptions, n: int) -> int:
    """Two full renders (each at the spp the profile gives a view: ``max_passes`` passes) with different seeds."""
    import tempfile

    mi, dr, variant = import_mitsuba(opts.variant)
    settings = settings_of(opts, cfg, variant)
    fov = math.radians(cfg.camera.fov_x_deg)
    cams, _ = gallery_cameras(cfg, n, "test")
    env0 = environment_of(cfg)
    with tempfile.TemporaryDirectory() as tmp:
        if cfg.preset == "sample":
            prev = render_views(cfg, sample_front_cameras(8, cfg.seed * 2 + 1), env0, 48, 16, fov,
                                replace(settings, gt=False, progress=False, seed=opts.seed + 7))
            expo = {"env_scale": _auto_exposure(prev["radiance"], cfg.lighting.target_mean_srgb), "lamp_scale": 0.0}
        else:
            expo = calibrate_exposure(mi, dr, cfg, env0, gallery_cameras(cfg, 8, "train")[0], fov, settings, Path(tmp), {})
    env_reaches = daylight_reaches(cfg)
    env = Environment(latlong=env0.latlong * np.float32(expo["env_scale"]), rotate_z_deg=env0.rotate_z_deg, source=env0.source) if env_reaches else None
    full = replace(settings, spp=opts.spp_per_pass * opts.max_passes, min_passes=1, max_passes=1, target_noise_db=None, gt=False)
    psnr, secs = noise_psnr(cfg, cams, env, opts.size, fov, full, expo["lamp_scale"])
    print(json.dumps({"noise_psnr_db": psnr, "views": n, "spp": full.spp, "sampler": opts.sampler, "seconds_per_view": secs,
                      "gallery_seed": cfg.seed, "preset": cfg.preset}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
