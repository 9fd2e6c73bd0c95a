"""``dars train`` (the two-stage trainer), ``dars render`` (every decomposed output of a run as images) and
``dars relight`` (re-render with another SH light / HDR probe and per-class material edits)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .._checks import DarsError
from ..defaults import DARS_DEFAULT
from ._common import COUNT, FINITE, NONNEGATIVE, POSITIVE, number, set_threads


def add_parser(sub: argparse._SubParsersAction) -> None:
    q = sub.add_parser("train", help="train the decoupled field on a scene (two-stage, checkpointed)")
    q.add_argument("scene", nargs="?", help="scene (not needed with --resume)")
    q.add_argument("--out", required=True, help="run directory (new or empty; see --resume and --force)")
    q.add_argument("--preset", default=None, choices=["fast", "paper"], help="named configuration (default: fast)")
    g = q.add_mutually_exclusive_group()
    g.add_argument("--minutes", type=NONNEGATIVE, default=0.0,
                   help="wall-clock budget: turned into a step count after timing the first steps on this machine "
                        "(logged; --steps N with that count reproduces the run exactly)")
    g.add_argument("--steps", type=COUNT, default=0, help="training steps (every schedule is in steps)")
    q.add_argument("--schedule-knots", default=None, metavar="S:N,...",
                   help="with --steps: replay a --minutes run whose clock re-timed its step count mid-run (the knots "
                        "its log printed: at step S the run had been planned to N steps)")
    q.add_argument("--resume", action="store_true",
                   help="continue the run in --out with its saved scene and settings (--steps/--minutes may extend it)")
    q.add_argument("--force", action="store_true",
                   help="start again in a folder holding a run (replaces its checkpoint, config and log), or write "
                        "into a non-empty folder beside its files (files dars did not write are never touched)")
    q.add_argument("--seed", type=COUNT, default=None, help="random seed (default: 0)")
    q.add_argument("--split", default=None, help="split to train on (default: train)")
    q.add_argument("--downscale", type=POSITIVE, default=1, metavar="N",
                   help="shrink the photos N times on load (default: 1); memory and time fall with N^2. Recorded in "
                        "the run: render, relight, eval and --resume use the same size")
    q.add_argument("--no-upright", action="store_true",
                   help="keep the scene's orientation: a COLMAP model, or a transforms JSON without an aabb that "
                        "`dars poses` did not write, is otherwise rotated on load so that world up is +z. Recorded in "
                        "the run: render, relight, eval and --resume load the scene the same way")
    q.add_argument("--priors", help="directory holding the prior stages' outputs (default: <scene>/priors when it "
                                    "has them; else they are computed from the photos into <out>/priors)")
    q.add_argument("--no-auto-priors", action="store_true",
                   help="do not compute missing priors (segmentation + metal mask, light): train without them")
    sampler = q.add_mutually_exclusive_group()
    sampler.add_argument("--dars", dest="dars", action="store_const", const=True, default=None,
                         help="the paper's distortion-aware sampler: W-weighted rays, per-ray fine budgets, W-guided "
                              "samples along the ray" + (" (the default)" if DARS_DEFAULT else
                                                         " (off by default: uniform sampling measured as good or "
                                                         "better on the validation galleries, README)"))
    sampler.add_argument("--no-dars", dest="dars", action="store_const", const=False,
                         help="uniform rays + hierarchical sampling"
                         + (" (the w/o DARS ablation)" if DARS_DEFAULT else " (the default)"))
    q.add_argument("--no-semantics", action="store_true",
                   help="ablation: no semantic input (no L_semantic, no label edges in W; L_mat keeps its class terms)")
    q.add_argument("--fixed-light", action="store_true", help="ablation: l_env fixed at its initial value")
    q.add_argument("--light-init", default="full", choices=["full", "ambient"],
                   help="how the light prior starts l_env: all 9 SH coefficients (full) or only band 0, its level and "
                        "colour (ambient; the directions are then left to the eq. 22 light stage)")
    q.add_argument("--light-fit", default="auto", choices=["auto", "on", "off"],
                   help="at the switch to stage (b), fit l_env's directional bands to the photos' shading on the "
                        "rendered depth's normals: auto = for an object whose light starts as a grey ambient (RGBA "
                        "photos get no light network estimate), on = always, off = never (README, \"An object's light "
                        "from its shading\")")
    q.add_argument("--no-mat-loss", action="store_true", help="ablation: no L_mat")
    q.add_argument("--light-residual", choices=["rgb", "grey", "off"], default=None,
                   help="the field's per-point light residual Δl(x): one per colour channel (rgb), one shared by the "
                        "channels, which shades but cannot tint (grey), or none (off); default: the preset's (README, "
                        "\"A colour-neutral light residual\")")
    q.add_argument("--sparse-depth", type=NONNEGATIVE, default=None, metavar="W",
                   help="weight of the sparse-depth loss: rays through feature points triangulated from the photos "
                        "and poses end at their depth (default: 0.1 for a room, 0 for an object; 0 = off)")
    q.add_argument("--opacity-loss", type=NONNEGATIVE, default=None, metavar="W",
                   help="weight of the mean (1 - opacity) of each batch's rays: rays end on a surface, not in the "
                        "learned background (default: 0.1 for a room, 0 for an object; never for objects on a "
                        "transparent background)")
    q.add_argument("--depth-normal", type=NONNEGATIVE, default=None, metavar="W",
                   help="weight of the depth-normal loss: the rendered normal follows the normal of the rendered "
                        "depth map (default: 0.5 for a room and an object; 0 = off)")
    q.add_argument("--patch-stride", type=number(int, min=1), default=None, metavar="N",
                   help="photo pixels between the pixels of the training patches (SSIM, depth-normal, albedo "
                        "smoothness; default: L_eikonal's step in pixels, so a patch covers the same length of surface "
                        "at any resolution)")
    q.add_argument("--eikonal", type=NONNEGATIVE, default=None, metavar="W",
                   help="weight of L_eikonal: the normal head follows the density's gradient (default: 0.01 for a "
                        "room, 0.1 for an object, taken over 1/512 and 1/64 of the box; 0 = off)")
    q.add_argument("--eikonal-step", type=number(float, above=0, max=1), default=None, metavar="F",
                   help="central-difference step of L_eikonal's density gradient, as a fraction of the box's mean "
                        "edge (default: 1/512 for a room, 1/64 for an object; a larger step follows the shape, a smaller "
                        "one the texture)")
    q.add_argument("--orientation", type=NONNEGATIVE, default=None, metavar="W",
                   help="weight of the orientation loss (Ref-NeRF): normals may not face away from the camera "
                        "(default: 1.0 for a room, 0.1 for an object; 0 = off)")
    q.add_argument("--planar-loss", type=NONNEGATIVE, default=None, metavar="W",
                   help="weight of the planarity loss: the rendered points of each large textureless region of a "
                        "photo (plain walls, floors) lie on one plane (default: 0 = off; README, \"A planarity prior for "
                        "textureless regions\")")
    q.add_argument("--albedo-smooth", type=NONNEGATIVE, default=None, metavar="W",
                   help="weight of the albedo smoothness prior (Retinex's): neighbouring pixels whose photo barely "
                        "changes share one albedo, so a smooth change of brightness goes to the light (default: "
                        "0.2 for a room, 0 for an object; 0 = off)")
    q.add_argument("--layout-depth", type=NONNEGATIVE, default=None, metavar="W",
                   help="weight of the room-layout loss: rays through the photos' large textureless regions end on "
                        "the room's box, found by a photometric plane sweep before the first step (toolkit.layout; "
                        "default: 0.1 for a room, 0 for an object; 0 = off)")
    q.add_argument("--layout-normal", type=NONNEGATIVE, default=None, metavar="W",
                   help="weight of the room-layout normal loss: the rendered normal of those same pixels is the "
                        "inward normal of the box face their ray leaves through (a wall's horizontal, the floor's "
                        "up; default: 0.1 for a room, 0 for an object; 0 = off)")
    q.add_argument("--shade", choices=["samples", "rays"], default=None,
                   help="where the heads and the PBR shading run: at every sample, shaded colours composited "
                        "(samples), or once per ray on the composited field feature (rays: fewer evaluations a step, "
                        "so more steps in a --minutes budget); default: the preset's (fast: rays for a room, samples for an "
                        "object; paper: samples)")
    q.add_argument("--baseline", choices=["nerf"], help="standard NeRF: radiance head, no priors, no DARS")
    q.add_argument("--albedo-supervision", action="store_true",
                   help="use the scene's ground-truth albedo maps in L_mat (eq. 20); makes albedo MAE circular")
    q.add_argument("--scene-type", default="auto", choices=["auto", "unbounded", "room", "object"],
                   help="unbounded (room is the same): space beyond the scene box is contracted and modelled too — "
                        "rooms, galleries, captures with surroundings; object: an isolated object on a known "
                        "background colour (RGBA with transparency); auto: object when the photos have real "
                        "transparency, else unbounded")
    q.add_argument("--labels", default="predicted", choices=["predicted", "ground-truth", "none"],
                   help="semantic labels and metal masks: predicted by the segmentation prior (default; none when "
                        "`dars priors segment` was not run), the scene's ground-truth maps (experiments only: "
                        "recorded in the run and its reports), or none")
    q.add_argument("--masks", default="auto", choices=["auto", "ignore", "alpha", "off"],
                   help="what the frames' mask_path maps mean: ignore (nerfstudio's meaning) — their 0 pixels "
                        "(people, a tripod, glare) are left out of training and of dars eval's scores; alpha — the "
                        "mask is the photo's alpha (an object captured with masks becomes an object on a white "
                        "background, as RGBA photos are); off — not read; auto (default): alpha when the masks "
                        "outline an object (they keep under half of the photos' borders), else ignore")
    q.add_argument("--snapshots", default="", help="comma-separated minutes at which to save the field, e.g. 2,5,10")
    q.add_argument("--batch-rays", type=COUNT, default=0, help="override rays per step (≥ 16)")
    q.add_argument("--device", default="auto", help="auto (CUDA when present), cpu or cuda")
    q.add_argument("--threads", type=COUNT, default=0, help="CPU threads (default: all cores)")
    q.add_argument("--quiet", action="store_true", help="no progress bar")
    q.set_defaults(func=cmd_train)

    q = sub.add_parser("render", help="render test views or a camera path with every decomposed output")
    q.add_argument("run", help="run directory of `dars train`")
    q.add_argument("--out", required=True, help="output directory")
    q.add_argument("--split", default="test", help="split of the run's scene to render")
    q.add_argument("--cameras", help="a transforms JSON whose frames are the camera path, in the run's world frame "
                                     "(instead of --split)")
    q.add_argument("--orbit", type=COUNT, default=0, help="render N views on an orbit around the scene instead")
    q.add_argument("--checkpoint", help="a snapshot checkpoint instead of the run's last one")
    q.add_argument("--limit", type=COUNT, default=0, help="render at most N views")
    q.add_argument("--force", action="store_true", help="write into a non-empty folder beside its files")
    q.add_argument("--json", action="store_true")
    q.set_defaults(func=cmd_render)

    q = sub.add_parser("relight", help="re-render with another SH light / HDR probe and per-class material edits")
    q.add_argument("run", help="run directory of `dars train`")
    g = q.add_mutually_exclusive_group()
    g.add_argument("--probe", help="HDR environment (.hdr/.exr, lat-long in the SPEC convention unless --layout)")
    g.add_argument("--sh", help='JSON with {"coeffs": [[r, g, b] x 9]} (e.g. from `dars priors sh-probe`)')
    q.add_argument("--layout", default="latlong", choices=["latlong", "angular"])
    q.add_argument("--probe-rotate-x", type=FINITE, default=0.0, help="rotate a +y-up probe into +z-up (90)")
    q.add_argument("--intensity", type=NONNEGATIVE, default=1.0, help="scale the new light")
    q.add_argument("--residual", default="scale", choices=["scale", "keep", "drop"],
                   help="what to do with the learnt local light (shadows): scale with the DC ratio, keep, drop")
    q.add_argument("--edit", action="append", help="material edit CLASS:KEY=VALUE[,...] (repeatable), "
                                                   "e.g. frame:metallic=0,roughness=0.8")
    q.add_argument("--out", required=True)
    q.add_argument("--split", default="test")
    q.add_argument("--cameras")
    q.add_argument("--orbit", type=COUNT, default=0)
    q.add_argument("--checkpoint")
    q.add_argument("--limit", type=COUNT, default=0)
    q.add_argument("--force", action="store_true", help="write into a non-empty folder beside its files")
    q.add_argument("--json", action="store_true")
    q.set_defaults(func=cmd_relight)


_LOSS_OPTIONS = (("opacity-loss", "opacity_loss", "opacity"), ("sparse-depth", "sparse_depth", "sparse_depth"),
                 ("depth-normal", "depth_normal", "depth_normal"), ("planar-loss", "planar_loss", "planar"),
                 ("layout-depth", "layout_depth", "layout_depth"), ("layout-normal", "layout_normal", "layout_normal"),
                 ("orientation", "orientation", "orientation"), ("albedo-smooth", "albedo_smooth", "albedo_smooth"),
                 ("eikonal", "eikonal", "eikonal"), ("eikonal-step", "eikonal_step", "eikonal_step"))
"""Loss-weight options of ``dars train``: (flag, argparse attribute, ``LossWeights`` field); None = by scene type."""

_RESUME_OPTIONS = (
    # (option, args attribute, the saved value of a run (config.json as a dict), the value asked for)
    ("--preset", "preset", lambda m: m["config"].get("preset"), lambda v: v),
    ("--seed", "seed", lambda m: m["config"].get("seed"), lambda v: v),
    ("--split", "split", lambda m: m.get("split", "train"), lambda v: v),
    ("--scene-type", "scene_type", lambda m: m["config"].get("scene_type"), lambda v: None if v == "auto" else v),
    ("sampler", "dars", lambda m: "--dars" if m["config"].get("sampler", {}).get("dars", True) else "--no-dars",
     lambda v: None if v is None else "--dars" if v else "--no-dars"),
    ("--no-semantics", "no_semantics", lambda m: not m["config"].get("semantics", True), lambda v: v or None),
    ("--fixed-light", "fixed_light", lambda m: bool(m["config"].get("fixed_light")), lambda v: v or None),
    ("--light-init", "light_init", lambda m: m["config"].get("light_init", "full"), lambda v: None if v == "full" else v),
    ("--light-fit", "light_fit", lambda m: m["config"].get("light_fit", "off"), lambda v: None if v == "auto" else v),
    ("--no-mat-loss", "no_mat_loss", lambda m: m["config"].get("losses", {}).get("mat", 1.0) == 0, lambda v: v or None),
    ("--baseline", "baseline", lambda m: "nerf" if m["config"].get("shading") == "radiance" else None, lambda v: v),
    ("--albedo-supervision", "albedo_supervision", lambda m: bool(m["config"].get("albedo_supervision")),
     lambda v: v or None),
    ("--batch-rays", "batch_rays", lambda m: m["config"].get("batch_rays"), lambda v: v or None),
    ("--shade", "shade", lambda m: "rays" if m["config"].get("deferred") else "samples", lambda v: v),
    *((f"--{flag}", attr, (lambda m, k=key: m["config"].get("losses", {}).get(k) or 0.0),
       lambda v: None if v is None else float(v))
      for flag, attr, key in _LOSS_OPTIONS),
    ("--patch-stride", "patch_stride", lambda m: m["config"].get("patch_stride", 1), lambda v: v),
    ("--labels", "labels", lambda m: m["config"].get("labels", "predicted"), lambda v: None if v == "predicted" else v),
    ("--masks", "masks", lambda m: m["config"].get("masks", "off"), lambda v: None if v == "auto" else v),
    ("--light-residual", "light_residual", lambda m: _residual_mode(m["config"].get("field", {})), lambda v: v),
)
"""Options that define a run: with ``--resume`` they must match the saved run (only its length may grow)."""


def _residual_mode(field: dict) -> str:
    """``--light-residual`` of a saved run's field config (runs saved before the option: rgb)."""
    if not field.get("light_residual", True):
        return "off"
    return field.get("light_residual_colour", "rgb")


