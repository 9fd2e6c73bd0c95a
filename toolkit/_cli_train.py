"""``dars train`` and ``dars render``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from ._checks import DarsError


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
    q.add_argument("--priors", help="directory holding the prior stages' outputs (default: <scene>/priors)")
    q.add_argument("--no-dars", action="store_true", help="ablation: uniform rays + hierarchical sampling")
    q.add_argument("--no-semantics", action="store_true", help="ablation: no semantic guidance")
    q.add_argument("--fixed-light", action="store_true", help="ablation: l_env fixed at its initial value")
    q.add_argument("--no-mat-loss", action="store_true", help="ablation: no L_mat")
    q.add_argument("--baseline", choices=["nerf"], help="standard NeRF: radiance head, no priors, no DARS")
    q.add_argument("--albedo-supervision", action="store_true",
                   help="use the scene's ground-truth albedo maps in L_mat (eq. 20); makes albedo MAE circular")
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


def _threads(n: int) -> None:
    if n > 0:
        torch.set_num_threads(n)


def cmd_train(args: argparse.Namespace) -> int:
    from .train import make_config, train

    _threads(args.threads)
    if not args.resume and not args.scene:
        raise DarsError("give a SCENE (or --resume an existing run)")
    if not args.resume and not args.minutes and not args.steps:
        raise DarsError("give a training length: --minutes M or --steps N")
    overrides: dict = {"seed": args.seed, "device": args.device, "minutes": args.minutes, "steps": args.steps}
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
               priors_root=args.priors)
    print(f"run: {Path(args.out)}  checkpoint: {ck}")
    return 0


def orbit_cameras(scene, n: int):
    """``n`` cameras on a circle around the scene box centre, looking at it (world up +z), at the mean
    training-camera distance and elevation."""
    from .scene import Cameras

    centre = scene.aabb.mean(0)
    o = scene.cameras.origins
    rel = o - centre
    radius = float(rel[:, :2].norm(dim=-1).mean())
    height = float(rel[:, 2].mean())
    c2ws = []
    for k in range(n):
        a = 2 * np.pi * k / n
        pos = centre + torch.tensor([radius * np.cos(a), radius * np.sin(a), height], dtype=torch.float32)
        fwd = torch.nn.functional.normalize(centre - pos, dim=0)
        right = torch.nn.functional.normalize(torch.linalg.cross(fwd, torch.tensor([0.0, 0, 1])), dim=0)
        up = torch.linalg.cross(right, fwd)
        m = torch.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, -fwd, pos
        c2ws.append(m)
    c = scene.cameras
    rep = lambda t: t[:1].repeat(n)  # noqa: E731
    return Cameras(torch.stack(c2ws), rep(c.fx), rep(c.fy), rep(c.cx), rep(c.cy), rep(c.width), rep(c.height))


def cmd_render(args: argparse.Namespace) -> int:
    from .io import write_png
    from .pipeline import render_image
    from .preview import render_output_images
    from .scene import load_scene
    from .train import load_run
    from tqdm import tqdm

    run = load_run(args.run, args.checkpoint)
    if args.cameras:
        scene = load_scene(args.cameras, "all")
    elif args.orbit:
        scene = None
    else:
        scene = load_scene(run.scene_path, args.split)
    cams = orbit_cameras(run.train_scene, args.orbit) if scene is None else scene.cameras
    keys = [f"orbit_{i:03d}" for i in range(len(cams))] if scene is None else [f.key for f in scene.frames]
    n = len(cams) if not args.limit else min(args.limit, len(cams))
    out = Path(args.out)
    written = []
    for i in tqdm(range(n), desc="render", file=sys.stderr, disable=args.json):
        outs = render_image(run.field, cams, i, run.cfg.render_sampler, run.occupancy, run.l_env, run.background,
                            run.train_scene.aabb, run.cfg.shading, run.dars_for(cams.c2w[i]),
                            near=run.train_scene.near, far=run.train_scene.far, deferred=run.cfg.deferred)
        for name, img in render_output_images(outs, srgb=run.train_scene.srgb).items():
            p = out / f"{keys[i]}_{name}.png"
            write_png(p, img)
            written.append(str(p))
    if args.json:
        print(json.dumps({"views": n, "files": written}))
    else:
        print(f"rendered {n} views ({len(written)} images) into {out}")
    return 0
