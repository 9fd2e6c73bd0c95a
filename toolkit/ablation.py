"""Table 6 — baselines and ablations as switches on one trainer, under one budget and one seed.

:func:`run_ablation` trains the variants of :data:`VARIANTS` one after another into ``OUT/<variant>/`` (ordinary run
directories), evaluates each with :func:`toolkit.evaluate.evaluate_run` (report in ``OUT/<variant>/eval/``) and writes
``OUT/ablation.json`` and ``OUT/ablation.md`` (:func:`toolkit.report.write_ablation_report`). Every variant gets the
same budget (``steps``, or ``minutes`` of wall-clock training each), the same seed, preset and overrides; the view
consistency of every variant is measured on the same surface patch (the scene's, or the one chosen automatically for
the first variant) so the Fig. 8 curves are comparable.

Re-running into the same ``OUT`` reuses finished variants and resumes interrupted ones (``train(resume=True)``); a
variant directory trained with another budget, preset or switches is refused rather than mixed in.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

from ._checks import ConfigError, DarsError
from .outputs import OutputDir

if TYPE_CHECKING:
    from .evaluate import EvalConfig, EvalResult

ABLATION_FILES = ("ablation.json", "ablation.md", "ablation_brightness.png", "ablation_weights.png")
"""What :func:`run_ablation` writes beside the variants' run folders."""

__all__ = ["ABLATION_FILES", "VARIANTS", "VARIANT_LABELS", "VariantResult", "AblationResult", "run_ablation"]

VARIANTS: dict[str, dict] = {
    "full": {},
    "no_dars": {"dars": False},
    "no_semantics": {"semantics": False},
    "fixed_light": {"fixed_light": True},
    "no_mat_loss": {"mat_loss": False},
    "nerf": {"baseline": "nerf"},
}
"""Variant name -> :func:`toolkit.train.make_config` switches (Table 6 rows, in order)."""

VARIANT_LABELS: dict[str, str] = {
    "full": "Full DARS-NeRF",
    "no_dars": "w/o DARS",
    "no_semantics": "w/o semantic guidance",
    "fixed_light": "w/o lighting decoupling (fixed lighting)",
    "no_mat_loss": "w/o material constraint loss",
    "nerf": "Standard NeRF",
}


@dataclass
class VariantResult:
    """One trained and evaluated variant."""

    name: str
    label: str
    run_dir: Path
    evaluation: EvalResult
    reused: bool = False
    wall_seconds: float = 0.0


@dataclass
class AblationResult:
    """The variants of one ablation, in training order (``full`` first when it is included)."""

    scene: str
    out_dir: Path
    preset: str
    steps: int
    minutes: float
    seed: int
    split: str
    variants: list[VariantResult] = field(default_factory=list)
    overrides: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        """The ``ablation.json`` document."""
        from .evaluate import METRIC_KEYS

        full = next((v for v in self.variants if v.name == "full"), None)
        full_doc = full.evaluation.to_json() if full is not None else {}
        items = []
        for v in self.variants:
            doc = v.evaluation.to_json()
            metrics = {k: doc[k] for k in METRIC_KEYS}
            delta = {}
            for k in METRIC_KEYS:
                f = full_doc.get(k)
                delta[k] = None if (metrics[k] is None or f is None) else metrics[k] - f
            vc = doc["details"].get("view_consistency") or {}
            items.append({
                "name": v.name, "label": v.label, "run": str(v.run_dir), "reused": v.reused,
                "wall_seconds": v.wall_seconds,
                "training": {k: doc["training"][k] for k in ("steps", "minutes", "variant", "switches", "priors",
                                                             "albedo_supervision")},
                "metrics": metrics, "unavailable": doc["unavailable"], "delta_vs_full": delta,
                "view_consistency_curve": {k: vc.get(k) for k in ("keys", "render_means", "gt_means", "units", "gt_value")}
                if vc else None,
                "sampling": doc["details"].get("sampling"),
                "eval_report": str(v.run_dir / "eval" / "report.md"),
            })
        return {"scene": self.scene, "preset": self.preset, "budget": {"steps": self.steps, "minutes": self.minutes},
                "seed": self.seed, "split": self.split, "overrides": {k: str(v) for k, v in self.overrides.items()},
                "metric_keys": list(METRIC_KEYS), "variants": items}


def _saved_config(run_dir: Path) -> dict | None:
    from .train.folder import read_run_meta

    if not (run_dir / "checkpoint.pt").is_file() or not (run_dir / "config.json").is_file():
        return None
    return read_run_meta(run_dir)["config"]


