"""Stage 15b — a static WebXR page for a baked GLB (three.js + LightProbe from our SH; SPEC stage 15).

``export_web(glb, out_dir)`` writes a directory any static web server can serve, with no build step::

    OUTDIR/index.html          importmap: "three" -> vendor/three/build/three.module.js, "three/addons/" -> examples/jsm/
    OUTDIR/main.js             ES module: WebGLRenderer (xr.enabled), OrbitControls, VRButton, GLTFLoader, LightProbe
    OUTDIR/dars_shading.js     the SH lighting GLSL generated from toolkit/shading.py (viewers.shading_glsl)
    OUTDIR/scene.glb           the asset (copied)
    OUTDIR/scene_light.json    the light and the initial view, beside the GLB (below)
    OUTDIR/vendor/three/...    the three.js files the page imports (and their own imports), copied from the pinned
                               npm package (tools/package.json; scripts/setup_node.sh installs it), plus LICENSE

``scene_light.json``: ``lightprobe`` — 27 floats for ``new LightProbe(new SphericalHarmonics3().fromArray(...))``
from :func:`toolkit.sh.sh_to_threejs_lightprobe` (our radiance SH rotated into three's +y-up frame, same basis);
``sh_world`` — the SPEC coefficients [9, 3] (+z up, for reference); ``exposure`` (stops); ``background``
(``"sh"``, ``"backdrop"`` or an sRGB triple); ``backdrop`` — the GLB's backdrop when drawn
(:meth:`toolkit.backdrop.Backdrop.to_json`, uploaded as a half-float lat-long texture and blended with the SH
radiance by its visibility, as ``dars view``; its box map, where it has one, is read where the ray from the eye
leaves the room's box); ``sky_scale`` — what the sky's SH radiance is multiplied by (1 / the
GLB's ``extras.dars.light_scale``, :func:`viewers.lighting.light_scale`); ``gltf_to_world`` (row-major 3×3: three's
frame to the dars world, where the backdrop lives); ``camera`` (three/glTF frame: ``position``, ``target``,
``fov_y_deg``, ``near``, ``far``);
``xr_start`` (headset start: the camera's floor position and yaw); ``specular``; ``source``; ``three_version``.

Shading on the page: three's ``MeshStandardMaterial`` from GLTFLoader keeps its texturing (sRGB base colour, ORM,
tangent-space normal map with the GLB's tangents); its image-based-lighting hooks (``RE_IndirectDiffuse``,
``RE_IndirectSpecular``) are redefined with ``onBeforeCompile`` to the training shading, generated from
:mod:`toolkit.shading` (``dars_shading.js``: the same GLSL as ``dars view`` and the DFG table as a float
texture) and reading the ``LightProbe``'s coefficients. three's stock probe shading is one URL switch away
(``?shading=three``: diffuse only, and scaled by ``1 − F_ss − F_ms``, up to ~45 % darker at grazing angles).
Output: linear × 2^exposure → clamp → sRGB (three's ``LinearToneMapping``), as ``dars view``.
"""

from __future__ import annotations

import html
import json
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from export.gltf import WORLD_TO_GLTF, load_glb
from toolkit._checks import ConfigError, DarsError
from toolkit.pinhole import PinholeCamera, look_at

from .camera import default_camera

__all__ = ["WebConfig", "WebExport", "export_web", "find_threejs", "vendor_threejs", "web_camera",
           "view_camera_from_web", "THREE_ENTRY_FILES"]

TEMPLATE_DIR = Path(__file__).with_name("web_template")
REPO_THREE_DIR = Path(__file__).resolve().parents[1] / "tools" / "node_modules" / "three"
"""Where ``scripts/setup_node.sh`` installs the pinned ``three`` package (tools/package-lock.json)."""
THREE_ENTRY_FILES = (
    "build/three.module.js",
    "examples/jsm/loaders/GLTFLoader.js",
    "examples/jsm/controls/OrbitControls.js",
    "examples/jsm/webxr/VRButton.js",
)
"""The three.js files ``main.js`` imports (their own imports are followed and copied too)."""

