"""Training benchmarks (issue 4): quality after wall-clock budgets, and throughput.

Cases (``--case``, default ``all``):

* ``sample``   — the bundled gallery, ``fast`` preset with the light prior (``dars priors light``, as the demo): test
  PSNR, normal MAE and albedo MAE after 2, 5 and 10 minutes
  (snapshots of one 10-minute run); same-run baseline: ``--baseline nerf`` (PSNR only).
* ``lego``     — NeRF-synthetic Lego at 400 px (100 train views), PSNR on ``val`` after 5 and 15 minutes, full model
  and ``--baseline nerf``.
* ``tiny``     — tiny Lego (100 px; first 100 train, views 100-105 test): PSNR after 3, 5 and 10 minutes for
  ``--baseline nerf`` and the full decomposed model (only figures measured in this run are printed).
* ``galleries`` — every held-out validation gallery (``samples/galleries.py``: rendered on first use, cached), photos
  and poses only: test PSNR, albedo MAE, normal MAE, mIoU, the exported GLB's median depth error on the test views
  and its moderngl preview PSNR beside the field's; per gallery, mean and worst.
* ``objects`` — object captures (``samples/render_object.py``: spot, bob, the bunny and the armadillo under an HDR
  probe, RGBA photos with ground-truth normals and albedo; rendered on first use, cached), ``--steps`` (default 2000):
  test PSNR, normal MAE, the normals' angle to the rendered depth's, albedo MAE; per object, mean and worst.
* ``throughput`` — training and rendering rays/s and peak memory for ``mlp`` vs ``grid`` fields and DARS vs uniform
  sampling, on the sample, in one run (ratios against grid + uniform).

Every training runs in its own subprocess (peak RSS per case). Figures depend on the machine and its load: run on a
quiet machine (``make bench``). Usage: ``python bench/bench_train.py --case tiny [--threads 2] [--out bench/out]``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SHARED = (ROOT / ".." / "shared" / "data").resolve()
PY = sys.executable


def _train(scene: str, out: Path, minutes: float, snapshots: str, threads: int, extra: list[str]) -> dict:
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.exists():
        import shutil

        shutil.rmtree(out)
    cmd = [PY, "-m", "toolkit.cli", "train", scene, "--out", str(out), "--threads", str(threads), "--quiet", *extra]
    if minutes:
        cmd += ["--minutes", str(minutes)]
    if snapshots:
        cmd += ["--snapshots", snapshots]
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t0 = time.time()
    subprocess.run(cmd, check=True, cwd=ROOT, env={**os.environ, "OMP_NUM_THREADS": str(threads)})
    rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    from toolkit.train.folder import read_checkpoint

    steps = int(read_checkpoint(out / "checkpoint.pt")["step"])  # the log keeps every log_every-th step only
    return {"wall_s": time.time() - t0, "peak_rss_mb": max(rss, before) / 1024.0, "steps": steps}


def _eval_psnr(run_dir: Path, split: str, checkpoint: Path | None, views: list[int] | None, threads: int) -> dict:
    import torch

    from toolkit.io import linear_to_srgb
    from toolkit.metrics import albedo_mae, material_mask, psnr
    from toolkit.pipeline import RenderInputs, render_image
    from toolkit.train import load_run

    torch.set_num_threads(threads)
    run = load_run(run_dir, checkpoint)
    sc = run.load_split(split)
    idx = views if views is not None else list(range(len(sc)))
    ps, maes, nmae = [], [], []
    t0 = time.time()
    for i in idx:
        o = render_image(run.field, sc.cameras, i, run.render_config(near=sc.near, far=sc.far),
                         RenderInputs(run.occupancy, run.l_env, run.background, sc.aabb,
                                      run.dars_for(sc.cameras.c2w[i]))).as_dict()
        ps.append(float(psnr(linear_to_srgb(o["rgb"].clamp(0, 1)).permute(2, 0, 1), sc.load_image(i))))
        if sc.has_extra("normal"):
            gt_n = sc.load_extra(i, "normal").permute(1, 2, 0)
            m_n = gt_n.norm(dim=-1) > 0.5
            if m_n.any():
                n = torch.nn.functional.normalize(o["normal"], dim=-1)
                nmae.append(float(torch.rad2deg(torch.acos((n * gt_n).sum(-1).clamp(-1, 1)[m_n])).mean()))
        if "albedo" in o and sc.has_extra("albedo") and sc.has_extra("semantic"):
            mask = material_mask(sc.load_extra(i, "semantic"), sc.load_extra(i, "depth") if sc.has_extra("depth") else None)
            if mask.any():
                maes.append(float(albedo_mae(o["albedo"].permute(2, 0, 1).clamp(0, 1), sc.load_extra(i, "albedo"), mask)))
    res = {"psnr": sum(ps) / len(ps), "views": len(idx), "render_s_per_view": (time.time() - t0) / len(idx)}
    if maes:
        res["albedo_mae"] = sum(maes) / len(maes)
    if nmae:
        res["normal_mae_deg"] = sum(nmae) / len(nmae)
    return res


def _milestones(run: Path, minutes: list[float], split: str, views, threads: int) -> dict:
    out = {}
    for m in minutes:
        ck = run / "snapshots" / f"checkpoint_{m:g}min.pt"
        if not ck.is_file():
            ck = run / "checkpoint.pt"
        out[m] = _eval_psnr(run, split, ck, views, threads)
    return out


def _table(title: str, header: list[str], rows: list[list]) -> str:
    lines = [f"\n{title}", " | ".join(header), " | ".join("---" for _ in header)]
    for r in rows:
        lines.append(" | ".join(f"{v:.3f}" if isinstance(v, float) else str(v) for v in r))
    return "\n".join(lines)


def case_quality(name: str, scene: str, minutes: list[float], split: str, views, threads: int, out_dir: Path,
                 variants: dict[str, list[str]]) -> dict:
    results = {}
    total = max(minutes)
    snaps = ",".join(f"{m:g}" for m in minutes)
    for vname, extra in variants.items():
        run = out_dir / name / vname
        info = _train(scene, run, total, snaps, threads, extra)
        results[vname] = {"train": info, "milestones": _milestones(run, minutes, split, views, threads)}
    header = ["variant"] + [f"PSNR @{m:g} min" for m in minutes] + ["steps", "peak RSS MB"]
    rows = []
    for vname, r in results.items():
        rows.append([vname] + [r["milestones"][m]["psnr"] for m in minutes] + [r["train"]["steps"],
                                                                                  r["train"]["peak_rss_mb"]])
    print(_table(f"[{name}] {scene} split={split} views={len(views) if views else 'all'} threads={threads}", header, rows))
    base = list(results)[-1]
    for vname, r in results.items():
        if vname != base:
            ratio = [r["milestones"][m]["psnr"] - results[base]["milestones"][m]["psnr"] for m in minutes]
            print(f"  {vname} vs {base}: " + ", ".join(f"{d:+.2f} dB @{m:g} min" for d, m in zip(ratio, minutes)))
    for vname, r in results.items():
        if any("normal_mae_deg" in r["milestones"][m] for m in minutes):
            print(f"  {vname} normal MAE: " + ", ".join(f"{r['milestones'][m].get('normal_mae_deg', float('nan')):.1f} deg @{m:g} min"
                                                        for m in minutes))
        if any("albedo_mae" in r["milestones"][m] for m in minutes):
            print(f"  {vname} albedo MAE: " + ", ".join(f"{r['milestones'][m].get('albedo_mae', float('nan')):.4f} @{m:g} min"
                                                        for m in minutes))
    return results


def case_throughput(threads: int, out_dir: Path) -> dict:
    """Training and rendering rays/s and peak memory (tracemalloc-free: RSS of a subprocess per config)."""
    code = r"""