def _check_resume(args: argparse.Namespace) -> None:
    """``--resume`` continues the run as it was started: refuse a SCENE, ``--preset`` ... that differ from it."""
    from ..train.folder import read_run_meta

    out = Path(args.out)
    if not (out / "checkpoint.pt").is_file():
        return  # train() says what is missing
    meta = read_run_meta(out)
    differ = []
    if args.scene and Path(args.scene).resolve() != Path(meta["scene"]).resolve():
        differ.append(f"scene {args.scene} (the run's: {meta['scene']})")
    if args.priors and (meta.get("priors_root") is None
                        or Path(args.priors).resolve() != Path(meta["priors_root"]).resolve()):
        differ.append(f"--priors {args.priors} (the run's: {meta.get('priors_root') or 'the scene priors'})")
    for option, attr, saved, asked in _RESUME_OPTIONS:
        want = asked(getattr(args, attr))
        if want is None:
            continue
        have = saved(meta)
        if want != have:
            shown = "on" if want is True else want
            differ.append(f"{option} {shown} (the run's: {'on' if have is True else 'off' if have is False else have})")
    if differ:
        raise DarsError(f"--resume continues {out} with the settings it was started with, but you asked for "
                        f"{'; '.join(differ)}. Resume without those options (only --steps/--minutes may extend the "
                        f"run), or start a new run with them: another --out, or --force to replace {out}")


