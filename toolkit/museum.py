"""A museum in one command (``dars train-many MANIFEST --out DIR``): every scene of a manifest through poses (when
the scene is a folder of photos) → priors → train → eval → export-asset, resumable, with a summary table.

Each stage runs as its own ``dars`` command in a subprocess (``python -m toolkit.cli ...``; data-parallel training
through ``torchrun`` when the scene asks for ``nproc`` > 1), so a stage's memory is returned when it ends, a failing
scene does not stop the others, and every stage keeps its own safety checks. Scenes run one after another, or
``jobs`` at a time (each in its own processes; with ``gpus`` every running scene gets one GPU through
``CUDA_VISIBLE_DEVICES``).

Layout of ``DIR``::

    DIR/summary.json, DIR/summary.md        one row per scene: status, steps, PSNR, asset size, time
    DIR/<name>/scene/                       dars poses output (only for a folder of photos)
    DIR/<name>/priors/<stage>/              dars priors STAGE outputs
    DIR/<name>/run/                         dars train (run/eval/: dars eval)
    DIR/<name>/asset/                       dars export-asset (scene.glb)
    DIR/<name>/logs/<stage>.log             each stage's output
    DIR/<name>/stages.json                  seconds spent per stage (accumulated over resumes)

Resume: a stage is skipped when its outputs are complete — ``transforms.json`` for poses; for the other stages the
folder's ``dars_manifest.json`` with every file it lists present, plus: the run's checkpoint at the requested steps
(else ``dars train --resume`` extends it), the evaluation of that checkpoint's step, an asset newer than the
checkpoint. An interrupted stage is run again (``--resume`` for poses and training, which continue from their last
checkpoint).

The manifest (JSON, or YAML when PyYAML is installed): a list of scenes, or ``{"defaults": {...}, "scenes": [...]}``
whose defaults apply to every scene. Fields of a scene (:data:`FIELDS`): ``name``; ``scene`` (a scene path) or
``photos`` (a folder of photos); ``steps`` or ``minutes``; ``preset``; ``seed``; ``priors`` (stage names, default
``["weights"]``); ``nproc``; and extra command-line options per stage: ``poses_args``, ``train_args``,
``eval_args``, ``asset_args`` (lists of strings), ``priors_args`` (``{stage: [...]}``). Relative paths are relative
to the manifest's folder.
"""

from __future__ import annotations

import json
import os
import queue
import re
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from ._checks import DarsError

__all__ = ["SceneJob", "read_manifest", "run_museum", "scene_stages", "write_summary", "FIELDS", "PRIOR_STAGES"]

PRIOR_STAGES = ("segment", "weights", "light", "colour", "layout")
"""The prior stages a scene may ask for, in the order they run (weights use the segment labels; ``layout`` is the room's
box, which ``dars train --layout-depth W`` reads instead of fitting it again)."""

FIELDS = {"name": "a folder name", "scene": "a scene path", "photos": "a folder of photos",
          "steps": "a whole number > 0", "minutes": "a number > 0", "preset": "fast or paper",
          "seed": "a whole number ≥ 0", "priors": "a list of prior stages", "nproc": "a whole number ≥ 1",
          "poses_args": "a list of strings", "train_args": "a list of strings", "eval_args": "a list of strings",
          "asset_args": "a list of strings", "priors_args": "a mapping {stage: [strings]}"}
"""Manifest fields of a scene and what each must be."""

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,99}$")


@dataclass(frozen=True)
class SceneJob:
    """One scene of a manifest, checked (see the module docstring for the fields)."""

    name: str
    scene: str | None = None
    photos: str | None = None
    steps: int = 0
    minutes: float = 0.0
    preset: str = "fast"
    seed: int = 0
    priors: tuple[str, ...] = ("weights",)
    nproc: int = 1
    poses_args: tuple[str, ...] = ()
    train_args: tuple[str, ...] = ()
    eval_args: tuple[str, ...] = ()
    asset_args: tuple[str, ...] = ()
    priors_args: dict = field(default_factory=dict)