import json, sys, time, resource, torch
sys.path.insert(0, %r)
torch.set_num_threads(%d)
from toolkit.train import make_config, prepare_data, init_state, train_step, resolve_config
from toolkit.field import FieldConfig
from toolkit.scene import load_scene
from toolkit.pipeline import RenderConfig, RenderInputs, render_dars_context, render_image
kw = json.loads(sys.argv[1])
enc = kw.pop('encoding')
scene = load_scene(%r, 'train')
cfg = make_config('fast' if enc == 'grid' else 'paper', steps=100000, pretrain_fraction=0.0, **kw)
cfg, scene = resolve_config(cfg, scene)
data = prepare_data(scene, cfg, log=lambda m: None)
st = init_state(cfg, data)
n_warm = 80 if enc == 'grid' else 5
for i in range(n_warm):
    if st.step %% cfg.occupancy_every == 0:
        st.occupancy.update(st.field.density, st.generator, all_cells=st.step < cfg.occupancy_warmup,
                            warmup=st.step < cfg.occupancy_warmup)
    train_step(st, data); st.step += 1
n = 20 if enc == 'grid' else 3
t = time.time()
for i in range(n):
    r = train_step(st, data); st.step += 1
dt = (time.time() - t) / n
# the render path a trained run uses: with DARS, the W maps of the nearest training views steer the samples
ctx = (render_dars_context(st.dars.cameras, st.dars.weight_maps, scene.cameras.c2w[0], cfg.render_sampler.n_neighbours)
       if cfg.render_sampler.dars and st.dars is not None else None)
