"""``dars train`` (the two-stage trainer), ``dars render`` (every decomposed output of a run as images) and
``dars relight`` (re-render with another SH light / HDR probe and per-class material edits)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .._checks import DarsError
from ._common import positive_int, set_threads


def add_parser(sub: argparse._SubParsersAction) -> None:
    q = sub.add_parser("train", help="train the decoupled field on a scene (two-stage, checkpointed)")
    q.add_argument("scene", nargs="?", help="scene (not needed with --resume)")
    q.add_argument("--out", required=True, help="run directory")
    q.add_argument("--preset", default="fast", choices=["fast", "paper"])
    g = q.add_mutually_exclusive_group()
    g.add_argument("--minutes", type=float, default=0.0, help="wall-clock training budget")
    g.add_argument("--steps", type=int, default=0, help="training steps")
    q.add_argument("--resume", action="store_true", help="continue the run in --out")
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--split", default="train")
    q.add_argument("--downscale", type=positive_int, default=1, metavar="N",
                   help="shrink the photos N times on load (default: 1); memory and time fall with N^2. Recorded in "
                        "the run: render, relight and eval use the same size")
    q.add_argument("--priors", help="directory holding the prior stages' outputs (default: <scene>/priors)")
    q.add_argument("--no-dars", action="store_true", help="ablation: uniform rays + hierarchical sampling")
    q.add_argument("--no-semantics", action="store_true", help="ablation: no semantic guidance")
    q.add_argument("--fixed-light", action="store_true", help="ablation: l_env fixed at its initial value")
    q.add_argument("--no-mat-loss", action="store_true", help="ablation: no L_mat")
    q.add_argument("--baseline", choices=["nerf"], help="standard NeRF: radiance head, no priors, no DARS")
    q.add_argument("--albedo-supervision", action="store_true",
                   help="use the scene's ground-truth albedo maps in L_mat (eq. 20); makes albedo MAE circular")
    q.add_argument("--scene-type", default="auto", choices=["auto", "room", "object"],
                   help="room: photos taken inside an enclosed room (walls start as an opaque layer on the box faces "
                        "after stage a); object: transparent start everywhere; auto: room when most cameras are "
                        "inside the scene box and the photos are not RGBA")
    q.add_argument("--snapshots", default="", help="comma-separated minutes at which to save the field, e.g. 2,5,10")
    q.add_argument("--batch-rays", type=int, default=0, help="override rays per step")
    q.add_argument("--device", default="auto", help="auto (CUDA when present), cpu or cuda")
    q.add_argument("--threads", type=int, default=0, help="CPU threads (default: all cores)")
    q.add_argument("--quiet", action="store_true", help="no progress bar")
    q.set_defaults(func=cmd_train)

    q = sub.add_parser("render", help="render test views or a camera path with every decomposed output")
    q.add_argument("run", help="run directory of `dars train`")
    q.add_argument("--out", required=True, help="output directory")
    q.add_argument("--split", default="test", help="split of the run's scene to render")
    q.add_argument("--cameras", help="a transforms JSON whose frames are the camera path (instead of --split)")
    q.add_argument("--orbit", type=int, default=0, help="render N views on an orbit around the scene instead")
    q.add_argument("--checkpoint", help="a snapshot checkpoint instead of the run's last one")
    q.add_argument("--limit", type=int, default=0, help="render at most N views")
    q.add_argument("--json", action="store_true")
    q.set_defaults(func=cmd_render)

    q = sub.add_parser("relight", help="re-render with another SH light / HDR probe and per-class material edits")
    q.add_argument("run", help="run directory of `dars train`")
    g = q.add_mutually_exclusive_group()
    g.add_argument("--probe", help="HDR environment (.hdr/.exr, lat-long in the SPEC convention unless --layout)")
    g.add_argument("--sh", help='JSON with {"coeffs": [[r, g, b] x 9]} (e.g. from `dars priors sh-probe`)')
    q.add_argument("--layout", default="latlong", choices=["latlong", "angular"])
    q.add_argument("--probe-rotate-x", type=float, default=0.0, help="rotate a +y-up probe into +z-up (90)")
    q.add_argument("--intensity", type=float, default=1.0, help="scale the new light")
    q.add_argument("--residual", default="scale", choices=["scale", "keep", "drop"],
                   help="what to do with the learnt local light (shadows): scale with the DC ratio, keep, drop")
    q.add_argument("--edit", action="append", help="material edit CLASS:KEY=VALUE[,...] (repeatable), "
                                                   "e.g. frame:metallic=0,roughness=0.8")
    q.add_argument("--out", required=True)
    q.add_argument("--split", default="test")
    q.add_argument("--cameras")
    q.add_argument("--orbit", type=int, default=0)
    q.add_argument("--checkpoint")
    q.add_argument("--limit", type=int, default=0)
    q.add_argument("--json", action="store_true")
    q.set_defaults(func=cmd_relight)


def cmd_train(args: argparse.Namespace) -> int:
    from ..train import make_config, train

    set_threads(args.threads)
    if not args.resume and not args.scene:
        raise DarsError("give a SCENE (or --resume an existing run)")
    if not args.resume and not args.minutes and not args.steps:
        raise DarsError("give a training length: --minutes M or --steps N")
    overrides: dict = {"seed": args.seed, "device": args.device, "minutes": args.minutes, "steps": args.steps}
    if args.scene_type != "auto":
        overrides["scene_type"] = args.scene_type
    if args.no_dars:
        overrides["dars"] = False
    if args.no_semantics:
        overrides["semantics"] = False
    if args.fixed_light:
        overrides["fixed_light"] = True
    if args.no_mat_loss:
        overrides["mat_loss"] = False
    if args.baseline:
        overrides["baseline"] = args.baseline
    if args.albedo_supervision:
        overrides["albedo_supervision"] = True
    if args.batch_rays:
        overrides["batch_rays"] = args.batch_rays
    if args.snapshots:
        try:
            overrides["snapshot_minutes"] = tuple(float(x) for x in args.snapshots.split(",") if x.strip())
        except ValueError as e:
            raise DarsError(f"--snapshots must be comma-separated minutes, got {args.snapshots!r}") from e
    cfg = make_config(args.preset, **overrides)
    ck = train(args.scene, args.out, cfg, resume=args.resume, split=args.split, progress_bar=not args.quiet,
               priors_root=args.priors, downscale=args.downscale)
    print(f"run: {Path(args.out)}  checkpoint: {ck}")
    return 0


def _cameras_for(args, run):
    """(cameras, file keys) of ``--cameras FILE``, ``--orbit N`` or the run's scene ``--split``."""
    from ..cameras import orbit_cameras
    from ..scene import load_scene

    if getattr(args, "cameras", None):
        scene = load_scene(args.cameras, "all")
    elif getattr(args, "orbit", 0):
        cams = orbit_cameras(run.train_scene.cameras, run.train_scene.aabb, args.orbit)
        return cams, [f"orbit_{i:03d}" for i in range(len(cams))]
    else:
        scene = run.load_split(args.split)
    return scene.cameras, [f.key for f in scene.frames]