def cmd_train(args: argparse.Namespace) -> int:
    set_threads(args.threads)
    if not args.resume and not args.scene:
        raise DarsError("give a SCENE (or --resume an existing run)")
    if not args.resume and not args.minutes and not args.steps:
        raise DarsError("give a training length: --minutes M or --steps N")
    if args.resume and args.force:
        raise DarsError("--resume continues the run in --out and --force starts it again: give one of them")
    if args.schedule_knots and args.resume:
        raise DarsError("--resume continues a run with the schedule knots it has: drop --schedule-knots")
    if args.schedule_knots and not args.steps:
        raise DarsError("--schedule-knots replays a re-timed run: give it with --steps N (both from that run's log)")
    if args.batch_rays and args.batch_rays < 16:
        raise DarsError(f"--batch-rays {args.batch_rays}: give at least 16 rays per step (or leave it out)")
    snapshots = ()
    if args.snapshots:
        try:
            snapshots = tuple(float(x) for x in args.snapshots.split(",") if x.strip())
        except ValueError as e:
            raise DarsError(f"--snapshots must be comma-separated minutes, got {args.snapshots!r}") from e
        if not all(0 < m < float("inf") for m in snapshots):
            raise DarsError(f"--snapshots {args.snapshots}: every milestone must be a positive, finite number of "
                            "minutes")
    if args.scene and not Path(args.scene).exists():
        raise DarsError(f"scene not found: {args.scene}")
    if args.resume:
        _check_resume(args)

    from ..distributed import init_from_env, shutdown
    from ..train import make_config, train

    ddp = init_from_env(args.device)  # launched by torchrun with WORLD_SIZE > 1: data-parallel
    seed = 0 if args.seed is None else args.seed
    overrides: dict = {"seed": seed, "device": args.device, "minutes": args.minutes, "steps": args.steps}
    if args.scene_type != "auto":
        overrides["scene_type"] = args.scene_type
    if args.dars is not None:  # --dars or --no-dars; neither: the default sampler
        overrides["dars"] = args.dars
    if args.no_semantics:
        overrides["semantics"] = False
    if args.fixed_light:
        overrides["fixed_light"] = True
    if args.light_init != "full":
        overrides["light_init"] = args.light_init
    if args.light_fit != "auto":
        overrides["light_fit"] = args.light_fit
    if args.no_mat_loss:
        overrides["mat_loss"] = False
    if args.baseline:
        overrides["baseline"] = args.baseline
    if args.albedo_supervision:
        overrides["albedo_supervision"] = True
    if args.labels != "predicted":
        overrides["labels"] = args.labels
    if args.masks != "auto":
        overrides["masks"] = args.masks
    if args.batch_rays:
        overrides["batch_rays"] = args.batch_rays
    if args.shade is not None:
        overrides["deferred"] = args.shade == "rays"
    if snapshots:
        overrides["snapshot_minutes"] = snapshots
    if args.patch_stride is not None:
        overrides["patch_stride"] = int(args.patch_stride)
    if args.schedule_knots:
        from ..train.config import parse_knots

        overrides["schedule_knots"] = parse_knots(args.schedule_knots)
    cfg = make_config(args.preset or "fast", **overrides)
    from dataclasses import replace

    asked = {key: float(getattr(args, attr)) for _, attr, key in _LOSS_OPTIONS if getattr(args, attr) is not None}
    if asked:
        cfg = replace(cfg, losses=replace(cfg.losses, **asked))
    if args.light_residual == "off":
        cfg = replace(cfg, field=replace(cfg.field, light_residual=False))
    elif args.light_residual is not None:
        cfg = replace(cfg, field=replace(cfg.field, light_residual=True, light_residual_colour=args.light_residual))
    priors = args.priors
    try:
        if not args.resume and priors is None and not args.no_auto_priors and cfg.shading != "radiance":
            priors = _auto_priors(args, ddp)
        ck = train(args.scene, args.out, cfg, resume=args.resume, split=args.split or "train",
                   progress_bar=not args.quiet, priors_root=priors, force=args.force, downscale=args.downscale,
                   upright="off" if args.no_upright else "auto")
    except BaseException:
        shutdown()
        raise
    shutdown(finished=True)
    if ddp is None or ddp.is_main:
        print(f"run: {Path(args.out)}  checkpoint: {ck}")
    return 0


