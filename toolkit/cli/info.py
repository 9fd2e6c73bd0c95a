"""``dars info`` (what a scene holds) and ``dars contact-sheet`` (a PNG grid of its images and maps)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ._common import POSITIVE, SCENE_HELP, print_json


def add_parser(sub: argparse._SubParsersAction) -> None:
    q = sub.add_parser("info", help="frames per split, image size, intrinsics, bounds, ground truth")
    q.add_argument("scene", help=SCENE_HELP)
    q.add_argument("--json", action="store_true", help="machine-readable output on stdout")
    q.set_defaults(func=cmd_info)

    q = sub.add_parser("contact-sheet", help="a PNG grid of images and their ground-truth maps")
    q.add_argument("scene")
    q.add_argument("--split", default="train")
    q.add_argument("--out", required=True, help="output PNG")
    q.add_argument("-n", type=POSITIVE, default=6, help="number of views")
    q.add_argument("--force", action="store_true", help="replace --out if it exists")
    q.set_defaults(func=cmd_contact_sheet)


def cmd_info(args: argparse.Namespace) -> int:
    from ..scene import scene_info

    info = scene_info(args.scene)
    if args.json:
        print_json(info)
        return 0
    print(f"scene     {info['scene']}  ({info['format']})")
    for s, d in info["splits"].items():
        gt = ", ".join(d["ground_truth"]) or "none"
        print(f"  {s:<6} {d['frames']:>4} frames  {d['image_size'][0]}x{d['image_size'][1]} px   ground truth: {gt}")
    k = info["intrinsics"]
    print(f"intrinsics fx={k['fx']:.2f} fy={k['fy']:.2f} cx={k['cx']:.2f} cy={k['cy']:.2f} "
          f"({'shared' if k['shared'] else 'per frame'}{', undistorted on load' if k['distortion'] else ''})")
    lo, hi = info["aabb"]
    print(f"bounds    [{lo[0]:.2f}, {lo[1]:.2f}, {lo[2]:.2f}] .. [{hi[0]:.2f}, {hi[1]:.2f}, {hi[2]:.2f}] m")
    if info["near_far"]:
        print(f"near/far  {info['near_far'][0]} / {info['near_far'][1]}")
    print(f"GT light  {'SH (27 coefficients)' if info['sh'] else 'none'}"
          f"{'; env map ' + info['envmap'] if info['envmap'] else ''}")
    up = info.get("upright")
    if up:
        tilt = f"tilted {up['tilt_deg']:.1f} deg (world up from {up['source']})" if up["tilt_deg"] is not None else ""
        print("upright   " + (f"rotated to +z up: input {tilt}" if up["applied"] else
                               f"input frame kept: {up.get('kept') or tilt + ', within tolerance'}"))
    return 0


def cmd_contact_sheet(args: argparse.Namespace) -> int:
    from ..outputs import check_output_file
    from ..scene import load_scene
    from ..visualise import contact_sheet

    path = check_output_file(args.out, args.force, suffixes=(".png",))
    scene = load_scene(args.scene, args.split)
    out = contact_sheet(scene, path, n=args.n)
    print(f"wrote {out}")
    return 0