_IMPORT_RE = re.compile(r"""(?:\bfrom\s*|\bimport\s*\(?\s*)['"]([^'"\n]+)['"]""")


@dataclass(frozen=True)
class WebConfig:
    """Options of :func:`export_web`."""

    title: str = "dars — WebXR preview"
    """The page title."""
    exposure: float = 0.0
    """Exposure in stops (colour × 2^exposure before the sRGB transfer); ``?exposure=EV`` overrides it."""
    background: str | tuple[float, float, float] = "auto"
    """Behind the model: ``"backdrop"``: the GLB's backdrop (the field's colour and learned background where the
    photos saw past the mesh, :mod:`toolkit.backdrop`; an error when the GLB has none); ``"sh"``: the SH environment; ``"auto"``: the backdrop
    when the GLB has one and the page shows the GLB's own light, else ``"sh"`` (as ``dars view``); or an sRGB
    colour."""
    specular: bool = True
    """Add the SH specular lobe to three's materials (False: the LightProbe's diffuse only)."""
    fov_y_deg: float = 50.0
    """Vertical field of view of the default camera (a ``camera`` passed to :func:`export_web` keeps its own)."""


@dataclass(frozen=True)
class WebExport:
    """Result of :func:`export_web`: the files written (absolute paths) and the vendored three.js version."""

    out_dir: Path
    index: Path
    glb: Path
    light_json: Path
    vendor_files: tuple[str, ...]
    three_version: str


def find_threejs(explicit: str | Path | None = None) -> Path:
    """The ``three`` npm package directory: ``explicit``, else ``$DARS_THREE_DIR``, else the repository's
    ``tools/node_modules/three`` (installed by ``scripts/setup_node.sh`` from ``tools/package-lock.json``).

    Raises:
        DarsError: not found, saying how to install it.
    """
    candidates = [Path(explicit)] if explicit else []
    if os.environ.get("DARS_THREE_DIR"):
        candidates.append(Path(os.environ["DARS_THREE_DIR"]))
    candidates.append(REPO_THREE_DIR)
    for c in candidates:
        if (c / "package.json").is_file() and (c / THREE_ENTRY_FILES[0]).is_file():
            return c
    raise DarsError("three.js not found (looked in " + ", ".join(str(c) for c in candidates) + "); install the "
                    "pinned npm packages with `bash scripts/setup_node.sh` (needs node/npm) or set DARS_THREE_DIR "
                    "to an npm `three` package directory")


def _resolve_import(spec: str, importer: Path, root: Path) -> Path | None:
    """The file a module specifier names inside the three package (None for URLs and foreign packages)."""
    if "://" in spec or not spec.endswith(".js") and spec != "three":
        return None
    if spec == "three":
        return root / "build" / "three.module.js"
    if spec.startswith("three/addons/"):
        return root / "examples" / "jsm" / spec[len("three/addons/"):]
    if spec.startswith("./") or spec.startswith("../"):
        return (importer.parent / spec).resolve()
    return None


def vendor_threejs(three_dir: str | Path, out_dir: str | Path,
                   entries: tuple[str, ...] = THREE_ENTRY_FILES) -> list[str]:
    """Copy the three.js entry files and everything they import (transitively) into ``out_dir``, keeping the
    package layout (``build/…``, ``examples/jsm/…``) so relative imports still resolve; plus ``LICENSE``.

    Returns:
        the copied paths relative to ``out_dir`` (sorted).

    Raises:
        DarsError: an entry file or an import is missing from the package.
    """
    root = Path(three_dir).resolve()
    out = Path(out_dir)
    todo = [root / e for e in entries]
    seen: set[Path] = set()
    while todo:
        f = todo.pop()
        if f in seen:
            continue
        if not f.is_file() or root not in f.parents:
            raise DarsError(f"three.js file {f} is missing from {root} (a partial npm install? re-run "
                            "`bash scripts/setup_node.sh`)")
        seen.add(f)
        for spec in _IMPORT_RE.findall(f.read_text(encoding="utf-8")):
            dep = _resolve_import(spec, f, root)
            if dep is not None and dep not in seen:
                todo.append(dep)
    copied = []
    for f in sorted(seen) + [root / "LICENSE"]:
        if not f.is_file():
            continue
        rel = f.relative_to(root)
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(f, out / rel)
        copied.append(rel.as_posix())
    return sorted(copied)