# ============================================================================ the manifest
def _load_document(path: Path) -> Any:
    if not path.is_file():
        raise DarsError(f"manifest not found: {path} (give a JSON or YAML list of scenes)")
    text = path.read_text(encoding="utf-8")
    if path.suffix.lower() in (".yaml", ".yml"):
        try:
            import yaml
        except ImportError as e:
            raise DarsError(f"{path} is YAML but PyYAML is not installed: `pip install pyyaml`, or write the "
                            "manifest as JSON") from e
        try:
            return yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise DarsError(f"manifest {path} is not valid YAML: {str(e).splitlines()[0]}") from e
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise DarsError(f"manifest {path} is not valid JSON: {e.msg} at line {e.lineno}, column {e.colno}") from e


def _check_entry(entry: Any, where: str, base: Path) -> SceneJob:
    if not isinstance(entry, dict):
        raise DarsError(f"{where}: expected a mapping of fields (name, scene or photos, steps ...), got "
                        f"{type(entry).__name__}")
    unknown = sorted(set(entry) - set(FIELDS))
    if unknown:
        raise DarsError(f"{where}: unknown field(s) {', '.join(map(repr, unknown))}; the fields are "
                        f"{', '.join(FIELDS)}")

    def bad(key: str, value: Any) -> DarsError:
        return DarsError(f"{where}: field '{key}' must be {FIELDS[key]}, got {value!r}")

    kw: dict = {}
    has = [k for k in ("scene", "photos") if entry.get(k) is not None]
    if len(has) != 1:
        raise DarsError(f"{where}: give exactly one of 'scene' (a scene: transforms JSON, COLMAP model ...) or "
                        f"'photos' (a folder of photos, posed with `dars poses`); got "
                        f"{' and '.join(has) if has else 'neither'}")
    for key in has:
        if not isinstance(entry[key], str) or not entry[key]:
            raise bad(key, entry[key])
        p = Path(entry[key]).expanduser()
        p = p if p.is_absolute() else base / p
        if not p.exists():
            raise DarsError(f"{where}: field '{key}': {p} not found")
        if key == "photos" and not p.is_dir():
            raise DarsError(f"{where}: field 'photos': {p} is not a folder of photos")
        kw[key] = str(p.resolve())
    name = entry.get("name", Path(kw.get("scene") or kw["photos"]).name)
    if not isinstance(name, str) or not _NAME.match(name):
        raise DarsError(f"{where}: field 'name' must be a folder name (letters, digits, '_', '-', '.'), got "
                        f"{name!r}" + ("" if "name" in entry else " (taken from the path: give a 'name')"))
    kw["name"] = name
    for key in ("steps", "seed", "nproc"):
        if key in entry:
            v = entry[key]
            low = {"steps": 1, "seed": 0, "nproc": 1}[key]
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise bad(key, v)
            kw[key] = v
    if "minutes" in entry:
        v = entry["minutes"]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < float("inf"):
            raise bad("minutes", v)
        kw["minutes"] = float(v)
    if ("steps" in kw) == ("minutes" in kw):
        raise DarsError(f"{where}: give a training length: exactly one of 'steps' or 'minutes'"
                        + (" (both given)" if "steps" in kw else ""))
    if "preset" in entry:
        if entry["preset"] not in ("fast", "paper"):
            raise bad("preset", entry["preset"])
        kw["preset"] = entry["preset"]
    if "priors" in entry:
        pri = entry["priors"]
        if not isinstance(pri, list) or not all(isinstance(s, str) for s in pri):
            raise bad("priors", pri)
        wrong = [s for s in pri if s not in PRIOR_STAGES]
        if wrong:
            raise DarsError(f"{where}: field 'priors': unknown stage(s) {', '.join(map(repr, wrong))}; the stages "
                            f"are {', '.join(PRIOR_STAGES)}")
        kw["priors"] = tuple(s for s in PRIOR_STAGES if s in pri)
    for key in ("poses_args", "train_args", "eval_args", "asset_args"):
        if key in entry:
            v = entry[key]
            if not isinstance(v, list) or not all(isinstance(s, (str, int, float)) for s in v):
                raise bad(key, v)
            kw[key] = tuple(str(s) for s in v)
    if "priors_args" in entry:
        v = entry["priors_args"]
        if not isinstance(v, dict) or not all(k in PRIOR_STAGES and isinstance(a, list) for k, a in v.items()):
            raise bad("priors_args", v)
        kw["priors_args"] = {k: [str(s) for s in a] for k, a in v.items()}
    return SceneJob(**kw)