def cmd_render(args: argparse.Namespace) -> int:
    from ..train.run import load_run, render_views

    run = load_run(args.run, args.checkpoint)
    cams, keys = _cameras_for(args, run)
    out = Path(args.out)
    n = len(cams) if not args.limit else min(args.limit, len(cams))
    written = render_views(run, cams, keys, out, limit=args.limit, progress=not args.json)
    if args.json:
        print(json.dumps({"views": n, "files": written}))
    else:
        print(f"rendered {n} views ({len(written)} images) into {out}")
    return 0


def cmd_relight(args: argparse.Namespace) -> int:
    import torch

    from ..io import write_json
    from ..relight import parse_material_edit, relight_hook
    from ..train.run import load_run, render_views
    from ..sh import fit_sh_probe, read_envmap, read_sh_json, rotation_x

    if not args.probe and not args.sh and not args.edit:
        raise DarsError("give a new light (--probe HDR or --sh JSON) and/or material edits (--edit CLASS:KEY=VALUE)")
    run = load_run(args.run, args.checkpoint)
    if run.cfg.shading != "pbr":
        raise DarsError(f"{args.run} is a radiance (standard NeRF) run: it has no materials or light to change")
    new_sh = None
    if args.probe:
        env = read_envmap(args.probe)
        rot = rotation_x(args.probe_rotate_x) if args.probe_rotate_x else None
        new_sh = fit_sh_probe(env, layout=args.layout, rotation=rot).coeffs.float()
    elif args.sh:
        new_sh = torch.from_numpy(read_sh_json(args.sh)).float()
    if new_sh is not None:
        new_sh = new_sh * args.intensity
    edits = [parse_material_edit(e) for e in (args.edit or [])]
    hook = relight_hook(run.l_env, new_sh, edits, args.residual)
    cams, keys = _cameras_for(args, run)
    out = Path(args.out)
    n = len(cams) if not args.limit else min(args.limit, len(cams))
    written = render_views(run, cams, keys, out, limit=args.limit, outputs_hook=hook, progress=not args.json)
    write_json(out / "relight.json", {"run": str(args.run), "sh": None if new_sh is None else new_sh.tolist(),
                                      "original_sh": run.l_env.tolist(), "residual": args.residual,
                                      "edits": [e.__dict__ for e in edits]})
    if args.json:
        print(json.dumps({"views": n, "files": written}))
    else:
        print(f"relit {n} views ({len(written)} images) into {out}")
    return 0