def _auto_priors(args: argparse.Namespace, ddp) -> str | None:
    """``dars train`` without ``--priors``: the scene's own priors when it has them, else the segmentation (labels +
    metal masks) and light priors computed from the photos into ``<out>/priors`` (rank 0 of a data-parallel run; the
    others wait). Returns the priors root to train with (None: the scene's)."""
    from ..outputs import OutputDir
    from ..priors import compute_priors, scene_has_priors
    from ..scene import load_scene
    from ..train.config import resolve_masks
    from ..train.folder import open_run_dir

    scene = load_scene(args.scene, args.split or "train", downscale=args.downscale,
                       upright="off" if args.no_upright else "auto")
    _, scene = resolve_masks(args.masks, scene)  # the priors see what training sees: an object's photos composited
    if scene_has_priors(scene):
        print(f"[dars] using the priors in {Path(args.scene) / 'priors'}", file=sys.stderr)
        return None
    open_run_dir(args.out, False, args.force)  # refuse a folder holding a run before any work
    root = Path(args.out) / "priors"
    if ddp is None or ddp.is_main:
        with OutputDir(args.out, "train", force=args.force).check(["priors/"]).guard() as folder:
            compute_priors(scene, root, force=True)
            folder.finish()
    if ddp is not None:
        ddp.barrier()
    return str(root)


