"""viewers.web: the static WebXR page — files, importmap, vendored three.js closure, the light JSON, `dars export-web`,
and the page in headless Chromium (driven by tools/web_check.mjs with playwright-core and Debian's chromium).

The Chromium check asserts: the page becomes ready, logs no console error and no page error, has the VR button and
``renderer.xr.enabled``, its canvas is not blank, and its pixels match ``dars view`` of the same view: PSNR ≥ 30 dB
(measured 49.5 dB on the textured cube — both run the GLSL generated from toolkit/shading.py; the residue is texture
filtering and 8-bit rounding). three's stock LightProbe shading (``?shading=three``) is only checked to load and draw.
"""

import functools
import http.server
import json
import os
import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from _viewer_assets import CUBE_SH, textured_cube, trained_sample
from toolkit._checks import ConfigError, DarsError
from toolkit.io import read_image
from toolkit.shading import dfg_table
from toolkit.sh import sh_to_threejs_lightprobe

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = os.environ.get("DARS_CHROMIUM", "/usr/bin/chromium")


@pytest.fixture(scope="module")
def cube_glb(tmp_path_factory):
    return textured_cube(tmp_path_factory.mktemp("cube") / "cube.glb")


@pytest.fixture(scope="module")
def page(cube_glb, tmp_path_factory):
    from viewers.web import export_web

    try:
        return export_web(cube_glb, tmp_path_factory.mktemp("web") / "site")
    except DarsError as e:
        if "three.js not found" in str(e):
            pytest.skip(f"three.js is not installed (node/npm missing?): {e}")
        raise


def test_export_web_writes_a_static_page(page):
    out = page.out_dir
    for name in ("index.html", "main.js", "dars_shading.js", "scene.glb", "scene_light.json", "vendor/three/LICENSE"):
        assert (out / name).is_file(), name
    html = (out / "index.html").read_text()
    importmap = json.loads(re.search(r'<script type="importmap">(.*?)</script>', html, re.S).group(1))["imports"]
    assert (out / importmap["three"]).is_file()
    assert (out / importmap["three/addons/"] / "loaders" / "GLTFLoader.js").is_file()
    assert '<script type="module" src="./main.js">' in html
    main = (out / "main.js").read_text()
    for spec in ("three", "three/addons/loaders/GLTFLoader.js", "three/addons/controls/OrbitControls.js",
                 "three/addons/webxr/VRButton.js", "./dars_shading.js"):
        assert f"from '{spec}'" in main, spec
    assert "renderer.xr.enabled = true" in main and "new THREE.LightProbe" in main
    assert set(page.vendor_files) >= {"build/three.module.js", "build/three.core.js", "examples/jsm/utils/BufferGeometryUtils.js",
                                      "examples/jsm/webxr/VRButton.js"}
    assert "build/three.webgpu.js" not in page.vendor_files  # only what the page needs
    # every import inside the vendored files resolves inside vendor/ (the page works offline)
    vendor = out / "vendor" / "three"
    for rel in page.vendor_files:
        if rel.endswith(".js"):
            for spec in re.findall(r"""\bfrom\s*['"](\.{1,2}/[^'"]+)['"]""", (vendor / rel).read_text()):
                assert ((vendor / rel).parent / spec).resolve().is_file(), f"{rel} imports missing {spec}"
    pinned = json.loads((ROOT / "tools" / "package.json").read_text())["dependencies"]["three"]
    assert page.three_version == pinned


