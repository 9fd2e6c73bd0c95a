"""``dars eval`` (metrics + report of one run) and ``dars ablate`` (Table 6 under one budget, one or several seeds)."""

from __future__ import annotations

import argparse
from pathlib import Path

from .._checks import DarsError
from ._common import COUNT, eval_device, log, number, print_json, set_threads

EVAL_FILES = ("metrics.json", "report.md", "curves.png", "weights.png", "brightness.png", "test_grid.png")
"""What ``dars eval`` writes (:func:`toolkit.report.write_eval_report`)."""


def add_parser(sub: argparse._SubParsersAction) -> None:
    q = sub.add_parser("eval", help="metrics (PSNR, SSIM, FLIP, LPIPS, materials, light, view consistency, ...) "
                                    "and a Markdown report of a run")
    q.add_argument("run", help="run directory of `dars train`")
    q.add_argument("--split", default="test", help="split of the run's scene to evaluate (default: test)")
    q.add_argument("--json", action="store_true", help="print only the metrics JSON on stdout")
    q.add_argument("--limit", type=COUNT, default=0, help="evaluate at most N views, evenly spaced (default: all)")
    q.add_argument("--lpips-weights", help="LPIPS weight file(s)/folder (else $DARS_LPIPS_WEIGHTS; else LPIPS is null)")
    q.add_argument("--reference-mesh", help="mesh file in the scene's frame: adds the Chamfer distance")
    q.add_argument("--mesh-resolution", type=number(int, min=8, max=4096), default=128,
                   help="marching-cubes cells for the Chamfer mesh")
    q.add_argument("--lux-factor", type=number(float, above=0),
                   help="lux per unit of linear luminance (view consistency in lux)")
    q.add_argument("--checkpoint", help="a snapshot checkpoint instead of the run's last one")
    q.add_argument("--out", help="output directory (default: RUN/eval)")
    q.add_argument("--force", action="store_true", help="write into a non-empty folder beside its files")
    q.add_argument("--threads", type=COUNT, default=0, help="CPU threads (default: all cores)")
    q.add_argument("--device", default="auto",
                   help="auto (CUDA when present), cpu or cuda[:N]: where the run is loaded and rendered")
    q.add_argument("--quiet", action="store_true", help="no progress bar")
    q.set_defaults(func=cmd_eval)

    q = sub.add_parser("ablate", help="train and evaluate the Table 6 variants under one budget, over one or "
                                      "several seeds (mean ± std, paired differences against the full model)")
    q.add_argument("scene", help="scene directory or file")
    q.add_argument("--out", required=True, help="output directory (one run per variant and seed: OUT/VARIANT/ with "
                                                "one seed, OUT/VARIANT/seed_S/ with several; ablation.json/.md)")
    q.add_argument("--preset", default="fast", choices=["fast", "paper"])
    g = q.add_mutually_exclusive_group(required=True)
    g.add_argument("--minutes", type=number(float, above=0), default=0.0,
                   help="wall-clock training budget per run (the variants then train different step counts)")
    g.add_argument("--steps", type=number(int, min=1), default=0,
                   help="training steps per run (equal steps: the budget to compare variants with)")
    s = q.add_mutually_exclusive_group()
    s.add_argument("--seed", type=COUNT, default=None, help="the one seed of every variant (default 0)")
    s.add_argument("--seeds", type=_seed_list, default=None,
                   help="comma-separated seeds, e.g. 0,1,2: every variant once per seed")
    from ..ablation import VARIANTS  # imports nothing heavy

    q.add_argument("--variants", nargs="+", type=_variant_list, action="extend", metavar="VARIANTS",
                   help=f"subset of variants, comma- or space-separated (default: all six: {','.join(VARIANTS)}; "
                        "no-dars is no_dars); no_semantics removes the semantic input (L_semantic, label edges in W), "
                        "no_mat_loss removes L_mat")
    q.add_argument("--split", default="test", help="split to evaluate")
    q.add_argument("--limit", type=COUNT, default=0, help="evaluate at most N views per variant")
    q.add_argument("--lpips-weights", help="LPIPS weight file(s)/folder")
    q.add_argument("--batch-rays", type=COUNT, default=0, help="override rays per step (every variant; ≥ 16)")
    q.add_argument("--labels", default="predicted", choices=("predicted", "ground-truth", "none"),
                   help="label and metal-mask source of every variant, as dars train --labels (default: predicted, "
                        "the segmentation prior's; the report lists which inputs were ground truth)")
    q.add_argument("--priors", help="directory holding the prior stages' outputs, as dars train --priors "
                                    "(default: <scene>/priors when it has them, else computed from the photos once "
                                    "into OUT/priors)")
    q.add_argument("--force", action="store_true", help="write into a non-empty folder beside its files")
    q.add_argument("--threads", type=COUNT, default=0, help="CPU threads (default: all cores)")
    q.add_argument("--device", default="auto",
                   help="auto (CUDA when present), cpu or cuda[:N]: every variant trains and is evaluated there")
    q.add_argument("--json", action="store_true", help="print only ablation.json on stdout")
    q.add_argument("--quiet", action="store_true", help="no progress bars")
    q.set_defaults(func=cmd_ablate)


