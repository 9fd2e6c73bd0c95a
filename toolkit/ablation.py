"""Table 6 — baselines and ablations as switches on one trainer, under one budget, over one or several seeds.

:func:`run_ablation` trains every variant of :data:`VARIANTS` with every seed, one run after another (seed by seed,
``full`` first), into ordinary run directories: ``OUT/<variant>/`` with a single seed (the layout of earlier
versions), ``OUT/<variant>/seed_<s>/`` with several. It evaluates each with :func:`toolkit.evaluate.evaluate_run`
(report in ``<run>/eval/``) and writes ``OUT/ablation.json`` and ``OUT/ablation.md``
(:func:`toolkit.report.write_ablation_report`): per-seed figures of each variant, their mean ± sample std over the
seeds, and the paired differences against ``full`` trained with the same seed (:func:`seed_statistics`,
:func:`paired_differences`). Every run gets the same budget — ``steps`` (the default in the documentation: equal
steps) or ``minutes`` of wall-clock training each (then the variants train different step counts, and the report
says so) — the same preset and overrides; the view consistency of every run is measured on the same surface patch
(the scene's, or the one chosen automatically for the first run) so the Fig. 8 curves are comparable.

Re-running into the same ``OUT`` reuses finished runs and resumes interrupted ones (``train(resume=True)``); a run
directory trained with another budget, preset, seed or switches is refused rather than mixed in, and so is a folder
laid out for a different number of seeds.
"""

from __future__ import annotations

import math
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

__all__ = ["ABLATION_FILES", "VARIANTS", "VARIANT_LABELS", "VARIANT_REMOVES", "VariantResult",
           "AblationResult", "run_ablation", "seed_statistics", "paired_differences", "parse_seeds"]

VARIANTS: dict[str, dict] = {
    "full": {"dars": True},
    "no_dars": {"dars": False},
    "no_semantics": {"dars": True, "semantics": False},
    "fixed_light": {"dars": True, "fixed_light": True},
    "no_mat_loss": {"dars": True, "mat_loss": False},
    "nerf": {"baseline": "nerf"},
}
"""Variant name -> :func:`toolkit.train.make_config` switches (Table 6 rows, in order). What each removes:
:data:`VARIANT_REMOVES`. The full model is the paper's, DARS on, and every variant but ``no_dars`` and ``nerf`` keeps
DARS, whatever ``dars train``'s default sampler (:data:`toolkit.defaults.DARS_DEFAULT`)."""

VARIANT_LABELS: dict[str, str] = {
    "full": "Full DARS-NeRF",
    "no_dars": "w/o DARS",
    "no_semantics": "w/o semantic input",
    "fixed_light": "w/o lighting decoupling (fixed lighting)",
    "no_mat_loss": "w/o material constraint loss",
    "nerf": "Standard NeRF",
}

VARIANT_REMOVES: dict[str, str] = {
    "full": "nothing: every part on",
    "no_dars": "DARS: rays are drawn uniformly over the pixels and every ray gets the same fine samples "
               "(hierarchical sampling), in training and in rendering",
    "no_semantics": "the semantic input only: no L_semantic (the semantic head is unsupervised, so mIoU is n/a) and no "
                    "label edge term E in W (W = G + M, computed at training time instead of the `dars priors weights` "
                    "maps); L_mat keeps its class terms (painting roughness, metallic target), which still read the "
                    "labels, and the metal mask still enters W",
    "fixed_light": "the lighting stage: l_env stays at its initial value (no l_env steps, eq. 22)",
    "no_mat_loss": "L_mat entirely (eq. 20: painting roughness, metallic target and, when on, the albedo term); the "
                   "labels still supervise the semantic head and shape W",
    "nerf": "the decomposition: radiance head, stratified + hierarchical samples, no priors, no DARS, no L_mat, "
            "no room prior",
}
"""What each variant of :data:`VARIANTS` turns off (documented in the report; see also ``TrainConfig.semantics`` and
``TrainConfig.mat_labels``). Runs made before ``no_semantics`` and L_mat's class terms were separate switches are
named ``no_semantics_legacy`` by :func:`toolkit.evaluate.variant_of` and are not reused for ``no_semantics``."""