def read_manifest(path: str | os.PathLike) -> list[SceneJob]:
    """The scenes of a manifest, checked.

    Raises:
        DarsError: unreadable, not a list of scenes, or a bad entry — naming the entry (number and name) and field.
    """
    path = Path(path)
    doc = _load_document(path)
    defaults: dict = {}
    if isinstance(doc, dict):
        extra = sorted(set(doc) - {"defaults", "scenes"})
        if extra or "scenes" not in doc:
            raise DarsError(f"manifest {path}: expected a list of scenes or {{\"defaults\": {{...}}, \"scenes\": "
                            f"[...]}}; got the key(s) {', '.join(map(repr, sorted(doc)))}")
        defaults = doc.get("defaults") or {}
        if not isinstance(defaults, dict):
            raise DarsError(f"manifest {path}: 'defaults' must be a mapping of fields, got {type(defaults).__name__}")
        unknown = sorted(set(defaults) - set(FIELDS) - {"name", "scene", "photos"})
        if unknown or {"name", "scene", "photos"} & set(defaults):
            raise DarsError(f"manifest {path}: 'defaults' may not hold {', '.join(map(repr, unknown or ['name/scene/photos']))}")
        doc = doc["scenes"]
    if not isinstance(doc, list) or not doc:
        raise DarsError(f"manifest {path}: expected a non-empty list of scenes, got "
                        f"{'an empty list' if doc == [] else type(doc).__name__}")
    jobs, seen = [], {}
    for i, entry in enumerate(doc, 1):
        label = entry.get("name") if isinstance(entry, dict) else None
        where = f"manifest {path}, entry {i}" + (f" ({label!r})" if label else "")
        merged = {**defaults, **entry} if isinstance(entry, dict) else entry
        if isinstance(entry, dict) and "steps" in entry and "minutes" in defaults:
            merged.pop("minutes")
        if isinstance(entry, dict) and "minutes" in entry and "steps" in defaults:
            merged.pop("steps")
        job = _check_entry(merged, where, path.parent)
        if job.name in seen:
            raise DarsError(f"{where}: field 'name': {job.name!r} is also entry {seen[job.name]}; every scene needs "
                            "its own name (its output folder)")
        seen[job.name] = i
        jobs.append(job)
    return jobs


# ============================================================================ stages and their outputs
def _manifest_complete(folder: Path) -> bool:
    """Whether ``folder`` holds a finished dars output: its manifest lists files and all of them are there."""
    try:
        doc = json.loads((folder / "dars_manifest.json").read_text())
    except (OSError, ValueError):
        return False
    files = doc.get("files") or []
    return bool(files) and all((folder / f.rstrip("/")).exists() for f in files)


def _checkpoint_step(run: Path) -> int:
    """The step of a run's checkpoint (0: none)."""
    ck = run / "checkpoint.pt"
    if not ck.is_file():
        return 0
    import torch

    try:
        return int(torch.load(ck, map_location="cpu", weights_only=False)["step"])
    except Exception:  # noqa: BLE001 - a damaged checkpoint: the run starts again
        return -1


def _target_steps(job: SceneJob, run: Path) -> int:
    """The steps the run must reach: ``steps``, or the count a ``minutes`` budget was calibrated to (0: unknown)."""
    if job.steps:
        return job.steps
    try:
        meta = json.loads((run / "config.json").read_text())
        return int(meta["config"].get("steps") or 0)
    except (OSError, ValueError, KeyError):
        return 0


def _scene_path(job: SceneJob, home: Path) -> str:
    return job.scene if job.scene else str(home / "scene")


def _dars(*args: str) -> list[str]:
    return [sys.executable, "-m", "toolkit.cli", *args]


@dataclass
class Stage:
    """One command of a scene's chain: ``argv`` to run, or None when its outputs are complete (skipped)."""

    name: str
    argv: list[str] | None
    why: str = ""