def _seed_list(text: str) -> list[int]:
    from ..ablation import parse_seeds
    from .._checks import ConfigError

    try:
        return parse_seeds(text)
    except ConfigError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def cmd_eval(args: argparse.Namespace) -> int:
    from ..outputs import OutputDir
    from ..train.folder import find_run

    set_threads(args.threads)
    run_dir = Path(args.run)
    if not run_dir.is_dir():
        raise DarsError(f"{run_dir} is not a directory; give the output directory of `dars train SCENE --out RUN`")
    if args.reference_mesh and not Path(args.reference_mesh).is_file():
        raise DarsError(f"--reference-mesh {args.reference_mesh}: file not found")
    if args.lpips_weights and not Path(args.lpips_weights).exists():
        raise DarsError(f"--lpips-weights {args.lpips_weights}: not found (give the LPIPS weight file(s) or their "
                        "folder, or leave the option out: LPIPS is then reported as unavailable)")
    find_run(run_dir, args.checkpoint)
    device = eval_device(args.device)
    option = "--out" if args.out else "the default output folder (RUN/eval; --out picks another)"
    out = OutputDir(args.out or run_dir / "eval", "eval", force=args.force, option=option).check(EVAL_FILES)

    from ..evaluate import EvalConfig, evaluate_run
    from ..report import headline_text, write_eval_report
    from ..train.run import load_run

    cfg = EvalConfig(limit=args.limit, lpips_weights=args.lpips_weights, reference_mesh=args.reference_mesh,
                     mesh_resolution=args.mesh_resolution, lux_factor=args.lux_factor, progress=not (args.quiet or args.json))
    run = load_run(run_dir, args.checkpoint, device=device)
    result = evaluate_run(run, args.split, cfg, log=log)
    with out:
        written = write_eval_report(result, out.path)
    doc = result.to_json()
    if args.json:
        print_json(doc)
        return 0
    print(f"{run_dir} — split '{args.split}', {doc['eval']['views']} views, step {doc['eval']['checkpoint_step']}")
    print(headline_text(doc, doc["unavailable"]))
    if doc["details"].get("object_psnr") is not None:
        print(f"object alone (alpha >= 0.5, without the plain background): PSNR {doc['details']['object_psnr']:.2f} dB")
    print(f"wrote {written['metrics']} and {written['report']}")
    return 0


def _variant_list(text: str) -> list[str]:
    """argparse type of ``--variants``: comma-separated names, ``no-dars`` for ``no_dars``."""
    from ..ablation import VARIANTS

    names = [t.strip().replace("-", "_") for t in text.split(",") if t.strip()]
    bad = [n for n in names if n not in VARIANTS]
    if bad or not names:
        raise argparse.ArgumentTypeError(f"unknown variant(s) {bad or [text]}: choose from {', '.join(VARIANTS)}")
    return names


def flat_variants(values: list[list[str]]) -> list[str]:
    """``--variants full,no-dars`` and ``--variants full no_dars`` alike: one flat list, each name once, in order."""
    return list(dict.fromkeys(v for part in values for v in part))


def _priors_of_split(root: Path, split: str) -> bool:
    """``root/priors.json`` exists and was computed from ``split``'s photos (priors an earlier ``dars ablate``
    computed from another split are computed again)."""
    from ..io import read_json

    try:
        doc = read_json(root / "priors.json", "priors record")
    except DarsError:  # missing or unreadable: computed again
        return False
    return str(doc.get("split")) == split


def cmd_ablate(args: argparse.Namespace) -> int:
    from ..ablation import ABLATION_FILES, VARIANTS
    from ..outputs import OutputDir
    from ..train.folder import check_priors_root

    set_threads(args.threads)
    if args.variants:
        args.variants = flat_variants(args.variants)
    if not (args.steps or args.minutes):
        raise DarsError("give a positive training budget per variant: --steps N or --minutes M")
    if args.batch_rays and args.batch_rays < 16:
        raise DarsError(f"--batch-rays {args.batch_rays}: give at least 16 rays per step (or leave it out)")
    if not Path(args.scene).exists():
        raise DarsError(f"scene not found: {args.scene}")
    check_priors_root(args.priors)
    variants = args.variants or list(VARIANTS)
    out = OutputDir(args.out, "ablate", force=args.force).check(list(ABLATION_FILES) + [f"{v}/" for v in variants]
                                                                 + ["priors/"])

    from ..ablation import run_ablation
    from ..evaluate import EvalConfig
    from ..report import ablation_text

    overrides: dict = {"device": args.device}  # as dars train: always passed, "auto" being the config's default
    if args.batch_rays:
        overrides["batch_rays"] = args.batch_rays
    if args.labels != "predicted":
        overrides["labels"] = args.labels
    priors = args.priors
    with out.guard():
        if priors is None:  # as dars train: the scene's priors, else computed once from the photos for every variant
            from ..priors import compute_priors, scene_has_priors
            from ..scene import load_scene

            # the training photos (as dars train), never the evaluated split: --split names the views to score
            scene = load_scene(args.scene, "train")
            if not scene_has_priors(scene):
                out.begin()  # the folder and its manifest (listing priors/) before the priors are written
                priors = str(out.path / "priors")
                if not _priors_of_split(Path(priors), "train"):
                    compute_priors(scene, priors, force=True)
        res = run_ablation(args.scene, out, preset=args.preset, minutes=args.minutes, steps=args.steps,
                           seed=None if args.seeds else (args.seed or 0), seeds=args.seeds,
                           variants=args.variants, overrides=overrides,
                           eval_cfg=EvalConfig(limit=args.limit, lpips_weights=args.lpips_weights), split=args.split,
                           progress_bar=not (args.quiet or args.json), log=log, priors_root=priors)
    doc = res.to_json()
    if args.json:
        print_json(doc)
        return 0
    print(ablation_text(doc))
    print(f"wrote {Path(args.out) / 'ablation.md'} and {Path(args.out) / 'ablation.json'}")
    return 0