"""Metrics whose per-seed figures, mean ± std and paired differences the report tabulates (``ablation.json`` has
them for every metric)."""


STAT_TITLES = {"psnr": "PSNR", "ssim": "SSIM", "albedo_mae": "albedo MAE", "roughness_rmse": "roughness RMSE",
               "normal_mae": "normal MAE", "miou": "mIoU"}


def _finite(x) -> bool:
    return x is not None and isinstance(x, (int, float)) and math.isfinite(x)


def seed_statistics(values: Sequence[float | None]) -> dict:
    """Mean and sample standard deviation (n − 1) of one metric over seeds; ``None`` values (unavailable) are left
    out.

    Args:
        values: the metric per seed, in seed order (``None`` where unavailable).

    Returns:
        ``{"values": [...], "n": count of numbers, "mean": float | None, "std": float | None}``; ``std`` is
        ``None`` below two numbers, ``mean`` is ``None`` with none.

    Example:
        >>> seed_statistics([1.0, 2.0, None, 3.0])
        {'values': [1.0, 2.0, None, 3.0], 'n': 3, 'mean': 2.0, 'std': 1.0}
    """
    xs = [float(v) for v in values if _finite(v)]
    n = len(xs)
    mean = sum(xs) / n if n else None
    std = math.sqrt(sum((x - mean) ** 2 for x in xs) / (n - 1)) if n >= 2 else None
    return {"values": [float(v) if _finite(v) else None for v in values], "n": n, "mean": mean, "std": std}


def paired_differences(values: Sequence[float | None], reference: Sequence[float | None]) -> dict:
    """Per-seed differences ``values[i] − reference[i]`` (the same seed) and their :func:`seed_statistics`.

    Args:
        values: a variant's metric per seed.
        reference: the full model's metric for the same seeds, in the same order.

    Returns:
        :func:`seed_statistics` of the differences (``values`` = the per-seed differences, ``None`` where either is
        unavailable) plus ``within_seed_noise``: ``|mean| < std`` (``None`` below two pairs).

    Raises:
        ValueError: the two lists differ in length.

    Example:
        >>> d = paired_differences([30.0, 31.0, 29.0], [29.5, 30.0, 29.5])
        >>> d["values"], round(d["mean"], 3), round(d["std"], 3), d["within_seed_noise"]
        ([0.5, 1.0, -0.5], 0.333, 0.764, True)
    """
    if len(values) != len(reference):
        raise ValueError(f"paired_differences: {len(values)} values against {len(reference)} reference values")
    diffs = [float(a) - float(b) if _finite(a) and _finite(b) else None for a, b in zip(values, reference)]
    st = seed_statistics(diffs)
    st["within_seed_noise"] = None if st["std"] is None else bool(abs(st["mean"]) < st["std"])
    return st


def parse_seeds(text: str) -> list[int]:
    """``"0,1,2"`` -> ``[0, 1, 2]`` (non-negative, distinct, at least one).

    Raises:
        ConfigError: not a comma-separated list of distinct non-negative integers.
    """
    try:
        seeds = [int(t) for t in str(text).replace(" ", "").split(",") if t != ""]
    except ValueError:
        raise ConfigError(f"seeds {text!r}: give a comma-separated list of integers, e.g. 0,1,2") from None
    if not seeds or any(s < 0 for s in seeds) or len(set(seeds)) != len(seeds):
        raise ConfigError(f"seeds {text!r}: give distinct non-negative integers, e.g. 0,1,2")
    return seeds


@dataclass
class VariantResult:
    """One trained and evaluated run: a variant with one seed."""

    name: str
    label: str
    run_dir: Path
    evaluation: EvalResult
    reused: bool = False
    wall_seconds: float = 0.0
    seed: int = 0