def scene_stages(job: SceneJob, home: Path, threads: int = 0) -> list[Stage]:
    """The stages of ``job`` whose outputs live in ``home`` (``DIR/<name>``), each with the command that (re)does it,
    or None when it is done. Stages after one that must run are always run (their inputs change)."""
    stages: list[Stage] = []
    th = ["--threads", str(threads)] if threads else []
    scene = _scene_path(job, home)
    later = False  # an earlier stage runs: everything after it is redone
    if job.photos:
        sdir = home / "scene"
        done = (sdir / "transforms.json").is_file()
        resume = ["--resume"] if (sdir / "dars_manifest.json").is_file() and not done else []
        later = not done
        stages.append(Stage("poses", None if done else
                            _dars("poses", job.photos, "--out", str(sdir), *resume, *th, "--quiet", *job.poses_args),
                            "transforms.json written" if done else ""))
    for s in job.priors:
        out = home / "priors" / s
        done = _manifest_complete(out) and not later
        later = later or not done
        extra = list(job.priors_args.get(s, []))
        if s == "layout" and "--no-upright" in job.train_args and "--no-upright" not in extra:
            extra.append("--no-upright")  # the box must be fitted in the frame training loads
        stages.append(Stage(f"priors-{s}", None if done else
                            _dars("priors", s, scene, "--out", str(out), "--force", *extra),
                            "complete" if done else ""))
    run = home / "run"
    step, target = _checkpoint_step(run), _target_steps(job, run)
    length = ["--steps", str(job.steps)] if job.steps else ["--minutes", f"{job.minutes:g}"]
    done = step > 0 and target > 0 and step >= target and not later
    if done:
        argv = None
    elif step > 0 and not later:
        argv = ["train", "--resume", "--out", str(run), *length, *th, "--quiet"]
    else:
        pri = ["--priors", str(home / "priors")] if job.priors else []
        argv = ["train", scene, "--out", str(run), *length, "--preset", job.preset, "--seed", str(job.seed), *pri,
                *th, "--quiet", "--force", *job.train_args]
    if argv is not None and job.nproc > 1:
        argv = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(job.nproc),
                "-m", "toolkit.cli", *argv]
    elif argv is not None:
        argv = _dars(*argv)
    later = later or not done
    stages.append(Stage("train", argv, f"checkpoint at step {step}" if done else ""))
    metrics = run / "eval" / "metrics.json"
    done = not later and _manifest_complete(run / "eval") and _eval_step(metrics) == step
    later = later or not done
    stages.append(Stage("eval", None if done else _dars("eval", str(run), "--quiet", *th, *job.eval_args),
                        "metrics of this checkpoint" if done else ""))
    asset = home / "asset"
    done = (not later and _manifest_complete(asset) and (asset / "mesh_stats.json").is_file()
            and (asset / "mesh_stats.json").stat().st_mtime >= (run / "checkpoint.pt").stat().st_mtime)
    stages.append(Stage("export-asset", None if done else
                        _dars("export-asset", str(run), "--out", str(asset), *job.asset_args),
                        "scene.glb of this checkpoint" if done else ""))
    return stages


def _eval_step(metrics: Path) -> int:
    try:
        return int(json.loads(metrics.read_text())["eval"]["checkpoint_step"])
    except (OSError, ValueError, KeyError, TypeError):
        return -1


# ============================================================================ running
def _read_times(home: Path) -> dict:
    try:
        return json.loads((home / "stages.json").read_text())
    except (OSError, ValueError):
        return {}


def _write_times(home: Path, times: dict) -> None:
    from .io import write_json

    write_json(home / "stages.json", times)


def run_scene(job: SceneJob, out: Path, threads: int = 0, env: dict | None = None,
              log: Callable[[str], None] = print) -> dict:
    """Run ``job``'s stages that are not done (see :func:`scene_stages`); returns its summary row."""
    home = out / job.name
    (home / "logs").mkdir(parents=True, exist_ok=True)
    times = _read_times(home)
    row: dict = {"name": job.name, "status": "done", "ran": [], "skipped": []}
    cwd = Path(__file__).resolve().parents[1]  # the checkout holding toolkit/, for `python -m toolkit.cli`
    penv = dict(os.environ if env is None else env)
    penv["PYTHONPATH"] = str(cwd) + (os.pathsep + penv["PYTHONPATH"] if penv.get("PYTHONPATH") else "")
    # stages are listed again after each run: what a stage writes decides whether the next is done
    for i in range(len(scene_stages(job, home, threads))):
        stage = scene_stages(job, home, threads)[i]
        if stage.argv is None:
            row["skipped"].append(stage.name)
            log(f"[train-many] {job.name}: {stage.name} done ({stage.why}), skipped")
            continue
        log(f"[train-many] {job.name}: {stage.name} ...")
        t0 = time.monotonic()
        with open(home / "logs" / f"{stage.name}.log", "a") as f:
            f.write(f"$ {' '.join(stage.argv)}\n")
            f.flush()
            rc = subprocess.run(stage.argv, cwd=cwd, env=penv, stdout=f, stderr=subprocess.STDOUT).returncode
        dt = time.monotonic() - t0
        times[stage.name] = round(times.get(stage.name, 0.0) + dt, 2)
        _write_times(home, times)
        if rc != 0:
            tail = (home / "logs" / f"{stage.name}.log").read_text(errors="replace").strip().splitlines()[-3:]
            row.update(status="failed", failed_stage=stage.name, exit_code=rc,
                       error=" | ".join(tail)[-500:], log=str(home / "logs" / f"{stage.name}.log"))
            log(f"[train-many] {job.name}: {stage.name} FAILED (exit {rc}); see {row['log']}")
            break
        row["ran"].append(stage.name)
        log(f"[train-many] {job.name}: {stage.name} done in {dt:.1f} s")
    row.update(_scene_figures(home))
    row["seconds"] = round(sum(times.values()), 1)
    row["stage_seconds"] = times
    return row


