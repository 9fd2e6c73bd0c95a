"""The GLB against its field: the point-query bake against the view-projected bake, on the same mesh, and the
backdrop (issue 16's "moderngl preview of the GLB within 4 dB of the field's own render").

For each run: the mesh is built once with ``dars export-asset``'s defaults (:func:`toolkit.asset.build_mesh`), then
baked twice — ``--bake-from points`` (the field's materials at each texel's surface point) and ``--bake-from views``
(each texel's albedo from the field's renders at the training views that see it, :mod:`toolkit.viewbake`). The views
bake is written three times: without a backdrop (``views``: the preview draws the SH radiance where the mesh is not),
with the field's learned background map alone where the photos saw it (``background``), and with export-asset's
backdrop of export-asset (``backdrop``: the field's rendered colour wherever the mesh leaves a training pixel uncovered,
the background map elsewhere; :mod:`toolkit.backdrop`). These four have no light occlusion
(``AssetConfig.light_occlusion=False``) and the field's point normals in the normal map (``normals_from="points"``):
the GLB of earlier versions. ``occlusion``: the backdrop GLB with the field's per-point light gain in its occlusion
channel (and its colour in the light tint) and the SH scaled to match; ``view_normals``: that, with the normal map
from the field's rendered normals at the training views; ``light_fit`` (export-asset's default): that, with the
occlusion and tint fitted so that the viewer's shading of the baked textures shows the field's colour at the
training views (``AssetConfig.light_fit``, :func:`toolkit.viewbake.fit_light`). Each GLB's moderngl preview is
scored against the test photos beside the field's own render (``bench_train._assets_depth_and_preview``: all test
views, the field rendered once for both; the depth error where the scene has ground-truth depth; each GLB's albedo
against the ground truth where the scene has it, beside the field's). Prints one row per run and bake, the gap to
the field, and the mean and worst gap over the runs, and writes ``OUT/runK/compare.png`` per run to look at: photo |
field | each GLB's preview on three test views. The ``trilinear`` column scores the same GLB under plain trilinear
mip-mapping (``PreviewConfig(texture_filter="trilinear")``: what other glTF viewers draw) beside ``dars view``'s
footprint filter, which knows the blur the view-projected bake put in the textures (the GLB's ``_TEXTURE_BLUR``).
Also prints the field's PSNR with its per-point light residual
switched off (the global SH only: what a GLB can carry).

Usage: ``python bench/bench_bake.py --run RUN [--run RUN2 ...] [--threads 2] [--view-rays 2000000]`` (export-asset's
defaults: 2048² textures, every pixel of up to 2M; ``--view-rays 300000`` for the GLBs before 2026-12-03). Without
``--run`` it first trains the bundled sample for 300 steps (``bench/out/bake/sample_run``, a few minutes).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))


def _sample_run(out: Path, threads: int) -> Path:
    run = out / "sample_run"
    if not (run / "checkpoint.pt").is_file():
        subprocess.run([sys.executable, "-m", "toolkit.cli", "train", str(ROOT / "samples" / "gallery"), "--out",
                        str(run), "--steps", "300", "--threads", str(threads), "--quiet", "--force"], check=True,
                       cwd=ROOT, env={**os.environ, "OMP_NUM_THREADS": str(threads)})
    return run


def bake_both(run: Path, out: Path, threads: int, view_rays: int, min_opacity: float = 0.5,
              min_component: float = 0.05) -> dict:
    """Mesh ``run`` once, bake it from points and from views, export and score both GLBs."""
    import torch

    from bench_train import _assets_depth_and_preview
    from export.gltf import export_gltf
    from toolkit.asset import Asset, AssetConfig, asset_field, bake_mesh, build_backdrop, build_mesh, view_maps
    from toolkit.train import load_run

    torch.set_num_threads(threads)
    loaded = load_run(run)  # once: the mesh, the bake, the comparison image and the no-residual score
    field = asset_field(loaded)
    cfg = AssetConfig(view_rays=view_rays, depth_min_opacity=min_opacity, min_component=min_component,
                      light_occlusion=False, normals_from="points")
    t0 = time.perf_counter()
    mesh, stats = build_mesh(field, cfg)
    print(f"[bench_bake] {run}: mesh of {mesh.num_faces} faces ({stats['method']}) in "
          f"{time.perf_counter() - t0:.0f} s", file=sys.stderr)
    t0 = time.perf_counter()
    maps = view_maps(field, replace(cfg, light_occlusion=True))  # with the light gain, for ``occlusion``
    render_s = time.perf_counter() - t0
    baked = {}
    for name, views in (("points", None), ("views", maps)):
        t0 = time.perf_counter()
        uvmesh, textures, bake = bake_mesh(mesh, field.material_fn, cfg, views=views)
        (out / name).mkdir(parents=True, exist_ok=True)
        export_gltf(uvmesh, textures, out / name / "scene.glb", sh=field.sh)
        baked[name] = {"bake_seconds": time.perf_counter() - t0 + (render_s if views is not None else 0.0),
                       "views": bake.get("views")}
    # background: the field's learned background map alone; backdrop (the default): its colour where the mesh is not
    for name, backdrop in (("background", build_backdrop(field, maps, cfg)),
                           ("backdrop", build_backdrop(field, maps, cfg, uvmesh))):
        if backdrop is None:
            continue
        (out / name).mkdir(parents=True, exist_ok=True)
        extras = Asset(mesh, uvmesh, textures, field.sh, stats, backdrop).gltf_extras()
        export_gltf(uvmesh, textures, out / name / "scene.glb", sh=field.sh, extras=extras)
        baked[name] = {**baked["views"], "backdrop_texels_seen": float((backdrop.visibility > 0).mean()),
                       "backdrop_mean_visibility": float(backdrop.visibility.mean())}
    # occlusion: the backdrop GLB with the field's light gain in its occlusion channel (and its tint), SH times s;
    # view_normals: that, with the normal map from the field's rendered normals; light_fit (export-asset's
    # default): that, with the occlusion and tint fitted so the viewer's shading shows the field's colour
    if "backdrop" in baked and "light_gain" in maps.values:
        occ_cfg = replace(cfg, light_occlusion=True)
        view_cfg = replace(occ_cfg, normals_from="views")
        for name, glb_cfg, fit_sh in (("occlusion", occ_cfg, None), ("view_normals", view_cfg, None),
                                      ("light_fit", view_cfg, field.sh)):
            t0 = time.perf_counter()
            uvmesh, textures, bake = bake_mesh(mesh, field.material_fn, glb_cfg, views=maps, sh=fit_sh)
            sh = field.sh * bake["light_scale"]
            backdrop = build_backdrop(field, maps, glb_cfg, uvmesh)
            extras = Asset(mesh, uvmesh, textures, sh, {**stats, "bake": bake}, backdrop).gltf_extras()
            (out / name).mkdir(parents=True, exist_ok=True)
            export_gltf(uvmesh, textures, out / name / "scene.glb", sh=sh, extras=extras)
            baked[name] = {"bake_seconds": time.perf_counter() - t0 + render_s, "views": bake.get("views"),
                           "light_scale": bake["light_scale"]}
    rows = _assets_depth_and_preview(run, {name: out / name for name in baked}, threads, albedo_vs_gt=True)
    for name, extra in baked.items():
        rows[name].update(extra, gap_db=rows[name]["field_psnr"] - rows[name]["preview_psnr"])
    rows["comparison_png"] = str(write_comparison(loaded, {name: out / name for name in baked}, out / "compare.png"))
    rows["field_without_residual_psnr"] = field_psnr_without_residual(loaded)
    return rows


def field_psnr_without_residual(run) -> float | None:
    """Mean test PSNR of a loaded run's field rendered with its per-point light residual Δl(x) switched off (global
    SH only): the part of the field's colour a GLB lit by that SH can carry. None when the field has no residual
    head. The run is left as it was."""
    import numpy as np
    import torch

    from toolkit.io import linear_to_srgb
    from toolkit.metrics import psnr
    from toolkit.train.run import light_residual_off

    if getattr(run.field, "light_head", None) is None:
        return None
    sc = run.load_split("test")
    scores = []
    with light_residual_off(run):
        for i in range(len(sc)):
            with torch.no_grad():
                o = run.render(sc.cameras, i)
            scores.append(float(psnr(linear_to_srgb(o.rgb.clamp(0, 1)).permute(2, 0, 1), sc.load_image(i))))
    return float(np.mean(scores))


def write_comparison(run, asset_dirs: dict, out_png: Path, n: int = 3) -> Path:
    """A PNG grid to look at: one row per test view (``n`` evenly spread) of a loaded run, columns photo | the field's
    render | each GLB's moderngl preview (in ``asset_dirs`` order)."""
    import numpy as np
    import torch

    from toolkit.io import linear_to_srgb, write_png
    from toolkit.pinhole import PinholeCamera
    from toolkit.visualise import tile
    from viewers.preview import OffscreenPreview

    sc = run.load_split("test")
    extent = float(np.linalg.norm((run.train_scene.aabb[1] - run.train_scene.aabb[0]).numpy()))
    idx = np.linspace(0, len(sc) - 1, min(n, len(sc))).round().astype(int)
    rows = []
    for i in idx:
        with torch.no_grad():
            o = run.render(sc.cameras, int(i))
        rows.append([sc.load_image(int(i)).permute(1, 2, 0).numpy(), linear_to_srgb(o.rgb.clamp(0, 1)).numpy()])
    for asset_dir in asset_dirs.values():
        with OffscreenPreview(asset_dir / "scene.glb") as view:
            for row, i in zip(rows, idx):
                cam = PinholeCamera.from_cameras(sc.cameras, int(i), near=extent * 1e-3, far=extent * 10)
                row.append(view.render(cam).to_float())
    write_png(out_png, tile(rows))
    return out_png


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", action="append", default=[], help="a training run (repeat for several)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--view-rays", type=int, default=2_000_000)
    ap.add_argument("--depth-min-opacity", type=float, default=0.5, help="export-asset's option of that name")
    ap.add_argument("--min-component", type=float, default=0.05, help="export-asset's option of that name")
    ap.add_argument("--out", default=str(ROOT / "bench" / "out" / "bake"))
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = [Path(r) for r in args.run] or [_sample_run(out, args.threads)]
    results = {}
    for k, run in enumerate(runs):
        results[str(run)] = bake_both(run, out / f"run{k}", args.threads, args.view_rays,
                                           args.depth_min_opacity, args.min_component)
    print(f"{'run':<40} {'GLB':<12} {'field dB':>9} {'preview dB':>11} {'trilinear':>10} {'gap dB':>7} {'depth m':>8} "
          f"{'bake s':>7} {'albedo MAE (aligned) vs GT':>27}")
    names = ("points", "views", "background", "backdrop", "occlusion", "view_normals", "light_fit")
    for run, rows in results.items():
        for name in (n for n in names if n in rows):
            r = rows[name]
            depth, alb = r["depth_error_median_m"], r.get("albedo_vs_gt")
            alb_txt = "-" if alb is None else f"{alb['albedo_mae']:.3f} ({alb['albedo_mae_aligned']:.3f})"
            depth_txt = "-" if depth is None else f"{depth:.3f}"
            print(f"{run[-40:]:<40} {name:<12} {r['field_psnr']:9.2f} {r['preview_psnr']:11.2f} "
                  f"{r['preview_psnr_trilinear']:10.2f} {r['gap_db']:7.2f} {depth_txt:>8} "
                  f"{r['bake_seconds']:7.0f} {alb_txt:>27}")
        print(f"{'':<40} photo | field | {' | '.join(n for n in names if n in rows)}: {rows['comparison_png']}")
        if "occlusion" in rows:
            print(f"{'':<40} occlusion: the GLB's SH is the run's x {rows['occlusion']['light_scale']:.3f}")
        if rows.get("field_without_residual_psnr") is not None:
            print(f"{'':<40} the field without its per-point light residual (global SH only, what a GLB can carry): "
                  f"{rows['field_without_residual_psnr']:.2f} dB")
        if "field_albedo_vs_gt" in rows:
            f = rows["field_albedo_vs_gt"]
            print(f"{'':<40} the field's own composited albedo vs GT: {f['albedo_mae']:.3f} "
                  f"({f['albedo_mae_aligned']:.3f}) on {f['pixels']} pixels")
    for name in names:
        gaps = [rows[name]["gap_db"] for rows in results.values() if name in rows]
        if gaps:
            print(f"{name}: gap to the field mean {sum(gaps) / len(gaps):.2f} dB, worst {max(gaps):.2f} dB "
                  f"over {len(gaps)} run(s) (issue 16's bound: 4 dB)")
    for a, b in (("views", "points"), ("background", "views"), ("backdrop", "views"), ("backdrop", "background"),
                 ("occlusion", "backdrop"), ("view_normals", "occlusion"), ("light_fit", "view_normals")):
        gain = [rows[a]["preview_psnr"] - rows[b]["preview_psnr"] for rows in results.values() if a in rows]
        if gain:
            print(f"{a} vs {b}: preview {sum(gain) / len(gain):+.2f} dB mean, {min(gain):+.2f} dB worst")
    gain = [rows["light_fit"]["preview_psnr"] - rows["light_fit"]["preview_psnr_trilinear"]
            for rows in results.values() if "light_fit" in rows]
    if gain:
        print(f"light_fit, the footprint filter (dars view, the WebXR page) vs plain trilinear mip-maps (other glTF "
              f"viewers): preview {sum(gain) / len(gain):+.2f} dB mean, {min(gain):+.2f} dB worst")
    (out / "bench_bake.json").write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