def test_light_json_and_generated_shading(page):
    from viewers.camera import default_camera
    from viewers.shading_glsl import glsl_shading_source
    from viewers.web import view_camera_from_web, web_camera

    light = json.loads(page.light_json.read_text())
    np.testing.assert_allclose(light["lightprobe"], sh_to_threejs_lightprobe(CUBE_SH), atol=1e-12)
    np.testing.assert_allclose(light["sh_world"], CUBE_SH, atol=1e-12)
    assert light["glb"] == "scene.glb" and light["background"] == "sh" and light["source"] == "asset"
    js = (page.out_dir / "dars_shading.js").read_text()
    assert glsl_shading_source() in js
    table = np.array([float(v) for v in js.split("new Float32Array([", 1)[1].split("])", 1)[0].split(",")], np.float32)
    np.testing.assert_array_equal(table.reshape(32, 32, 2), dfg_table().numpy())
    # the page's camera is the exported view: three/glTF frame there and back
    pts = np.random.default_rng(0).normal(size=(50, 3))
    cam = default_camera(pts, 320, 240)
    back = view_camera_from_web(web_camera(cam, (pts.min(0) + pts.max(0)) / 2), 320, 240)
    np.testing.assert_allclose(back.c2w, cam.c2w, atol=1e-9)
    assert (back.fx, back.fy, back.cx, back.cy) == pytest.approx((cam.fx, cam.fy, cam.cx, cam.cy))


def test_export_web_errors(cube_glb, tmp_path, monkeypatch):
    from viewers.web import WebConfig, export_web, find_threejs

    with pytest.raises(ConfigError, match=".glb"):
        export_web(tmp_path / "scene.gltf", tmp_path / "out")
    with pytest.raises(ConfigError, match="exposure"):
        export_web(cube_glb, tmp_path / "out", cfg=WebConfig(exposure=float("nan")))
    monkeypatch.setenv("DARS_THREE_DIR", str(tmp_path / "nothing"))
    monkeypatch.setattr("viewers.web.REPO_THREE_DIR", tmp_path / "not-installed")
    with pytest.raises(DarsError, match="setup_node.sh"):
        find_threejs(tmp_path / "also-nothing")


def test_vendor_threejs_follows_imports(tmp_path):
    from viewers.web import vendor_threejs

    pkg = tmp_path / "three"
    (pkg / "build").mkdir(parents=True)
    (pkg / "examples" / "jsm" / "a").mkdir(parents=True)
    (pkg / "build" / "three.module.js").write_text("import { X } from './three.core.js';\nexport { X };\n")
    (pkg / "build" / "three.core.js").write_text("export const X = 1; // from 'https://example.com/not-a-file.js'\n")
    (pkg / "build" / "unused.js").write_text("export const Y = 2;\n")
    (pkg / "examples" / "jsm" / "a" / "A.js").write_text("import { X } from 'three';\nimport '../b/B.js';\n")
    (pkg / "LICENSE").write_text("MIT\n")
    with pytest.raises(DarsError, match="B.js"):
        vendor_threejs(pkg, tmp_path / "out", entries=("build/three.module.js", "examples/jsm/a/A.js"))
    (pkg / "examples" / "jsm" / "b").mkdir()
    (pkg / "examples" / "jsm" / "b" / "B.js").write_text("export {};\n")
    copied = vendor_threejs(pkg, tmp_path / "out", entries=("build/three.module.js", "examples/jsm/a/A.js"))
    assert copied == ["LICENSE", "build/three.core.js", "build/three.module.js", "examples/jsm/a/A.js",
                      "examples/jsm/b/B.js"]


# ========================================================================================================= Chromium
class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):  # keep pytest output clean
        pass


@pytest.fixture
def serve():
    servers = []

    def start(directory: Path) -> str:
        handler = functools.partial(_QuietHandler, directory=str(directory))
        httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        threading.Thread(target=httpd.serve_forever, daemon=True).start()
        servers.append(httpd)
        return f"http://127.0.0.1:{httpd.server_address[1]}"

    yield start
    for s in servers:
        s.shutdown()
        s.server_close()


def _web_check(url: str, shot: Path, width: int, height: int) -> dict:
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed: the page cannot be driven (apt nodejs; scripts/setup.sh installs it)")
    if not Path(CHROMIUM).is_file():
        pytest.skip(f"chromium is not installed at {CHROMIUM} (Debian `chromium`, in scripts/setup.sh's apt list)")
    if not (ROOT / "tools" / "node_modules" / "playwright-core").is_dir():
        pytest.skip("playwright-core is not installed in tools/node_modules (run scripts/setup_node.sh)")
    r = subprocess.run([node, str(ROOT / "tools" / "web_check.mjs"), url, "--out", str(shot), "--width", str(width),
                        "--height", str(height), "--chromium", CHROMIUM, "--timeout", "90000"],
                       capture_output=True, text=True, timeout=300)
    if r.returncode == 2 or not r.stdout.strip():
        pytest.fail(f"web_check could not run chromium: {r.stderr}")
    return json.loads(r.stdout)