def _views(args):
    """(cameras or None, file keys) of ``--cameras FILE``, ``--orbit N`` (cameras: None until the run is loaded) or
    the run's scene ``--split``; read before the run, so a bad camera file or split fails before any heavy work."""
    from ..scene import load_scene
    from ..train.folder import find_run, run_scene_options

    meta, _ = find_run(args.run, args.checkpoint)
    if args.cameras:  # a camera path is in the run's world frame: never re-oriented on its own
        scene = load_scene(args.cameras, "all", upright="off")
    elif args.orbit:
        return None, [f"orbit_{i:03d}" for i in range(args.orbit)]
    else:
        scene = load_scene(meta["scene"], args.split, **run_scene_options(meta))
    return scene.cameras, [f.key for f in scene.frames]


def _render_out(args, keys: list[str], extra: tuple[str, ...] = ()):
    """The output folder of render / relight, checked for every file the views will write."""
    from ..outputs import OutputDir
    from ..visualise import OUTPUT_NAMES

    n = len(keys) if not args.limit else min(args.limit, len(keys))
    planned = [f"{k}_{name}.png" for k in keys[:n] for name in OUTPUT_NAMES] + list(extra)
    return OutputDir(args.out, args.command, force=args.force).check(planned)


def cmd_render(args: argparse.Namespace) -> int:
    from ..cameras import orbit_cameras
    from ..train.run import load_run, render_views

    cams, keys = _views(args)
    out = _render_out(args, keys)
    run = load_run(args.run, args.checkpoint)
    if cams is None:
        cams = orbit_cameras(run.train_scene.cameras, run.train_scene.aabb, args.orbit)
    n = len(cams) if not args.limit else min(args.limit, len(cams))
    with out:
        written = render_views(run, cams, keys, out.path, limit=args.limit, progress=not args.json)
    if args.json:
        print(json.dumps({"views": n, "files": written}))
    else:
        print(f"rendered {n} views ({len(written)} images) into {out.path}")
    return 0