@dataclass
class AblationResult:
    """The runs of one ablation, in training order (seed by seed; ``full`` first when it is included)."""

    scene: str
    out_dir: Path
    preset: str
    steps: int
    minutes: float
    seed: int
    """The first seed (the only one of a single-seed ablation)."""
    split: str
    variants: list[VariantResult] = field(default_factory=list)
    """Every run (variant × seed)."""
    overrides: dict = field(default_factory=dict)
    seeds: list[int] = field(default_factory=list)
    """Every seed, in training order (default: ``[seed]``)."""

    def __post_init__(self):
        if not self.seeds:
            self.seeds = [self.seed]

    def names(self) -> list[str]:
        """Variant names in training order."""
        return list(dict.fromkeys(v.name for v in self.variants))

    def first_seed_runs(self) -> list[VariantResult]:
        """One run per variant — the first seed's — for the figures."""
        first = {}
        for v in self.variants:
            first.setdefault(v.name, v)
        return list(first.values())

    def to_json(self) -> dict:
        """The ``ablation.json`` document.

        Per variant: ``runs`` (one entry per seed: its metrics, training facts, inputs, difference to ``full`` with the
        same seed), ``per_seed`` (metric -> values in seed order), ``summary`` (metric -> :func:`seed_statistics`),
        ``paired_vs_full`` (metric -> :func:`paired_differences` against ``full``; absent without ``full``),
        ``within_seed_noise`` (the :data:`toolkit.report.STAT_KEYS` whose ``|mean paired difference| < std``), ``noise_note`` (that
        as a sentence). ``metrics`` and ``delta_vs_full`` are the means over seeds (with one seed: that run's values);
        ``run``, ``training``, ``view_consistency_curve``, ``sampling`` and ``eval_report`` are the first seed's.
        """
        from .evaluate import METRIC_KEYS

        by = {(v.name, v.seed): v for v in self.variants}
        full_metrics = {}
        for s in self.seeds:
            if ("full", s) in by:
                doc = by[("full", s)].evaluation.to_json()
                full_metrics[s] = {k: doc[k] for k in METRIC_KEYS}
        items = []
        for name in self.names():
            runs = [by[(name, s)] for s in self.seeds if (name, s) in by]
            run_docs = [_run_doc(v, full_metrics.get(v.seed)) for v in runs]
            seeds = [v.seed for v in runs]
            per_seed = {k: [r["metrics"][k] for r in run_docs] for k in METRIC_KEYS}
            summary = {k: seed_statistics(per_seed[k]) for k in METRIC_KEYS}
            paired = None
            if all(s in full_metrics for s in seeds) and full_metrics:
                paired = {k: paired_differences(per_seed[k], [full_metrics[s][k] for s in seeds]) for k in METRIC_KEYS}
            first = run_docs[0]
            unavailable = {}
            for r in run_docs:
                for k, why in r["unavailable"].items():
                    unavailable.setdefault(k, why)
            noisy = [] if paired is None or name == "full" else [k for k in _stat_keys() if paired[k]["within_seed_noise"]]
            items.append({
                "name": name, "label": VARIANT_LABELS.get(name, name), "removes": VARIANT_REMOVES.get(name, ""),
                "seeds": seeds, "run": first["run"], "reused": all(r["reused"] for r in run_docs),
                "wall_seconds": sum(r["wall_seconds"] for r in run_docs),
                "training": first["training"],
                "metrics": {k: summary[k]["mean"] for k in METRIC_KEYS},
                "unavailable": unavailable,
                "delta_vs_full": {k: None if paired is None else paired[k]["mean"] for k in METRIC_KEYS},
                "view_consistency_curve": first["view_consistency_curve"],
                "sampling": first["sampling"], "eval_report": first["eval_report"],
                "runs": run_docs, "per_seed": per_seed, "summary": summary, "paired_vs_full": paired,
                "within_seed_noise": noisy, "noise_note": _noise_note(name, paired, noisy),
            })
        budget = {"steps": self.steps, "minutes": self.minutes}
        if self.minutes and not self.steps:
            budget["warning"] = WALL_CLOCK_WARNING
        return {"scene": self.scene, "preset": self.preset, "budget": budget,
                "seed": self.seed, "seeds": list(self.seeds), "split": self.split,
                "layout": "OUT/<variant>/" if len(self.seeds) == 1 else "OUT/<variant>/seed_<s>/",
                "overrides": {k: str(v) for k, v in self.overrides.items()},
                "metric_keys": list(METRIC_KEYS), "stat_keys": list(_stat_keys()),
                "statistics": "mean ± sample standard deviation (n − 1) over seeds; paired differences are variant − "
                              "full with the same seed",
                "inputs": _inputs_summary(items), "variants": items}