def test_page_renders_in_headless_chromium_like_dars_view(page, serve, tmp_path):
    from viewers.preview import render_preview
    from viewers.web import view_camera_from_web

    w, h = 320, 240
    report = _web_check(serve(page.out_dir) + "/index.html?dpr=1&noaa", tmp_path / "page.png", w, h)
    assert report["ready"], report
    assert report["console_errors"] == [] and report["page_errors"] == [], report
    assert report["failed_requests"] == [], report
    assert report["xr_enabled"] and report["vr_button"] in ("VR NOT SUPPORTED", "ENTER VR", "VR NOT ALLOWED",
                                                              "WEBXR NOT AVAILABLE"), report
    assert report["meshes"] == 6 and report["webgl"].startswith("WebGL 2.0")
    shot = read_image(tmp_path / "page.png")[..., :3]
    assert shot.shape == (h, w, 3)
    assert shot.std() > 0.02, "the canvas is blank"
    light = json.loads(page.light_json.read_text())
    ref = render_preview(page.glb, view_camera_from_web(light["camera"], w, h))
    assert ref.mask.mean() > 0.1
    mse = float(((shot - ref.to_float()) ** 2).mean())
    psnr_db = -10 * np.log10(max(mse, 1e-12))
    assert psnr_db >= 30.0, f"page vs dars view: PSNR {psnr_db:.1f} dB (bound 30 dB)"


def _site(glb, out):
    """export_web of ``glb`` into ``out``; skips when three.js is not installed."""
    from viewers.web import export_web

    try:
        return export_web(glb, out)
    except DarsError as e:
        if "three.js not found" in str(e):
            pytest.skip(f"three.js is not installed (node/npm missing?): {e}")
        raise


@pytest.mark.parametrize("with_box", [False, True])
def test_page_draws_the_backdrop_like_dars_view(serve, tmp_path, with_box):
    """A GLB with a backdrop (toolkit.backdrop): the page draws it behind the model, blended with the SH radiance by
    its visibility, as ``dars view`` does (a half-float texture there, float32 here). Its occlusion channel (0.6)
    darkens the model's SH lighting and its light_scale (1.5) the sky's SH on the page as in ``dars view``. With a
    box map (``with_box``), the page keys it by where each ray from its eye leaves the box, as ``dars view``."""
    from toolkit.backdrop import Backdrop, BoxProjection
    from viewers.preview import PreviewConfig, render_preview
    from viewers.web import WebConfig, export_web, view_camera_from_web

    rng = np.random.default_rng(8)
    box = {}
    if with_box:
        proj = BoxProjection(np.zeros(3), np.eye(3), np.array([-2.5, -2.0, -1.0]), np.array([2.0, 2.5, 3.0]),
                             np.array([True, True, False, True, True, False]), np.array([0.1, 0.0, 0.5]))
        box = dict(box=proj, box_radiance=rng.uniform(0, 1.2, (16, 32, 3)), box_weight=rng.uniform(0, 1, (16, 32)))
    bd = Backdrop(rng.uniform(0, 1.2, (8, 16, 3)), rng.uniform(0, 1, (8, 16)), **box)
    glb = textured_cube(tmp_path / "cube.glb", extras={"backdrop": bd.to_json(), "light_scale": 1.5}, occlusion=0.6)
    site = _site(glb, tmp_path / "site")
    light = json.loads(site.light_json.read_text())
    assert light["background"] == "backdrop" and light["backdrop"]["height"] == 8
    assert light["sky_scale"] == pytest.approx(1 / 1.5)
    w, h = 320, 240
    report = _web_check(serve(site.out_dir) + "/index.html?dpr=1&noaa", tmp_path / "page.png", w, h)
    assert report["ready"] and not report["console_errors"] and not report["page_errors"], report
    shot = read_image(tmp_path / "page.png")[..., :3]
    cam = view_camera_from_web(light["camera"], w, h)
    ref, sh_only = render_preview(glb, cam), render_preview(glb, cam, PreviewConfig(background="sh"))
    sky = ~ref.mask
    assert sky.mean() > 0.3 and np.abs(ref.to_float() - sh_only.to_float())[sky].mean() > 0.05  # a visible change
    psnr_db = -10 * np.log10(max(float(((shot - ref.to_float()) ** 2).mean()), 1e-12))
    assert psnr_db >= 30.0, f"page vs dars view with the backdrop: PSNR {psnr_db:.1f} dB (bound 30 dB)"
    with pytest.raises(ConfigError, match="carries no backdrop"):
        export_web(textured_cube(tmp_path / "plain.glb"), tmp_path / "plain", cfg=WebConfig(background="backdrop"))