def run_ablation(
    scene: str | Path,
    out_dir: str | Path,
    preset: str = "fast",
    minutes: float = 0.0,
    steps: int = 0,
    seed: int = 0,
    variants: Sequence[str] | None = None,
    overrides: dict | None = None,
    eval_cfg: EvalConfig | None = None,
    split: str = "test",
    progress_bar: bool = False,
    log: Callable[[str], None] | None = None,
    priors_root: str | Path | None = None,
) -> AblationResult:
    """Train and evaluate the Table 6 variants under one budget; write ``ablation.json`` and ``ablation.md``.

    Args:
        scene: the scene (as ``dars train`` takes it).
        out_dir: output directory (or a checked :class:`toolkit.outputs.OutputDir`); variant ``v`` trains into
            ``out_dir/v``. A folder that is not new, empty or dars's is refused (:mod:`toolkit.outputs`).
        preset: training preset (``fast`` or ``paper``).
        minutes: wall-clock training budget per variant (exclusive with ``steps``).
        steps: training steps per variant.
        seed: seed of every variant.
        variants: names from :data:`VARIANTS` (default: all six, in Table 6 order).
        overrides: extra :func:`toolkit.train.make_config` overrides applied to every variant (e.g. ``batch_rays``).
        eval_cfg: evaluation options (the patch is fixed across variants, see the module docstring).
        split: split to evaluate.
        progress_bar: training progress bars on stderr.
        log: progress lines (default: stderr).
        priors_root: the prior stages' outputs every variant reads (as ``dars train --priors``; default
            ``<scene>/priors``); variants that switch a prior off ignore it.

    Returns:
        :class:`AblationResult`.

    Raises:
        ConfigError: no budget or both budgets, unknown variant, or an override that is an ablation switch.
        DarsError: a variant directory holds a run with another configuration.
    """
    from .evaluate import EvalConfig, evaluate_run, variant_of
    from .report import write_ablation_report, write_eval_report
    from .train.run import load_run
    from .train import TrainConfig, make_config, train

    log = log or (lambda m: print(m, file=sys.stderr))
    if bool(steps) == bool(minutes):
        raise ConfigError("run_ablation: give exactly one budget, steps=N or minutes=M (the same for every variant)")
    names = list(variants) if variants else list(VARIANTS)
    unknown = [n for n in names if n not in VARIANTS]
    if unknown or not names:
        raise ConfigError(f"run_ablation: unknown variant(s) {unknown}; choose from {list(VARIANTS)}")
    if len(set(names)) != len(names):
        raise ConfigError(f"run_ablation: variants repeat: {names}")
    if "full" in names:  # the reference row is trained first
        names = ["full"] + [n for n in names if n != "full"]
    overrides = dict(overrides or {})
    clash = [k for k in overrides if k in ("dars", "semantics", "fixed_light", "mat_loss", "baseline", "seed", "steps",
                                           "minutes", "shading")]
    if clash:
        raise ConfigError(f"run_ablation: overrides {clash} would change what the variants compare; remove them")
    from .scene import load_scene

    load_scene(scene, "train")  # fail before any training when the scene or the evaluation split is unusable
    if len(load_scene(scene, split)) == 0:
        raise DarsError(f"run_ablation: split '{split}' of {scene} has no views to evaluate")
    folder = out_dir if isinstance(out_dir, OutputDir) else OutputDir(out_dir, "ablate")
    folder.check(list(ABLATION_FILES) + [f"{n}/" for n in names])
    out = folder.path
    folder.begin()
    result = AblationResult(scene=str(scene), out_dir=out, preset=preset, steps=int(steps), minutes=float(minutes),
                            seed=int(seed), split=split, overrides=overrides)
    budget = f"{steps} steps" if steps else f"{minutes:g} min"
    ecfg = EvalConfig() if eval_cfg is None else eval_cfg
    for k, name in enumerate(names, 1):
        label = VARIANT_LABELS[name]
        run_dir = out / name
        cfg = make_config(preset, seed=seed, steps=int(steps), minutes=float(minutes), **overrides, **VARIANTS[name])
        t0 = time.monotonic()
        saved = _saved_config(run_dir)
        reused = saved is not None
        if saved is not None:
            old = TrainConfig.from_dict(saved)
            mismatch = [f for f, a, b in (("variant", variant_of(old), name), ("preset", old.preset, preset),
                                           ("steps", old.steps, int(steps)), ("minutes", old.minutes, float(minutes)),
                                           ("seed", old.seed, seed)) if a != b]
            if mismatch:
                raise DarsError(f"{run_dir} already holds a run with another {', '.join(mismatch)} "
                                f"(variant {variant_of(old)}, {old.steps} steps / {old.minutes:g} min, seed {old.seed}); "
                                "choose another --out so the variants share one budget")
            log(f"[ablate {k}/{len(names)}] {label}: run exists in {run_dir}; resuming/reusing it")
            train(scene, run_dir, cfg, resume=True, progress_bar=progress_bar, log=log, priors_root=priors_root)
        else:
            log(f"[ablate {k}/{len(names)}] {label}: training ({budget}, preset {preset}, seed {seed}) -> {run_dir}")
            train(scene, run_dir, cfg, progress_bar=progress_bar, log=log, priors_root=priors_root)
        run = load_run(run_dir)
        log(f"[ablate {k}/{len(names)}] {label}: trained {run.step} steps in {run.elapsed / 60:.2f} min; evaluating")
        ev = evaluate_run(run, split, ecfg, log=log)
        vc = ev.details.get("view_consistency")
        if vc and ecfg.patch_centre is None and vc["patch"]["source"].startswith("automatic"):
            p = vc["patch"]  # the next variants measure the same automatically chosen patch
            ecfg = replace(ecfg, patch_centre=tuple(p["centre"]), patch_normal=tuple(p["normal"]), patch_size=p["size"],
                           patch_source=f"{p['source']} (chosen for the {label} variant, shared by all)")
        write_eval_report(ev, run_dir / "eval")
        result.variants.append(VariantResult(name, label, run_dir, ev, reused, time.monotonic() - t0))
        m = ev.metrics
        log(f"[ablate {k}/{len(names)}] {label}: PSNR {_f(m['psnr'])} dB, SSIM {_f(m['ssim'])}, "
            f"FLIP {_f(m['flip'])}, view consistency {_f(m['view_consistency'])}")
        del run
    write_ablation_report(result, out)
    folder.finish()
    log(f"[ablate] wrote {out / 'ablation.md'} and {out / 'ablation.json'}")
    return result


def _f(x) -> str:
    return "n/a" if x is None else f"{x:.4g}"
