"""Benchmark of the moderngl preview: headless FPS at 1280 x 720 (EGL, Mesa llvmpipe on the CPU) for a baked sample
and a generated 500k-triangle mesh, per mode; optionally the baked-vs-field PSNR of a training run.

* ``baked sample``: an ``export-asset`` GLB of samples/gallery (``--asset DIR_OR_GLB``; without it a short run is
  trained and exported first, as tests/test_viewer.py does: ~4 min on one thread).
* ``500k mesh``: a 501 x 501 height-field "terrain" (500,000 triangles, 251,001 vertices) with UVs, tangents,
  2048² textures and 7 semantic primitives, written with :func:`export.gltf.export_gltf`.

FPS = frames / wall time of draw + ``glFinish`` (no read-back), after 2 warm-up frames; the first frame (shader
compile, texture upload) is reported separately. llvmpipe's rasteriser threads follow ``LP_NUM_THREADS``
(``--threads``, default 1, as the team's shared machine requires).

Usage: ``python bench/bench_viewer.py [--asset DIR_OR_GLB] [--frames 20] [--threads 1] [--psnr-run RUN [--psnr-asset DIR]]``
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))


def terrain_glb(path: Path, n: int = 500, texture: int = 2048) -> Path:
    """A height field with ``2 n²`` triangles as a textured GLB (world +z up, 10 m square)."""
    import numpy as np

    from export.gltf import export_gltf
    from toolkit.bake import PBRTextures, UVMesh, compute_tangents

    g = np.linspace(0.0, 1.0, n + 1)
    u, v = np.meshgrid(g, g, indexing="xy")
    x, y = (u - 0.5) * 10.0, (0.5 - v) * 10.0
    z = 0.4 * np.sin(x * 1.3) * np.cos(y * 0.9) + 0.15 * np.sin(x * 5.1 + y * 3.7)
    verts = np.stack([x, y, z], -1).reshape(-1, 3).astype(np.float32)
    dzdx = 0.4 * 1.3 * np.cos(x * 1.3) * np.cos(y * 0.9) + 0.15 * 5.1 * np.cos(x * 5.1 + y * 3.7)
    dzdy = -0.4 * 0.9 * np.sin(x * 1.3) * np.sin(y * 0.9) + 0.15 * 3.7 * np.cos(x * 5.1 + y * 3.7)
    nrm = np.stack([-dzdx, -dzdy, np.ones_like(z)], -1).reshape(-1, 3)
    nrm = (nrm / np.linalg.norm(nrm, axis=1, keepdims=True)).astype(np.float32)
    idx = np.arange((n + 1) * (n + 1)).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    uvs = np.stack([u, v], -1).reshape(-1, 2).astype(np.float32)
    labels = (np.floor(verts[faces[:, 0], 0] + 5.0) * 7 // 10).astype(np.uint8) % 7
    order = np.argsort(labels, kind="stable")
    uvm = UVMesh(verts, faces[order], uvs, nrm, compute_tangents(verts, faces, uvs, nrm), np.arange(len(verts)),
                 labels[order])
    yy, xx = np.mgrid[0:texture, 0:texture]
    base = np.stack([(xx // 64 + yy // 64) % 2 * 120 + 80, 90 + yy * 100 // texture, 60 + xx * 120 // texture], -1)
    orm = np.stack([np.full_like(xx, 255), 60 + (xx * 190 // texture), ((yy // 256) % 2) * 255], -1)
    nt = np.stack([0.2 * np.sin(xx / 9.0), 0.2 * np.cos(yy / 7.0), np.ones_like(xx, dtype=float)], -1)
    nt /= np.linalg.norm(nt, axis=-1, keepdims=True)
    tex = PBRTextures(base.astype(np.uint8), orm.astype(np.uint8), np.round((nt + 1) * 127.5).astype(np.uint8),
                      np.ones((texture, texture), bool))
    sh = np.zeros((9, 3))
    sh[0], sh[2] = 3.0, (0.8, 0.9, 1.0)
    return export_gltf(uvm, tex, path, sh=sh)


def sample_asset(work: Path) -> Path:
    from _viewer_assets import trained_sample

    print("[bench] no --asset: training samples/gallery briefly and exporting it (a few minutes, one thread)",
          file=sys.stderr)
    return trained_sample(work)[1]


def measure(asset_path: Path, frames: int, modes=("lit", "albedo", "semantics")) -> list[dict]:
    from export.gltf import load_glb
    from viewers.camera import default_camera
    from viewers.preview import OffscreenPreview, PreviewConfig, create_headless_context, resolve_asset_path

    t0 = time.perf_counter()
    asset = load_glb(resolve_asset_path(asset_path))
    load_s = time.perf_counter() - t0
    ctx = create_headless_context()
    rows = []
    try:
        t0 = time.perf_counter()
        view = OffscreenPreview(asset, ctx=ctx)
        upload_s = time.perf_counter() - t0
        cam = default_camera(asset.vertices, 1280, 720)
        for mode in modes:
            cfg = PreviewConfig(mode=mode)
            t0 = time.perf_counter()
            view.draw(cam, cfg)
            ctx.finish()
            first = time.perf_counter() - t0
            fps = view.measure_fps(cam, cfg, frames=frames)
            rows.append({"triangles": int(asset.faces.shape[0]), "vertices": int(asset.vertices.shape[0]),
                         "mode": mode, "fps": fps, "ms": 1000.0 / fps, "first_frame_s": first,
                         "load_s": load_s, "upload_compile_s": upload_s,
                         "texture": asset.images["base_color"].shape[0] if "base_color" in asset.images else 0})
        view.release()
    finally:
        ctx.release()
    return rows


def baked_vs_field_psnr(run: Path, asset: Path, views=(0, 7, 14)) -> dict:
    """Mean PSNR of `dars view` vs Run.render (test cameras; pixels the mesh covers and the field renders with
    opacity > 0.5), lit and albedo."""
    import numpy as np
    import torch

    from toolkit.io import linear_to_srgb
    from toolkit.metrics import psnr
    from toolkit.pinhole import PinholeCamera
    from toolkit.train import load_run
    from viewers.preview import OffscreenPreview, PreviewConfig

    r = load_run(run)
    scene = r.load_split("test")
    extent = float(np.linalg.norm((scene.aabb[1] - scene.aabb[0]).numpy()))
    chw = lambda a: torch.as_tensor(np.asarray(a, np.float32)).permute(2, 0, 1)  # noqa: E731
    lit, alb = [], []
    with OffscreenPreview(asset) as view:
        for i in views:
            with torch.no_grad():
                o = r.render(scene.cameras, i, deferred=True).as_dict()
            cam = PinholeCamera.from_cameras(scene.cameras, i, near=extent * 1e-3, far=extent * 10)
            a, b = view.render(cam), view.render(cam, PreviewConfig(mode="albedo"))
            m = torch.from_numpy(a.mask) & (o["opacity"] > 0.5)
            lit.append(float(psnr(chw(a.to_float()), chw(linear_to_srgb(o["rgb"].clamp(0, 1))), m)))
            alb.append(float(psnr(chw(b.to_float()), chw(linear_to_srgb(o["albedo"].clamp(0, 1))), m)))
    return {"steps": r.step, "minutes": r.elapsed / 60, "lit": lit, "albedo": alb}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--asset", default=None, help="export-asset directory or .glb of the baked sample")
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--threads", type=int, default=1, help="llvmpipe rasteriser threads (LP_NUM_THREADS)")
    p.add_argument("--psnr-run", default=None, help="also report baked-vs-field PSNR for this RUN")
    p.add_argument("--psnr-asset", default=None, help="its export-asset directory (default: --asset)")
    args = p.parse_args()
    os.environ["LP_NUM_THREADS"] = str(args.threads)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory(prefix="dars_bench_viewer_") as tmp:
        work = Path(tmp)
        asset = Path(args.asset) if args.asset else sample_asset(work)
        t0 = time.perf_counter()
        terrain = terrain_glb(work / "terrain.glb")
        gen_s = time.perf_counter() - t0
        rows = [("baked sample", r) for r in measure(asset, args.frames)]
        rows += [("500k mesh", r) for r in measure(terrain, args.frames)]
        print(f"\nheadless moderngl preview, 1280x720, EGL llvmpipe, LP_NUM_THREADS={args.threads}, "
              f"{args.frames} frames (draw + glFinish); 500k mesh generated in {gen_s:.1f} s")
        print(f"{'asset':<14}{'triangles':>10}{'texture':>9}{'mode':>11}{'FPS':>8}{'ms/frame':>10}{'1st frame s':>13}"
              f"{'upload+compile s':>18}")
        for name, r in rows:
            print(f"{name:<14}{r['triangles']:>10,}{r['texture']:>9}{r['mode']:>11}{r['fps']:>8.1f}{r['ms']:>10.1f}"
                  f"{r['first_frame_s']:>13.2f}{r['upload_compile_s']:>18.2f}")
        by = {(n, r["mode"]): r["fps"] for n, r in rows}
        print(f"ratios: lit / albedo frame time — sample {by[('baked sample', 'albedo')] / by[('baked sample', 'lit')]:.2f}x,"
              f" 500k {by[('500k mesh', 'albedo')] / by[('500k mesh', 'lit')]:.2f}x; 500k / sample frame time (lit) "
              f"{by[('baked sample', 'lit')] / by[('500k mesh', 'lit')]:.2f}x")
        if args.psnr_run:
            res = baked_vs_field_psnr(Path(args.psnr_run), Path(args.psnr_asset or asset))
            print(f"baked vs field ({res['steps']} steps, {res['minutes']:.1f} min): lit PSNR "
                  f"{', '.join(f'{x:.2f}' for x in res['lit'])} dB (mean {sum(res['lit']) / len(res['lit']):.2f}); "
                  f"albedo {', '.join(f'{x:.2f}' for x in res['albedo'])} dB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