def _page_shot(glb, serve, tmp_path, w: int, h: int):
    """The page of ``glb`` in headless Chromium at w x h (no antialiasing), checked to load cleanly: (its RGB
    screenshot, the page's camera for ``render_preview``)."""
    from viewers.web import view_camera_from_web

    site = _site(glb, tmp_path / "site")
    report = _web_check(serve(site.out_dir) + "/index.html?dpr=1&noaa", tmp_path / "page.png", w, h)
    assert report["ready"] and not report["console_errors"] and not report["page_errors"], report
    cam = view_camera_from_web(json.loads(site.light_json.read_text())["camera"], w, h)
    return read_image(tmp_path / "page.png")[..., :3], cam


def _psnr(a, b) -> float:
    return float(-10 * np.log10(max(float(((a - b) ** 2).mean()), 1e-12)))


def test_page_applies_the_light_tint_like_dars_view(serve, tmp_path):
    """A GLB with a light-tint texture (the colour of the field's per-point light, toolkit.asset
    AssetConfig.light_tint): the page multiplies the model's shading by it as ``dars view`` does, a visible change
    of colour against the same cube without it."""
    from viewers.preview import render_preview

    glb = textured_cube(tmp_path / "cube.glb", light_tint=(1.3, 1.0, 0.6))
    shot, cam = _page_shot(glb, serve, tmp_path, 320, 240)
    ref = render_preview(glb, cam)
    plain = render_preview(textured_cube(tmp_path / "plain.glb"), cam)
    m = ref.mask
    assert m.mean() > 0.1
    ratio = ref.to_float()[m].mean(0) / np.maximum(plain.to_float()[m].mean(0), 1e-6)
    assert ratio[0] > 1.05 and ratio[2] < 0.85, ratio  # warmer: red up, blue down
    psnr_db = _psnr(shot, ref.to_float())
    assert psnr_db >= 30.0, f"page vs dars view with a light tint: PSNR {psnr_db:.1f} dB (bound 30 dB)"


def test_page_filters_textures_like_dars_view(serve, tmp_path):
    """A GLB with a _TEXTURE_BLUR attribute (the blur a view-projected bake puts in its textures), drawn small so
    the checker is minified: the page narrows its mip filter as ``dars view`` does (a visible change against plain
    trilinear mip-mapping there) and matches it."""
    from viewers.preview import PreviewConfig, render_preview

    glb = textured_cube(tmp_path / "cube.glb", texture_blur=64.0)
    shot, cam = _page_shot(glb, serve, tmp_path, 48, 36)
    ref = render_preview(glb, cam)
    trilinear = render_preview(glb, cam, PreviewConfig(texture_filter="trilinear"))
    assert ref.mask.mean() > 0.1
    change = np.abs(ref.to_float() - trilinear.to_float())[ref.mask].mean()
    assert change > 0.01, change  # the filter matters here
    psnr_db, psnr_trilinear = _psnr(shot, ref.to_float()), _psnr(shot, trilinear.to_float())
    assert psnr_db >= 30.0, f"page vs dars view with a texture blur: PSNR {psnr_db:.1f} dB (bound 30 dB)"
    assert psnr_db > psnr_trilinear + 1.0, (psnr_db, psnr_trilinear)  # the page narrows its filter too


