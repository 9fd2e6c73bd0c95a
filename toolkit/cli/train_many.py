"""``dars train-many MANIFEST --out DIR``: a whole museum — every scene of a manifest through poses, priors, train,
eval and export-asset, resumable, with a summary table (:mod:`toolkit.museum`)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .._checks import DarsError
from ._common import COUNT, POSITIVE


def add_parser(sub: argparse._SubParsersAction) -> None:
    q = sub.add_parser(
        "train-many", help="a museum in one command: every scene of a manifest through poses, priors, train, eval and "
                           "export-asset (resumable; summary table)",
        description="Run every scene of MANIFEST (a JSON or YAML list of scenes, or {defaults, scenes}) through "
                    "poses (a folder of photos) -> priors -> train -> eval -> export-asset into DIR/<name>/, and write "
                    "DIR/summary.json and DIR/summary.md (steps, PSNR, asset size, time per scene). Run it again "
                    "after an interruption: finished stages are skipped (detected from their outputs), an "
                    "interrupted training continues from its checkpoint. Scene fields: name; scene or photos; steps "
                    "or minutes; preset; seed; priors (default [weights]); nproc (data-parallel training through "
                    "torchrun); poses_args, train_args, eval_args, asset_args (lists of extra options); priors_args "
                    "({stage: [options]}).")
    q.add_argument("manifest", help="JSON or YAML manifest of the scenes")
    q.add_argument("--out", required=True, help="output folder (new, empty, or an earlier train-many's: resumed)")
    q.add_argument("--jobs", type=POSITIVE, default=1, help="scenes at once, each in its own processes (default: 1)")
    q.add_argument("--gpus", default="", help="comma-separated GPU ids: each running scene gets one "
                                              "(CUDA_VISIBLE_DEVICES), e.g. --jobs 4 --gpus 0,1,2,3")
    q.add_argument("--threads", type=COUNT, default=0, help="CPU threads of each training and evaluation (default: all)")
    q.add_argument("--dry-run", action="store_true", help="list the stages each scene would run or skip, run nothing")
    q.add_argument("--force", action="store_true", help="write into a non-empty folder beside its files")
    q.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    q.set_defaults(func=cmd_train_many)


def cmd_train_many(args: argparse.Namespace) -> int:
    from ..museum import read_manifest, run_museum, scene_stages
    from ..outputs import OutputDir

    jobs = read_manifest(args.manifest)  # every entry checked before any work
    gpus = [g.strip() for g in args.gpus.split(",") if g.strip()] or None
    out_path = Path(args.out)
    if args.dry_run:
        plan = {j.name: [{"stage": s.name, "run": s.argv is not None, "command": s.argv}
                         for s in scene_stages(j, out_path / j.name, args.threads)] for j in jobs}
        if args.json:
            print(json.dumps(plan, indent=2))
        else:
            for name, stages in plan.items():
                print(f"{name}: " + ", ".join(f"{s['stage']} ({'run' if s['run'] else 'done'})" for s in stages))
        return 0
    out = OutputDir(out_path, "train-many", force=args.force).check(["summary.json", "summary.md"]
                                                                     + [f"{j.name}/" for j in jobs])
    log = (lambda m: print(m, file=sys.stderr))
    with out:
        rows = run_museum(jobs, out.path, args.jobs, args.threads, gpus, log)
    failed = [r["name"] for r in rows if r["status"] != "done"]
    if args.json:
        print(json.dumps({"scenes": rows}, indent=2))
    else:
        print((out.path / "summary.md").read_text(), end="")
        print(f"summary: {out.path / 'summary.json'}, {out.path / 'summary.md'}")
    if failed:
        raise DarsError(f"{len(failed)} of {len(rows)} scenes failed ({', '.join(failed)}); their logs are in "
                        f"{out.path}/<name>/logs/; fix the cause and run the same command again (finished stages "
                        "are skipped)")
    return 0
