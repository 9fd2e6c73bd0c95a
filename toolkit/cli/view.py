"""``dars view`` and ``dars export-web``: the moderngl preview (window or headless PNG) and the static WebXR page.

The commands only parse, call :mod:`viewers` (imported inside the handlers, so ``dars --help`` stays fast and a
missing optional dependency only affects these commands) and write outputs. A RUN given to ``export-web`` goes
through :func:`toolkit.asset.build_asset` first.

* ``dars view ASSET [--headless --out PNG] [--camera SCENE:SPLIT:INDEX] [--mode lit] [--sh JSON | --probe HDR]
  [--exposure EV] [--width W --height H] [--json]`` — ASSET is a ``.glb`` or an ``export-asset`` directory. Without
  ``--headless`` (and ``--out``) it opens the interactive window (glfw; keys: :data:`viewers.window.HELP`).
* ``dars export-web RUN_OR_GLB OUTDIR [--camera ...] [--sh JSON | --probe HDR] [--exposure EV] [--title T]`` —
  a ``.glb``, an ``export-asset`` directory, or a RUN (then the asset is exported first into OUTDIR with the
  ``export-asset`` defaults, which the mesh/bake options below override).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from .._checks import DarsError
from ._common import FINITE, number
from .asset import add_bake_options, add_mesh_options, asset_config, export_glb

WEB_FILES = ("index.html", "main.js", "scene.glb", "scene_light.json", "dars_shading.js", "vendor/")
"""What ``dars export-web`` writes into OUTDIR (:func:`viewers.web.export_web`)."""


def _add_light_options(q: argparse.ArgumentParser) -> None:
    g = q.add_mutually_exclusive_group()
    g.add_argument("--sh", default=None, metavar="JSON",
                   help="relight with SH coefficients from a JSON file ({'coeffs': 9 x [r, g, b]}, as written by "
                        "`dars priors sh-probe FILE --json`)")
    g.add_argument("--probe", default=None, metavar="HDR", help="relight with an HDR environment map (.hdr/.exr)")
    q.add_argument("--probe-layout", choices=("latlong", "angular"), default="latlong",
                   help="--probe parametrisation: SPEC lat-long (world frame) or an angular light probe (+y up)")
    q.add_argument("--camera", default=None, metavar="SCENE:SPLIT:INDEX",
                   help="view from a scene camera, e.g. samples/gallery:test:0 (default: framing the asset)")
    q.add_argument("--exposure", type=FINITE, default=0.0, help="exposure in stops (colour x 2^EV)")


def add_parser(sub: argparse._SubParsersAction) -> None:
    q = sub.add_parser("view", help="moderngl preview of a baked GLB (window, or --headless --out PNG)")
    q.add_argument("asset", help="a .glb file or an `export-asset` output directory (with scene.glb)")
    q.add_argument("--headless", action="store_true", help="render offscreen (EGL) to --out instead of a window")
    q.add_argument("--out", default=None, help="PNG to write (implies --headless)")
    q.add_argument("--force", action="store_true", help="replace --out if it exists")
    q.add_argument("--mode", default="lit", choices=("lit", "albedo", "roughness", "metallic", "normals", "semantics"))
    _add_light_options(q)
    q.add_argument("--width", type=number(int, min=1, max=16384), default=None,
                   help="image width (default: the camera's, else 1280)")
    q.add_argument("--height", type=number(int, min=1, max=16384), default=None,
                   help="image height (default: keeps the camera's aspect, else 720)")
    q.add_argument("--background", choices=("auto", "backdrop", "sh", "colour"), default="auto",
                   help="lit mode, behind the mesh: auto (default): the GLB's backdrop (the field's learned "
                        "background, where the photos saw it) unless relit, else the SH light; backdrop; sh; "
                        "colour (flat grey)")
    q.add_argument("--texture-filter", choices=("footprint", "trilinear"), default="footprint",
                   help="footprint (default): the mip filter narrowed to each pixel's footprint less the blur the bake "
                        "put in the textures (the GLB's _TEXTURE_BLUR), as the WebXR page draws; trilinear: plain "
                        "trilinear mip-maps, what other glTF viewers draw")
    q.add_argument("--screenshots", default=".", help="window mode: directory for screenshot PNGs (key p / F12)")
    q.add_argument("--json", action="store_true", help="machine-readable result on stdout (headless)")
    q.set_defaults(func=cmd_view)

    q = sub.add_parser("export-web", help="static WebXR page (three.js + scene.glb + LightProbe) for headsets")
    q.add_argument("source", metavar="RUN_OR_GLB", help="a .glb, an `export-asset` directory, or a RUN directory")
    q.add_argument("out", metavar="OUTDIR", help="output directory (index.html, main.js, scene.glb, vendor/)")
    _add_light_options(q)
    q.add_argument("--title", default="dars — WebXR preview", help="page title")
    q.add_argument("--no-specular", action="store_true", help="diffuse SH lighting only")
    q.add_argument("--force", action="store_true", help="write into a non-empty OUTDIR beside its files")
    add_mesh_options(q)
    add_bake_options(q)
    q.add_argument("--json", action="store_true", help="machine-readable result on stdout")
    q.set_defaults(func=cmd_export_web)


def _camera(args, width: int | None):
    from viewers.camera import camera_from_spec

    return camera_from_spec(args.camera, width) if args.camera else None


def _lights(asset, args) -> tuple[list[tuple[str, object]], str]:
    """(lights for the window, the source of the first), the relight first when given."""
    from viewers.lighting import asset_sh, resolve_sh

    sh, source = resolve_sh(asset, args.sh, args.probe, args.probe_layout)
    lights = [(source, sh)]
    own = asset_sh(asset)
    if (args.sh or args.probe) and own is not None:
        lights.append(("asset", own))
    return lights, source


def cmd_view(args: argparse.Namespace) -> int:
    from export.gltf import load_glb
    from viewers.camera import default_camera
    from viewers.preview import PreviewConfig, resolve_asset_path

    from ..io import write_png
    from ..outputs import check_output_file

    headless = args.headless or args.out is not None
    if headless and not args.out:
        raise DarsError("--headless needs --out PNG (the image to write)")
    if args.out:
        check_output_file(args.out, args.force, suffixes=(".png",))
    path = resolve_asset_path(args.asset)
    asset = load_glb(path)
    lights, source = _lights(asset, args)
    cfg = PreviewConfig(mode=args.mode, exposure=args.exposure, background=args.background,
                        texture_filter=args.texture_filter)
    camera = _camera(args, args.width)
    if headless:
        from viewers.preview import render_preview

        if camera is None:
            camera = default_camera(asset.vertices, args.width or 1280, args.height or 720)
        elif args.height is not None:
            camera = camera.resized(args.width or camera.width, args.height)
        t0 = time.perf_counter()
        img = render_preview(asset, camera, cfg, lights[0][1])
        seconds = time.perf_counter() - t0
        out = Path(args.out)
        write_png(out, img.to_float())
        result = {"out": str(out), "asset": str(path), "mode": args.mode, "width": camera.width,
                  "height": camera.height, "exposure": args.exposure, "light": source,
                  "coverage": round(float(img.mask.mean()), 4), "seconds": round(seconds, 3)}
        if args.json:
            sys.stdout.write(json.dumps(result, indent=2) + "\n")
        else:
            print(f"wrote {out} ({camera.width}x{camera.height}, {args.mode}, light: {source}, "
                  f"mesh covers {result['coverage']:.1%})")
        return 0
    from viewers.window import run_window

    shots = run_window(asset, lights, camera, cfg, width=args.width or 1280, height=args.height or 720,
                       screenshot_dir=args.screenshots, log=lambda m: print(m, file=sys.stderr))
    if args.json:
        sys.stdout.write(json.dumps({"screenshots": [str(s) for s in shots]}) + "\n")
    return 0


def _glb_for(source: Path, out: Path, args, cfg) -> tuple[Path, dict]:
    """The GLB to publish: given, inside an export-asset directory, or exported from a RUN into OUTDIR."""
    if source.is_file():
        return source, {}
    if (source / "scene.glb").is_file():
        return source / "scene.glb", {}
    if (source / "checkpoint.pt").is_file() and (source / "config.json").is_file():
        from viewers.refit import viewer_correction

        from ..asset import build_asset

        print(f"[dars] {source} is a training run: exporting its asset first (mesh + bake)", file=sys.stderr)
        asset = build_asset(source, cfg, viewer_correction=viewer_correction)
        out.mkdir(parents=True, exist_ok=True)
        return export_glb(asset, out / "scene.glb", sh=asset.sh), asset.stats
    raise DarsError(f"{source}: expected a .glb, an `export-asset` directory (with scene.glb) or a RUN directory "
                    "(with config.json and checkpoint.pt)")


def _check_light_files(args) -> None:
    """Read ``--sh`` / ``--probe`` once before any heavy work, so a bad file fails first."""
    if args.sh:
        from ..sh import read_sh_json

        read_sh_json(args.sh)
    if args.probe:
        from ..sh import read_envmap

        read_envmap(args.probe)


def cmd_export_web(args: argparse.Namespace) -> int:
    from export.gltf import load_glb
    from viewers.lighting import resolve_sh
    from viewers.web import WebConfig, export_web

    from ..outputs import OutputDir

    source = Path(args.source)
    if not source.exists():
        raise DarsError(f"{source} not found (give a .glb, an export-asset directory or a RUN directory)")
    cfg_asset = asset_config(args)
    folder = OutputDir(args.out, "export-web", force=args.force, option="OUTDIR").check(WEB_FILES)
    _check_light_files(args)
    camera = _camera(args, None)
    if source.is_file() or (source / "scene.glb").is_file():
        load_glb(source if source.is_file() else source / "scene.glb")  # a damaged GLB fails before OUTDIR is made
    elif (source / "checkpoint.pt").is_file() and (source / "config.json").is_file():
        from ..train.folder import find_run

        find_run(source)
    else:
        raise DarsError(f"{source}: expected a .glb, an `export-asset` directory (with scene.glb) or a RUN directory "
                        "(with config.json and checkpoint.pt)")
    cfg = WebConfig(title=args.title, exposure=args.exposure, specular=not args.no_specular)
    with folder:
        out = folder.path
        glb, asset_stats = _glb_for(source, out, args, cfg_asset)
        asset = load_glb(glb)
        sh, light = resolve_sh(asset, args.sh, args.probe, args.probe_layout)
        res = export_web(glb, out, sh=sh, camera=camera, cfg=cfg, source=light)
    result = {"out": str(res.out_dir), "index": str(res.index), "glb": str(res.glb), "light_json": str(res.light_json),
              "light": light, "three_version": res.three_version, "vendor_files": list(res.vendor_files),
              "serve": f"python -m http.server --directory {res.out_dir} 8000  # then open http://localhost:8000/"}
    if asset_stats:
        result["asset"] = {k: asset_stats[k] for k in ("vertices", "faces") if k in asset_stats}
    if args.json:
        sys.stdout.write(json.dumps(result, indent=2) + "\n")
    else:
        print(f"wrote {res.index} (three.js {res.three_version}, light: {light}); serve it with\n  {result['serve']}")
    return 0