def cmd_relight(args: argparse.Namespace) -> int:
    import torch

    from ..io import write_json
    from ..cameras import orbit_cameras
    from ..relight import parse_material_edit, relight_hook
    from ..sh import fit_sh_probe, read_envmap, read_sh_json, rotation_x
    from ..train.run import load_run, render_views

    if not args.probe and not args.sh and not args.edit:
        raise DarsError("give a new light (--probe HDR or --sh JSON) and/or material edits (--edit CLASS:KEY=VALUE)")
    new_sh = None  # the light and the edits are read before the run: a bad file fails before any heavy work
    if args.probe:
        env = read_envmap(args.probe)
        rot = rotation_x(args.probe_rotate_x) if args.probe_rotate_x else None
        new_sh = fit_sh_probe(env, layout=args.layout, rotation=rot).coeffs.float()
    elif args.sh:
        new_sh = torch.from_numpy(read_sh_json(args.sh)).float()
    if new_sh is not None:
        new_sh = new_sh * args.intensity
    edits = [parse_material_edit(e) for e in (args.edit or [])]
    cams, keys = _views(args)
    out = _render_out(args, keys, extra=("relight.json",))
    run = load_run(args.run, args.checkpoint)
    if run.cfg.shading != "pbr":
        raise DarsError(f"{args.run} is a radiance (standard NeRF) run: it has no materials or light to change")
    hook = relight_hook(run.l_env, new_sh, edits, args.residual)
    if cams is None:
        cams = orbit_cameras(run.train_scene.cameras, run.train_scene.aabb, args.orbit)
    n = len(cams) if not args.limit else min(args.limit, len(cams))
    with out:
        written = render_views(run, cams, keys, out.path, limit=args.limit, outputs_hook=hook, progress=not args.json)
        write_json(out.path / "relight.json", {"run": str(args.run), "sh": None if new_sh is None else new_sh.tolist(),
                                               "original_sh": run.l_env.tolist(), "residual": args.residual,
                                               "edits": [e.__dict__ for e in edits]})
    if args.json:
        print(json.dumps({"views": n, "files": written}))
    else:
        print(f"relit {n} views ({len(written)} images) into {out.path}")
    return 0