# ========================================================================================================= cameras
def web_camera(camera: PinholeCamera, target: np.ndarray | None = None) -> dict:
    """The page's initial view (three/glTF +y-up frame) from a :class:`PinholeCamera` (world +z up).

    The page uses a centred principal point and square pixels; ``target`` (world) defaults to a point ahead of the
    camera at the asset-independent distance of 1/10 of ``far``.
    """
    pos = camera.position
    fwd = -camera.c2w[:3, 2]
    if target is None:
        target = pos + fwd * max(camera.far * 0.1, 1e-2)
    to = lambda v: [float(x) for x in WORLD_TO_GLTF @ np.asarray(v, dtype=np.float64)]  # noqa: E731
    fov = float(np.degrees(2.0 * np.arctan(0.5 * camera.height / camera.fy)))
    return {"position": to(pos), "target": to(target), "fov_y_deg": fov, "near": float(camera.near),
            "far": float(camera.far)}


def view_camera_from_web(cam: dict, width: int, height: int) -> PinholeCamera:
    """The :class:`PinholeCamera` (world +z up) the page shows for ``scene_light.json``'s ``camera`` at a viewport
    size — what three.js' ``PerspectiveCamera`` + ``lookAt`` give (used to compare the page with ``dars view``)."""
    back = lambda v: WORLD_TO_GLTF.T @ np.asarray(v, dtype=np.float64)  # noqa: E731
    f = 0.5 * height / np.tan(np.radians(cam["fov_y_deg"]) * 0.5)
    return PinholeCamera(look_at(back(cam["position"]), back(cam["target"])), f, f, width / 2, height / 2, width, height,
                      cam["near"], cam["far"])


def _xr_start(camera: dict, floor_y: float) -> dict:
    pos, tgt = np.asarray(camera["position"]), np.asarray(camera["target"])
    d = tgt - pos
    yaw = float(np.degrees(np.arctan2(-d[0], -d[2])))  # rotation about +y taking -z to the view direction
    return {"position": [float(pos[0]), float(floor_y), float(pos[2])], "yaw_deg": yaw}