WALL_CLOCK_WARNING = ("wall-clock budget: every run trained the same minutes, so the variants trained different numbers "
                      "of steps (each run's `training.steps`); a difference mixes the variant's effect with its speed "
                      "and the machine's load. Compare at equal steps (--steps N).")


def _stat_keys() -> tuple[str, ...]:
    """The metrics that get seed statistics (:data:`toolkit.report.STAT_KEYS`; imported here, not at module level,
    so ``dars --help`` stays free of numpy)."""
    from .report import STAT_KEYS

    return STAT_KEYS


def _noise_note(name: str, paired: dict | None, noisy: list[str]) -> str:
    if name == "full" or paired is None:
        return ""
    n = max((paired[k]["n"] for k in _stat_keys()), default=0)
    if n < 2:
        return "one seed: no estimate of seed noise, so no difference can be called significant or not."
    if not noisy:
        return (f"every available paired difference to the full model is larger than its spread over {n} seeds "
                "(|mean| ≥ std).")
    return (f"the differences to the full model in {', '.join(STAT_TITLES[k] for k in noisy)} are within seed noise "
            f"(|mean paired difference| < its std over {n} seeds).")


def _run_inputs(run_dir: Path, training: dict) -> dict:
    """Which inputs of a run were ground truth: ``labels`` from its ``config.json``, the recorded prior sources."""
    from .train.folder import read_run_meta

    cfg = read_run_meta(run_dir)["config"]
    labels = cfg.get("labels")
    priors = training.get("priors") or {}
    gt = []
    if labels == "ground-truth" or priors.get("labels") == "provided":
        gt.append("semantic labels")
    if labels == "ground-truth" or priors.get("metal") == "provided":
        gt.append("metal masks")
    if training.get("albedo_supervision"):
        gt.append("albedo maps (L_mat)")
    return {"labels": labels if labels is not None else "not recorded (run predates --labels)",
            "labels_source": priors.get("labels"), "metal_source": priors.get("metal"),
            "labels_used_by": priors.get("labels_used_by"),
            "albedo_supervision": bool(training.get("albedo_supervision")), "ground_truth": gt}


def _run_doc(v: VariantResult, full_metrics: dict | None) -> dict:
    from .evaluate import METRIC_KEYS

    doc = v.evaluation.to_json()
    metrics = {k: doc[k] for k in METRIC_KEYS}
    delta = {k: None if (full_metrics is None or not _finite(metrics[k]) or not _finite(full_metrics.get(k)))
             else metrics[k] - full_metrics[k] for k in METRIC_KEYS}
    vc = doc["details"].get("view_consistency") or {}
    training = {k: doc["training"][k] for k in ("steps", "field_steps", "minutes", "variant", "switches", "priors",
                                               "albedo_supervision")}
    return {"seed": v.seed, "run": str(v.run_dir), "reused": v.reused, "wall_seconds": v.wall_seconds,
            "training": training, "inputs": _run_inputs(v.run_dir, training),
            "metrics": metrics, "unavailable": doc["unavailable"], "delta_vs_full": delta,
            "view_consistency_curve": {k: vc.get(k) for k in ("keys", "render_means", "gt_means", "units", "gt_value")}
            if vc else None,
            "sampling": doc["details"].get("sampling"),
            "eval_report": str(v.run_dir / "eval" / "report.md")}