def _without_base_colour_texture(glb: Path, out: Path) -> Path:
    """``glb`` with its material's baseColorTexture reference removed (the other maps stay)."""
    import pygltflib

    g = pygltflib.GLTF2.load(str(glb))
    g.materials[0].pbrMetallicRoughness.baseColorTexture = None
    g.save(str(out))
    return out


def test_page_filters_the_other_maps_of_a_glb_without_base_colour(serve, tmp_path):
    """A GLB with normal and ORM maps but no base-colour texture: the page still takes its filter's gradients (from
    the normal map's UVs) and its blur unit (the normal map's side), so the blur changes the minified occlusion
    checker as it does with a base colour (unset gradients would sample every map at its finest level whatever the
    blur)."""
    from viewers.preview import OffscreenPreview

    shots = {}
    for blur in (0.0, 64.0):
        glb = _without_base_colour_texture(textured_cube(tmp_path / f"cube{blur:.0f}.glb", texture_blur=blur,
                                                         occlusion_checker=True),
                                           tmp_path / f"plain{blur:.0f}.glb")
        (tmp_path / f"b{blur:.0f}").mkdir()
        shots[blur], _ = _page_shot(glb, serve, tmp_path / f"b{blur:.0f}", 48, 36)
    with OffscreenPreview(glb) as view:
        # The blur's unit is the normal map's side: the cube's atlas is 3 cells of 32 px across. The 1-texel
        # stand-in the renderer binds for a map the GLB lacks must not set it.
        assert view.renderer.texture_size == 3 * 32.0
    assert shots[0.0].std() > 0.02
    change = np.abs(shots[0.0] - shots[64.0]).mean()
    assert change > 0.001, change  # 0 with unset gradients


def test_page_with_threejs_stock_shading_loads(page, serve, tmp_path):
    report = _web_check(serve(page.out_dir) + "/index.html?dpr=1&shading=three", tmp_path / "stock.png", 160, 120)
    assert report["ready"] and not report["console_errors"] and not report["page_errors"], report
    assert read_image(tmp_path / "stock.png").std() > 0.02


# ================================================================================================================ CLI
def _dars(*args, timeout=900):
    return subprocess.run([sys.executable, "-m", "toolkit.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=ROOT, timeout=timeout, env=dict(os.environ, OMP_NUM_THREADS="1"))


def test_cli_export_web(cube_glb, tmp_path, capsys):
    from toolkit.cli import main

    (tmp_path / "sh.json").write_text(json.dumps({"coeffs": (CUBE_SH * 2).tolist()}))
    rc = main(["export-web", str(cube_glb), str(tmp_path / "site"), "--sh", str(tmp_path / "sh.json"),
               "--exposure", "-1", "--json"])
    cap = capsys.readouterr()
    if rc != 0 and "three.js not found" in cap.err:
        pytest.skip("three.js is not installed (node/npm missing?)")
    assert rc == 0, cap.err
    out = json.loads(cap.out)
    light = json.loads(Path(out["light_json"]).read_text())
    np.testing.assert_allclose(light["sh_world"], CUBE_SH * 2)
    assert light["exposure"] == -1 and "sh.json" in light["source"]
    assert (tmp_path / "site" / "scene.glb").read_bytes() == Path(cube_glb).read_bytes()
    assert main(["export-web", str(tmp_path / "nothing"), str(tmp_path / "x")]) == 2
    assert "not found" in capsys.readouterr().err
    assert main(["export-web", str(tmp_path), str(tmp_path / "x")]) == 2
    assert "RUN directory" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_export_web_from_a_run(tmp_path_factory):
    from _viewer_assets import surface_level

    run, _ = trained_sample(tmp_path_factory.mktemp("sample"))
    out = tmp_path_factory.mktemp("site")
    r = _dars("export-web", run, out, "--resolution", 64, "--texture", 256, "--view-rays", 20000, "--level", f"{surface_level(run):.4f}",
              "--json")
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res["asset"]["faces"] > 100 and (out / "scene.glb").is_file() and (out / "index.html").is_file()