# ========================================================================================================== export
def export_web(glb: str | Path, out_dir: str | Path, sh: np.ndarray | None = None, camera: PinholeCamera | None = None,
               cfg: WebConfig = WebConfig(), three_dir: str | Path | None = None, source: str | None = None) -> WebExport:
    """Write the static WebXR page for a GLB (module docstring).

    Args:
        glb: the baked asset (``.glb``).
        out_dir: output directory (created; existing page files are overwritten).
        sh: float [9, 3] SPEC radiance SH to light with (default: the asset's, :func:`viewers.lighting.resolve_sh`).
        camera: the initial desktop view (default: framing the asset).
        cfg: page options.
        three_dir: the ``three`` npm package (default: :func:`find_threejs`).
        source: a description of the light written into the JSON (default: where it came from).

    Returns:
        :class:`WebExport`.

    Raises:
        SceneError: the GLB cannot be read.
        DarsError: three.js is not installed.
        ConfigError: bad options.
    """
    from toolkit.sh import sh_to_threejs_lightprobe

    from toolkit.shading import ShadingConfig, dfg_table

    from toolkit.sh import check_sh_coeffs

    from .lighting import draws_backdrop, light_scale, resolve_sh
    from .shading_glsl import glsl_shading_source

    if not np.isfinite(cfg.exposure):
        raise ConfigError(f"exposure={cfg.exposure} must be finite")
    if not (cfg.background in ("auto", "sh", "backdrop")
            or (isinstance(cfg.background, tuple) and len(cfg.background) == 3)):
        raise ConfigError(f"background={cfg.background!r}: use 'auto', 'sh', 'backdrop' or an (r, g, b) triple")
    if not 1.0 < cfg.fov_y_deg < 170.0:
        raise ConfigError(f"fov_y_deg={cfg.fov_y_deg} must be in (1, 170)")
    glb = Path(glb)
    if glb.suffix.lower() != ".glb":
        raise ConfigError(f"export_web: {glb} must be a .glb file (one binary file the page can fetch)")
    asset = load_glb(glb)
    three = find_threejs(three_dir)
    if sh is None:
        sh, default_source = resolve_sh(asset)
    else:
        sh, default_source = check_sh_coeffs(sh, "export_web sh"), "given"
    background = cfg.background
    if isinstance(background, str):
        background = "backdrop" if draws_backdrop(background, asset, sh) else "sh"
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    vendor = vendor_threejs(three, out / "vendor" / "three")
    three_version = json.loads((three / "package.json").read_text())["version"]

    lo, hi = asset.vertices.min(0), asset.vertices.max(0)
    centre = (lo + hi) / 2.0
    if camera is None:
        camera = default_camera(asset.vertices, 1280, 720, cfg.fov_y_deg)
        target = centre
    else:
        depth = float(np.dot(centre - camera.position, -camera.c2w[:3, 2]))
        target = camera.position - camera.c2w[:3, 2] * max(depth, 1e-2)
    cam = web_camera(camera, target)
    floor_y = float((WORLD_TO_GLTF @ lo)[1])  # world z min = glTF y min
    light = {
        "format": "dars-web 1",
        "glb": "scene.glb",
        "lightprobe": sh_to_threejs_lightprobe(sh),
        "sh_world": [[float(v) for v in row] for row in np.asarray(sh)],
        "exposure": float(cfg.exposure),
        "background": background if isinstance(background, str) else [float(c) for c in background],
        "sky_scale": 1.0 / light_scale(asset),
        "backdrop": asset.backdrop.to_json() if background == "backdrop" else None,
        "gltf_to_world": [[float(v) for v in row] for row in WORLD_TO_GLTF.T],
        "specular": bool(cfg.specular),
        "camera": cam,
        "xr_start": _xr_start(cam, floor_y),
        "source": source or default_source,
        "three_version": three_version,
        "frames": "lightprobe, camera, xr_start: three.js / glTF (+y up); sh_world: dars world (+z up, SPEC)",
    }
    target_glb = out / "scene.glb"
    if glb.resolve() != target_glb.resolve():
        shutil.copyfile(glb, target_glb)
    (out / "scene_light.json").write_text(json.dumps(light, indent=2) + "\n")
    page = (TEMPLATE_DIR / "index.html").read_text(encoding="utf-8")
    page = page.replace("{{TITLE}}", html.escape(cfg.title)).replace("{{GLB}}", "scene.glb")
    (out / "index.html").write_text(page, encoding="utf-8")
    shutil.copyfile(TEMPLATE_DIR / "main.js", out / "main.js")
    glsl = glsl_shading_source(ShadingConfig(specular=cfg.specular))
    if "`" in glsl or "${" in glsl:
        raise DarsError("generated GLSL contains characters that cannot go into a JS template string")
    table = dfg_table().numpy().astype(np.float32)
    values = ",".join(f"{v:.9g}" for v in table.reshape(-1))
    (out / "dars_shading.js").write_text(
        "// Generated by viewers/web.py from toolkit/shading.py (viewers/shading_glsl.py): do not edit.\n"
        f"export const DARS_SHADING_GLSL = `{glsl}`;\n"
        f"export const DARS_DFG_SIZE = {table.shape[0]};\n"
        "// toolkit.shading.dfg_table(): [roughness row i/31][n.v column (j+0.5)/32][A, B], float32\n"
        f"export const DARS_DFG_TABLE = new Float32Array([{values}]);\n", encoding="utf-8")
    return WebExport(out.resolve(), (out / "index.html").resolve(), target_glb.resolve(),
                     (out / "scene_light.json").resolve(), tuple(vendor), three_version)