def _inputs_summary(items: list[dict]) -> dict:
    """Which runs were trained with which label setting and which ground truth, over the whole ablation."""
    labels = sorted({str(r["inputs"]["labels"]) for it in items for r in it["runs"]})
    gt = sorted({g for it in items for r in it["runs"] for g in r["inputs"]["ground_truth"]})
    return {"labels": labels, "ground_truth": gt}


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
    seed: int | None = None,
    variants: Sequence[str] | None = None,
    overrides: dict | None = None,
    eval_cfg: EvalConfig | None = None,
    split: str = "test",
    progress_bar: bool = False,
    log: Callable[[str], None] | None = None,
    priors_root: str | Path | None = None,
    seeds: Sequence[int] | None = None,
) -> AblationResult:
    """Train and evaluate the Table 6 variants under one budget, for one or several seeds; write ``ablation.json``
    and ``ablation.md``.

    Args:
        scene: the scene (as ``dars train`` takes it).
        out_dir: output directory (or a checked :class:`toolkit.outputs.OutputDir`); variant ``v`` trains into
            ``out_dir/v`` with one seed, ``out_dir/v/seed_<s>`` with several. A folder that is not new, empty or
            dars's is refused (:mod:`toolkit.outputs`).
        preset: training preset (``fast`` or ``paper``).
        minutes: wall-clock training budget per run (exclusive with ``steps``; the variants then train different
            step counts, which the report says).
        steps: training steps per run (equal steps: the budget to compare variants with).
        seed: the one seed of every variant (exclusive with ``seeds``; default 0).
        variants: names from :data:`VARIANTS` (default: all six, in Table 6 order).
        overrides: extra :func:`toolkit.train.make_config` overrides applied to every variant (e.g. ``batch_rays``).
        eval_cfg: evaluation options (the patch is fixed across runs, see the module docstring).
        split: split to evaluate.
        progress_bar: training progress bars on stderr.
        log: progress lines (default: stderr).
        priors_root: the prior stages' outputs every variant reads (as ``dars train --priors``; default
            ``<scene>/priors``); variants that switch a prior off ignore it.
            ``overrides={"device": ...}`` picks where every variant trains; it is evaluated on the same device.
        seeds: several seeds: every variant is trained once per seed (exclusive with ``seed``).

    Returns:
        :class:`AblationResult`.

    Raises:
        ConfigError: no budget or both budgets, both ``seed`` and ``seeds``, bad seeds, unknown variant, or an override
            that is an ablation switch.
        DarsError: a run directory holds a run with another configuration, or the folder is laid out for another
            number of seeds.
    """
    from .evaluate import EvalConfig, evaluate_run, variant_of
    from .report import write_ablation_report, write_eval_report
    from .train.run import load_run
    from .train import TrainConfig, make_config, train
    from .train.step import train_device

    log = log or (lambda m: print(m, file=sys.stderr))
    if bool(steps) == bool(minutes):
        raise ConfigError("run_ablation: give exactly one budget, steps=N or minutes=M (the same for every variant)")
    if seed is not None and seeds is not None:
        raise ConfigError("run_ablation: give seed=S or seeds=[...], not both")
    seed_list = [0 if seed is None else int(seed)] if seeds is None else [int(x) for x in seeds]
    if not seed_list or min(seed_list) < 0 or len(set(seed_list)) != len(seed_list):
        raise ConfigError(f"run_ablation: seeds {list(seed_list)}: give distinct non-negative integers, e.g. [0, 1, 2]")
    multi = len(seed_list) > 1
    names = list(variants) if variants else list(VARIANTS)
    unknown = [n for n in names if n not in VARIANTS]
    if unknown or not names:
        raise ConfigError(f"run_ablation: unknown variant(s) {unknown}; choose from {list(VARIANTS)}")
    if len(set(names)) != len(names):
        raise ConfigError(f"run_ablation: variants repeat: {names}")
    if "full" in names:  # the reference row is trained first
        names = ["full"] + [n for n in names if n != "full"]
    overrides = dict(overrides or {})
    clash = [k for k in overrides if k in ("dars", "semantics", "mat_labels", "fixed_light", "mat_loss", "baseline",
                                           "seed", "steps", "minutes", "shading")]
    if clash:
        raise ConfigError(f"run_ablation: overrides {clash} would change what the variants compare; remove them")
    from .scene import load_scene

    load_scene(scene, "train")  # fail before any training when the scene or the evaluation split is unusable
    if len(load_scene(scene, split)) == 0:
        raise DarsError(f"run_ablation: split '{split}' of {scene} has no views to evaluate")
    folder = out_dir if isinstance(out_dir, OutputDir) else OutputDir(out_dir, "ablate")
    folder.check(list(ABLATION_FILES) + [f"{n}/" for n in names])
    out = folder.path
    for n in names:  # one layout per folder: a single-seed run is not the parent of per-seed runs, nor the reverse
        vdir = out / n
        if multi and ((vdir / "config.json").is_file() or (vdir / "checkpoint.pt").is_file()):
            raise DarsError(f"{vdir} holds a single-seed run; several seeds train into {vdir}/seed_<s>/. "
                            "Choose another --out for a multi-seed ablation")
        if not multi and vdir.is_dir() and any(p.is_dir() for p in vdir.glob("seed_*")):
            raise DarsError(f"{vdir} holds per-seed runs (seed_<s>/); rerun with the same --seeds or choose "
                            "another --out")
    folder.begin()
    result = AblationResult(scene=str(scene), out_dir=out, preset=preset, steps=int(steps), minutes=float(minutes),
                            seed=seed_list[0], split=split, overrides=overrides, seeds=seed_list)
    budget = f"{steps} steps" if steps else f"{minutes:g} min"
    ecfg = EvalConfig() if eval_cfg is None else eval_cfg
    total = len(names) * len(seed_list)
    k = 0
    for s in seed_list:
        for name in names:
            k += 1
            label = VARIANT_LABELS[name]
            tag = f"[ablate {k}/{total}] {label}" + (f" (seed {s})" if multi else "")
            run_dir = out / name / f"seed_{s}" if multi else out / name
            cfg = make_config(preset, seed=s, steps=int(steps), minutes=float(minutes), **overrides, **VARIANTS[name])
            t0 = time.monotonic()
            saved = _saved_config(run_dir)
            reused = saved is not None
            if saved is not None:
                old = TrainConfig.from_dict(saved)
                mismatch = [f for f, a, b in (("variant", variant_of(old), name), ("preset", old.preset, preset),
                                               ("steps", old.steps, int(steps)), ("minutes", old.minutes, float(minutes)),
                                               ("seed", old.seed, s), ("labels", old.labels, cfg.labels)) if a != b]
                if mismatch:
                    why = (" — a run made before 'no semantic input' and 'no L_mat' were separate switches"
                           if variant_of(old) == "no_semantics_legacy" else "")
                    raise DarsError(f"{run_dir} already holds a run with another {', '.join(mismatch)} "
                                    f"(variant {variant_of(old)}{why}, {old.steps} steps / {old.minutes:g} min, "
                                    f"seed {old.seed}, labels {old.labels}); choose another --out so the variants "
                                    "share one budget")
                log(f"{tag}: run exists in {run_dir}; resuming/reusing it")
                train(scene, run_dir, cfg, resume=True, progress_bar=progress_bar, log=log, priors_root=priors_root)
            else:
                log(f"{tag}: training ({budget}, preset {preset}, seed {s}) -> {run_dir}")
                train(scene, run_dir, cfg, progress_bar=progress_bar, log=log, priors_root=priors_root)
            run = load_run(run_dir, device=str(train_device(cfg)))
            log(f"{tag}: trained {run.step} steps in {run.elapsed / 60:.2f} min; evaluating")
            ev = evaluate_run(run, split, ecfg, log=log)
            vc = ev.details.get("view_consistency")
            if vc and ecfg.patch_centre is None and vc["patch"]["source"].startswith("automatic"):
                p = vc["patch"]  # the next runs measure the same automatically chosen patch
                ecfg = replace(ecfg, patch_centre=tuple(p["centre"]), patch_normal=tuple(p["normal"]),
                               patch_size=p["size"],
                               patch_source=f"{p['source']} (chosen for the {label} variant, shared by all)")
            write_eval_report(ev, run_dir / "eval")
            result.variants.append(VariantResult(name, label, run_dir, ev, reused, time.monotonic() - t0, s))
            m = ev.metrics
            log(f"{tag}: PSNR {_f(m['psnr'])} dB, SSIM {_f(m['ssim'])}, "
                f"FLIP {_f(m['flip'])}, view consistency {_f(m['view_consistency'])}")
            del run
    write_ablation_report(result, out)
    folder.finish()
    log(f"[ablate] wrote {out / 'ablation.md'} and {out / 'ablation.json'}")
    return result


def _f(x) -> str:
    return "n/a" if x is None else f"{x:.4g}"