assert (ctx is not None) == bool(cfg.render_sampler.dars), 'DARS render path not taken'
t = time.time()
o = render_image(st.field, scene.cameras, 0, RenderConfig(sampler=cfg.render_sampler, shading=cfg.shading,
                 deferred=True, chunk=4096), RenderInputs(st.occupancy, st.l_env.detach(), st.background, scene.aabb,
                 dars=ctx))
rt = time.time() - t
h, w = o.rgb.shape[:2]
print(json.dumps({'train_rays_s': cfg.batch_rays / dt, 'samples_per_ray': r['samples_per_ray'],
                  'render_rays_s': h * w / rt, 'peak_rss_mb': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
""" % (str(ROOT), threads, str(ROOT / "samples" / "gallery"))
    configs = {"grid + uniform": {"encoding": "grid", "dars": False}, "grid + DARS": {"encoding": "grid", "dars": True},
               "mlp + uniform": {"encoding": "mlp", "dars": False}, "mlp + DARS": {"encoding": "mlp", "dars": True}}
    res = {}
    for name, kw in configs.items():
        p = subprocess.run([PY, "-c", code, json.dumps(kw)], capture_output=True, text=True, cwd=ROOT,
                           env={**os.environ, "OMP_NUM_THREADS": str(threads)})
        if p.returncode != 0:
            raise RuntimeError(f"throughput case {name} failed:\n{p.stderr[-2000:]}")
        res[name] = json.loads(p.stdout.strip().splitlines()[-1])
    base = res["grid + uniform"]
    rows = [[k, v["train_rays_s"], v["train_rays_s"] / base["train_rays_s"], v["render_rays_s"],
             v["render_rays_s"] / base["render_rays_s"], v["samples_per_ray"], v["peak_rss_mb"]] for k, v in res.items()]
    print(_table(f"[throughput] samples/gallery, threads={threads} (ratios vs grid + uniform)",
                 ["config", "train rays/s", "ratio", "render rays/s", "ratio", "samples/ray", "peak RSS MB"], rows))
    return res


def _asset_depth_and_preview(run_dir: Path, asset_dir: Path, threads: int) -> dict:
    """Median depth error of the exported GLB on the test views (against the scene's ground-truth depth), and the
    moderngl preview's PSNR against the photos beside the field's own render's (all test views): ``preview_psnr``
    with ``dars view``'s footprint texture filter, ``preview_psnr_trilinear`` with plain trilinear mip-maps (what
    other glTF viewers draw)."""
    return _assets_depth_and_preview(run_dir, {"asset": asset_dir}, threads)["asset"]


def _assets_depth_and_preview(run_dir: Path, asset_dirs: dict[str, Path], threads: int,
                              albedo_vs_gt: bool = False) -> dict:
    """:func:`_asset_depth_and_preview` of several GLBs of one run (``name -> export-asset folder``), the field
    rendered once per test view for all of them.

    With ``albedo_vs_gt`` and ground-truth albedo in the test split, also each GLB's albedo (the preview's albedo
    mode, linearised) and the field's composited albedo against it, on ``dars eval``'s material pixels that every GLB
    covers: ``albedo_mae``, ``albedo_mae_aligned`` and ``pixels`` under each name's ``albedo_vs_gt`` and under
    ``"field_albedo_vs_gt"``."""
    import numpy as np
    import torch

    from export.gltf import load_glb
    from toolkit.evaluate import _material_region
    from toolkit.io import linear_to_srgb, srgb_to_linear
    from toolkit.metrics import albedo_mae, albedo_mae_aligned, mesh_depth_error, psnr
    from toolkit.pinhole import PinholeCamera
    from toolkit.train import load_run
    from viewers.preview import OffscreenPreview, PreviewConfig

    torch.set_num_threads(threads)
    run = load_run(run_dir)
    sc = run.load_split("test")
    extras = sc.extras_available()
    with_albedo = albedo_vs_gt and "albedo" in extras
    extent = float(np.linalg.norm((run.train_scene.aabb[1] - run.train_scene.aabb[0]).numpy()))
    chw = lambda a: torch.as_tensor(np.asarray(a, np.float32)).permute(2, 0, 1)  # noqa: E731
    photos = [sc.load_image(i) for i in range(len(sc))]
    depths = [sc.load_extra(i, "depth") for i in range(len(sc))] if "depth" in extras else None
    p_field, field_albedo, gt_albedo, masks = [], [], [], []
    for i in range(len(sc)):
        with torch.no_grad():
            o = run.render(sc.cameras, i)
        p_field.append(float(psnr(linear_to_srgb(o.rgb.clamp(0, 1)).permute(2, 0, 1), photos[i])))
        if with_albedo:
            labels = sc.load_extra(i, "semantic") if "semantic" in extras else None
            masks.append(_material_region(sc, i, extras, None if depths is None else depths[i], labels)[0])
            field_albedo.append(o.albedo.clamp(0, 1).permute(2, 0, 1))
            gt_albedo.append(sc.load_extra(i, "albedo"))
    res, glb_albedo = {}, {}
    for name, asset_dir in asset_dirs.items():
        glb = asset_dir / "scene.glb"
        asset = load_glb(glb)
        depth_med, cover, p_view, p_trilinear = [], [], [], []
        with OffscreenPreview(glb) as view:
            for i in range(len(sc)):
                if depths is not None:
                    e = mesh_depth_error(asset.vertices, asset.faces, sc.cameras, i, depths[i])
                    depth_med.append(e["median"])
                    cover.append(e["coverage"])
                cam = PinholeCamera.from_cameras(sc.cameras, i, near=extent * 1e-3, far=extent * 10)
                p_view.append(float(psnr(chw(view.render(cam).to_float()), photos[i])))
                plain = view.render(cam, PreviewConfig(texture_filter="trilinear"))  # what other glTF viewers draw
                p_trilinear.append(float(psnr(chw(plain.to_float()), photos[i])))
                if with_albedo:
                    alb = view.render(cam, PreviewConfig(mode="albedo"))
                    masks[i] = masks[i] & torch.as_tensor(alb.mask)
                    glb_albedo.setdefault(name, []).append(
                        torch.as_tensor(srgb_to_linear(np.asarray(alb.to_float(), np.float64)), dtype=torch.float32)
                        .permute(2, 0, 1))
        finite = [d for d in depth_med if np.isfinite(d)]
        res[name] = {"depth_error_median_m": float(np.median(finite)) if finite else None,
                     "depth_coverage": float(np.mean(cover)) if cover else None,
                     "field_psnr": float(np.mean(p_field)), "preview_psnr": float(np.mean(p_view)),
                     "preview_psnr_trilinear": float(np.mean(p_trilinear))}
    if with_albedo:
        gt, m = torch.stack(gt_albedo), torch.stack(masks)
        score = lambda pred: {"albedo_mae": float(albedo_mae(pred, gt, m)),  # noqa: E731
                              "albedo_mae_aligned": float(albedo_mae_aligned(pred, gt, m)[0]), "pixels": int(m.sum())}
        for name, preds in glb_albedo.items():
            res[name]["albedo_vs_gt"] = score(torch.stack(preds))
        res["field_albedo_vs_gt"] = score(torch.stack(field_albedo))
    return res


def _with_mean_and_worst(rows: dict[str, dict], keys: list[str], worse_high: set[str]) -> list[list]:
    """Table rows: one per entry of ``rows`` (its name, then ``keys``), then the mean and the worst of each key (the
    largest for ``worse_high`` keys, else the smallest), over the entries that have it."""
    table = [[name] + [r.get(k) for k in keys] for name, r in rows.items()]

    def agg(fn, k):
        vals = [r[k] for r in rows.values() if r.get(k) is not None]
        return fn(vals) if vals else None

    table.append(["mean"] + [agg(lambda v: sum(v) / len(v), k) for k in keys])
    table.append(["worst"] + [agg(max if k in worse_high else min, k) for k in keys])
    return table


def case_galleries(seeds: list[int], minutes: float, steps: int, threads: int, out_dir: Path, train_seed: int,
                   extra: list[str], export_only: bool = False, export_extra: list[str] | None = None) -> dict:
    """Every validation gallery (photos + poses only: no box, no labels, no ground-truth light): train, evaluate,
    export the GLB, measure its depth error and its moderngl preview; print each gallery, the mean and the worst.

    ``export_only``: keep each gallery's run from an earlier call (its step count read back from the run) and only
    export and score the GLB again, with ``export_extra`` added to ``dars export-asset``."""
    sys.path.insert(0, str(ROOT / "samples"))
    from galleries import ensure_gallery

    from toolkit.evaluate import EvalConfig, evaluate_run
    from toolkit.train import load_run

    rows = {}
    for seed in seeds:
        scene = ensure_gallery(seed, "validation")
        run = out_dir / "galleries" / f"seed_{seed}" / "run"
        asset = run.parent / "asset"
        if export_only:
            if not (run / "checkpoint.pt").is_file():
                raise SystemExit(f"--export-only: {run} holds no trained run; run the galleries case without it first")
        else:
            budget = ["--steps", str(steps)] if steps else ["--minutes", str(minutes)]
            info = _train(str(scene), run, 0, "", threads, ["--seed", str(train_seed), *budget, *extra])
        trained = load_run(run)
        if export_only:  # the train row of the earlier call: its step count (wall time and memory not kept)
            info = {"steps": trained.step, "wall_s": None, "peak_rss_mb": None}
        res = evaluate_run(trained, "test", EvalConfig())
        m = res.metrics
        if asset.exists():
            import shutil

            shutil.rmtree(asset)
        subprocess.run([PY, "-m", "toolkit.cli", "export-asset", str(run), "--out", str(asset), "--json",
                        *(export_extra or [])], check=True,
                       cwd=ROOT, stdout=subprocess.DEVNULL, env={**os.environ, "OMP_NUM_THREADS": str(threads)})
        geo = _asset_depth_and_preview(run, asset, threads)
        rows[seed] = {"steps": info["steps"], "train_wall_s": info["wall_s"], "peak_rss_mb": info["peak_rss_mb"],
                      "psnr": m.get("psnr"), "ssim": m.get("ssim"), "albedo_mae": m.get("albedo_mae"),
                      "albedo_mae_aligned": res.details["materials"]["albedo_mae_aligned"],
                      "metallic_mae": res.details["materials"]["metallic_mae"],
                      "normal_mae": m.get("normal_mae"), "miou": m.get("miou"), "env_light_l2": m.get("env_light_l2"),
                      **geo}
        print(f"[galleries] seed {seed}: " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                                       for k, v in rows[seed].items()), flush=True)
    keys = ["psnr", "albedo_mae", "albedo_mae_aligned", "metallic_mae", "normal_mae", "depth_error_median_m",
            "preview_psnr", "preview_psnr_trilinear", "field_psnr", "miou", "steps"]
    worse_high = {"albedo_mae", "albedo_mae_aligned", "metallic_mae", "normal_mae", "depth_error_median_m"}
    table = _with_mean_and_worst({f"seed {s}": r for s, r in rows.items()}, keys, worse_high)
    print(_table(f"[galleries] {len(rows)} validation galleries, fast preset, "
                 f"{'%d steps' % steps if steps else '%g min' % minutes}, {threads} threads, train seed {train_seed} "
                 "(photos + poses only)", ["gallery"] + keys, table))
    return rows


def case_objects(objects: list[tuple[str, int]], steps: int, threads: int, out_dir: Path, train_seed: int,
                 extra: list[str]) -> dict:
    """Every object capture of ``samples/render_object.py`` (a reference mesh under an HDR probe, RGBA photos;
    rendered on first use, cached): train for ``steps``, evaluate on the test views; print each object's PSNR,
    normal MAE (against the ground truth), the normals' angle to the rendered depth's, albedo MAE (raw and
    scale-aligned), the final light's L2 to the probe's SH (eq. 36), then the mean and the worst."""
    sys.path.insert(0, str(ROOT / "samples"))
    from render_object import ensure_object

    from toolkit.evaluate import EvalConfig, evaluate_run
    from toolkit.train import load_run

    rows = {}
    for mesh, seed in objects:
        scene = ensure_object(mesh, seed)
        name = f"{mesh}_s{seed}"
        run = out_dir / "objects" / name / "run"
        info = _train(str(scene), run, 0, "", threads, ["--seed", str(train_seed), "--steps", str(steps), *extra])
        res = evaluate_run(load_run(run), "test", EvalConfig())
        m, nd = res.metrics, res.details.get("normal_vs_depth") or {}
        rows[name] = {"steps": info["steps"], "train_wall_s": info["wall_s"], "psnr": m.get("psnr"), "ssim": m.get("ssim"),
                      "normal_mae": m.get("normal_mae"), "normal_vs_depth_deg": nd.get("angle_mean_deg"),
                      "back_facing_share": nd.get("back_facing_share"), "albedo_mae": m.get("albedo_mae"),
                      "albedo_mae_aligned": res.details["materials"]["albedo_mae_aligned"],
                      "env_light_l2": m.get("env_light_l2")}
        print(f"[objects] {name}: " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                               for k, v in rows[name].items()), flush=True)
    keys = ["psnr", "ssim", "normal_mae", "normal_vs_depth_deg", "back_facing_share", "albedo_mae", "albedo_mae_aligned",
            "env_light_l2", "steps"]
    worse_high = {"normal_mae", "normal_vs_depth_deg", "back_facing_share", "albedo_mae", "albedo_mae_aligned",
                  "env_light_l2"}
    table = _with_mean_and_worst(rows, keys, worse_high)
    print(_table(f"[objects] {len(rows)} object captures, {steps} steps, {threads} threads, train seed {train_seed}"
                 f"{' ' + ' '.join(extra) if extra else ''} (photos + poses only)", ["object"] + keys, table))
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", default="all", choices=["all", "sample", "lego", "tiny", "throughput", "galleries", "objects"])
    ap.add_argument("--objects", default="all",
                    help="objects case: 'all' (every mesh at seed 0) or MESH:SEED,... (e.g. spot:0,bunny:1)")
    ap.add_argument("--galleries", default="all",
                    help="galleries case: 'all' validation galleries, the first N (a quick look; report all), or "
                         "validation seeds, comma-separated (e.g. 1000001,)")
    ap.add_argument("--minutes", type=float, default=10.0, help="galleries case: training budget per gallery")
    ap.add_argument("--steps", type=int, default=0,
                    help="galleries case: a step budget instead of --minutes; objects case: the step budget (default 2000)")
    ap.add_argument("--seed", type=int, default=0, help="galleries and objects cases: training seed")
    ap.add_argument("--train-args", default="", help="galleries and objects cases: extra `dars train` arguments (quoted)")
    ap.add_argument("--export-only", action="store_true",
                    help="galleries case: keep the runs already in OUT/galleries and only export and score the GLBs")
    ap.add_argument("--export-args", default="", help="galleries case: extra `dars export-asset` arguments (quoted)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=str(ROOT / "bench" / "out"))
    ap.add_argument("--variants", default="both", choices=["both", "full", "nerf"],
                    help="quality cases: train the full model, the --baseline nerf model, or both (default)")
    ap.add_argument("--lego-views", type=int, default=20, help="evaluate Lego on every (100 / N)-th val view")
    args = ap.parse_args()
    out = Path(args.out)
    results: dict = {}

    def pick(variants: dict[str, list[str]]) -> dict[str, list[str]]:
        if args.variants == "both":
            return variants
        return {k: v for k, v in variants.items() if ("--baseline" in v) == (args.variants == "nerf")}

    cases = ["throughput", "tiny", "sample", "lego"] if args.case == "all" else [args.case]
    for c in cases:
        if c == "sample":
            priors = out / "sample" / "priors"     # the light network's estimate, as `make demo` does
            subprocess.run([PY, "-m", "toolkit.cli", "priors", "light", "samples/gallery", "--out", str(priors / "light"),
                            "--force", "--json"], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
            results[c] = case_quality("sample", "samples/gallery", [2, 5, 10], "test", None, args.threads, out,
                                      pick({"full (fast)": ["--priors", str(priors)],
                                            "standard NeRF (fast)": ["--baseline", "nerf"]}))
        elif c == "tiny":
            f = SHARED / "tiny_lego" / "tiny_lego_100.npz"
            if not f.is_file():
                print(f"[tiny] skipped: {f} not present")
                continue
            results[c] = case_quality("tiny", str(f), [3, 5, 10], "test", None, args.threads, out,
                                      pick({"full (fast)": [], "standard NeRF (fast, --baseline nerf)": ["--baseline", "nerf"]}))
        elif c == "lego":
            d = SHARED / "nerf_synthetic" / "lego"
            if not d.is_dir():
                print(f"[lego] skipped: {d} not present")
                continue
            step = max(1, 100 // args.lego_views)
            results[c] = case_quality("lego", str(d), [5, 15], "val", list(range(0, 100, step)), args.threads, out,
                                      pick({"full (fast)": [], "standard NeRF (fast)": ["--baseline", "nerf"]}))
        elif c == "galleries":
            sys.path.insert(0, str(ROOT / "samples"))
            from galleries import VALIDATION_SEEDS

            if args.galleries == "all":
                seeds = list(VALIDATION_SEEDS)
            elif "," in args.galleries or int(args.galleries) in VALIDATION_SEEDS:
                seeds = [int(v) for v in args.galleries.split(",") if v]
                bad = [v for v in seeds if v not in VALIDATION_SEEDS]
                if bad:
                    ap.error(f"--galleries {args.galleries}: {bad} are not validation seeds ({list(VALIDATION_SEEDS)})")
            else:
                seeds = list(VALIDATION_SEEDS)[:int(args.galleries)]
            results[c] = case_galleries(seeds, args.minutes, args.steps, args.threads, out, args.seed,
                                        args.train_args.split(), args.export_only, args.export_args.split())
        elif c == "objects":
            sys.path.insert(0, str(ROOT / "samples"))
            from render_object import MESHES, VALIDATION

            if args.objects == "all":
                objects = list(VALIDATION)
            else:
                objects = []
                for item in (v for v in args.objects.split(",") if v):
                    mesh, _, seed = item.partition(":")
                    if mesh not in MESHES or not seed.isdigit():
                        ap.error(f"--objects {item!r}: expected MESH:SEED with MESH one of {sorted(MESHES)}")
                    objects.append((mesh, int(seed)))
            results[c] = case_objects(objects, args.steps or 2000, args.threads, out, args.seed, args.train_args.split())
        elif c == "throughput":
            results[c] = case_throughput(args.threads, out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"bench_train_{args.case}_{args.variants}.json").write_text(json.dumps(results, indent=2, default=str))
    print(f"\nfigures written to {out / f'bench_train_{args.case}_{args.variants}.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