def _scene_figures(home: Path) -> dict:
    run = home / "run"
    fig: dict = {"steps": max(0, _checkpoint_step(run)) or None, "psnr": None, "asset_bytes": None}
    try:
        fig["psnr"] = json.loads((run / "eval" / "metrics.json").read_text()).get("psnr")
    except (OSError, ValueError):
        pass
    try:
        fig["asset_bytes"] = int(json.loads((home / "asset" / "mesh_stats.json").read_text())["glb_bytes"])
    except (OSError, ValueError, KeyError, TypeError):
        pass
    try:
        fig["world_size"] = json.loads((run / "config.json").read_text()).get("world_size", 1)
    except (OSError, ValueError):
        pass
    return fig


def write_summary(out: Path, rows: list[dict]) -> tuple[Path, Path]:
    """``summary.json`` and ``summary.md`` (a table: scene, status, steps, PSNR, asset size, time) in ``out``."""
    from .io import write_json

    write_json(out / "summary.json", {"scenes": rows})
    lines = ["| scene | status | steps | PSNR (dB) | asset (MB) | time (min) |", "|---|---|---:|---:|---:|---:|"]
    for r in rows:
        status = r["status"] if r["status"] != "failed" else f"failed at {r.get('failed_stage')}"
        psnr = "–" if r.get("psnr") is None else f"{r['psnr']:.2f}"
        size = "–" if r.get("asset_bytes") is None else f"{r['asset_bytes'] / 1e6:.2f}"
        lines.append(f"| {r['name']} | {status} | {r.get('steps') or '–'} | {psnr} | {size} | "
                     f"{r.get('seconds', 0) / 60:.1f} |")
    md = out / "summary.md"
    from .outputs import atomic_write

    with atomic_write(md, "w") as f:
        f.write("\n".join(lines) + "\n")
    return out / "summary.json", md


def run_museum(jobs: list[SceneJob], out: str | os.PathLike, jobs_at_once: int = 1, threads: int = 0,
               gpus: list[str] | None = None, log: Callable[[str], None] = print) -> list[dict]:
    """Run every scene (``jobs_at_once`` in parallel, each with one of ``gpus`` when given) into ``out``; write the
    summary after each scene; returns the summary rows in manifest order."""
    out = Path(out)
    rows: dict[str, dict] = {}
    slots: queue.Queue = queue.Queue()
    for g in (gpus or [None]) * max(1, jobs_at_once):
        slots.put(g)

    def one(job: SceneJob) -> dict:
        gpu = slots.get()
        try:
            env = dict(os.environ)
            if gpu is not None:
                env["CUDA_VISIBLE_DEVICES"] = gpu
            row = run_scene(job, out, threads, env, log)
        finally:
            slots.put(gpu)
        rows[job.name] = row
        write_summary(out, [rows[j.name] for j in jobs if j.name in rows])
        return row

    if jobs_at_once <= 1:
        for job in jobs:
            one(job)
    else:
        with ThreadPoolExecutor(max_workers=jobs_at_once) as pool:
            list(pool.map(one, jobs))
    ordered = [rows[j.name] for j in jobs]
    write_summary(out, ordered)
    return ordered

