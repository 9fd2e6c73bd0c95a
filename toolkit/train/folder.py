"""The run folder of :func:`~toolkit.train.train`: may it be written (:mod:`toolkit.outputs`), its ``config.json`` and
checkpoints read with clear errors, and what ``--resume`` continues.

A run folder holds :data:`toolkit.outputs.RUN_FILES` and ``dars_manifest.json``. A new run goes into a new or empty
folder (or beside other files with ``force``); a folder holding a run is continued with ``resume`` or started again
with ``force`` (its earlier run files are deleted; files dars did not write are never touched).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from .._checks import ConfigError, DarsError
from ..io import check_torch_file, load_torch, read_json
from ..outputs import RUN_FILES, OutputDir, read_manifest

__all__ = ["open_run_dir", "find_run", "read_run_meta", "read_run_config", "run_scene_options", "read_checkpoint",
           "check_priors_root",
           "FIRST_CHECKPOINT_STEPS", "FIRST_CHECKPOINT_SECONDS", "first_checkpoint_due", "CHECKPOINT_KEYS"]

FIRST_CHECKPOINT_STEPS = 100
FIRST_CHECKPOINT_SECONDS = 60.0
"""The first checkpoint of a run is written after this many steps or seconds of training, whichever comes first (then
every ``checkpoint_every`` steps or 5 minutes), so an early kill still leaves a run to ``--resume``."""
CHECKPOINT_KEYS = ("field", "background", "l_env", "occupancy", "step", "elapsed")
"""What every checkpoint holds (a resumable one also the optimisers and the RNG state)."""


def first_checkpoint_due(state, ck_path: Path) -> bool:
    """Whether the run's first checkpoint is due now (none written yet, and 100 steps or a minute trained)."""
    return ((state.step >= FIRST_CHECKPOINT_STEPS or state.elapsed >= FIRST_CHECKPOINT_SECONDS)
            and not ck_path.exists())


def _fix(run_dir: Path) -> str:
    return (f"copy it again if it was copied, use a snapshot (--checkpoint {run_dir}/snapshots/FILE) if there is one, "
            f"or train again: `dars train SCENE --out {run_dir} --force`")


def read_run_meta(run_dir: str | os.PathLike) -> dict:
    """``config.json`` of a run folder as a dict (``config``, ``scene``, ``split``, ``priors_root`` ...).

    Raises:
        DarsError: missing, corrupt or not a dars run config, naming the file.
    """
    run_dir = Path(run_dir)
    path = run_dir / "config.json"
    fix = (f"{run_dir} is not a complete dars run: train one with `dars train SCENE --out RUN`, or start this one "
           f"again with `dars train SCENE --out {run_dir} --force`")
    meta = read_json(path, "run config", fix)
    missing = [k for k in ("config", "scene") if k not in meta]
    if missing or not isinstance(meta.get("config"), dict):
        raise DarsError(f"run config {path} lacks {', '.join(missing) or 'a valid config'}: it was not written by "
                        f"`dars train`; {fix}")
    return meta


def find_run(run_dir: str | os.PathLike, checkpoint: str | os.PathLike | None = None) -> tuple[dict, Path]:
    """Check that ``run_dir`` is a training run (and ``checkpoint``, a snapshot, exists) and read its ``config.json``;
    the checkpoint itself is not read here.

    Returns:
        (``config.json`` as a dict, the checkpoint's path).

    Raises:
        DarsError: no such folder, not a run, a missing checkpoint or a corrupt ``config.json``, naming the file.
    """
    run_dir = Path(run_dir)
    ck_path = Path(checkpoint) if checkpoint else run_dir / "checkpoint.pt"
    if not run_dir.is_dir():
        raise DarsError(f"RUN directory not found: {run_dir} (give the --out directory of `dars train SCENE --out RUN`)")
    if not (run_dir / "config.json").is_file() and not ck_path.is_file():
        raise DarsError(f"{run_dir} is not a training run (a run holds config.json and checkpoint.pt): create one "
                        "with `dars train SCENE --out RUN`")
    meta = read_run_meta(run_dir)
    if not Path(meta["scene"]).exists():
        raise DarsError(f"{run_dir} was trained on {meta['scene']} (config.json), which is not there any more: the run "
                        "needs its scene's cameras and box; put the scene back at that path")
    if not ck_path.is_file():
        if checkpoint:
            raise DarsError(f"--checkpoint {ck_path}: file not found (snapshots are in {run_dir / 'snapshots'})")
        raise DarsError(f"{run_dir} has no checkpoint.pt (the run stopped before its first checkpoint); continue it "
                        f"with `dars train --resume --out {run_dir}` or start it again with --force")
    check_torch_file(ck_path, "checkpoint", _fix(run_dir))
    return meta, ck_path


def run_scene_options(meta: dict) -> dict:
    """How a run loaded its scene, from its ``config.json``: the :func:`~toolkit.scene.load_scene` keywords
    ``downscale`` (``dars train --downscale``; 1 for runs written before it) and ``upright`` (``"off"`` with
    ``--no-upright``, and for runs written before scenes were made upright on load: they trained in the input's frame)
    and ``masks`` (the run's resolved ``--masks``: ``ignore``, ``alpha`` or ``off``; ``off`` for runs written before
    masks were read, which trained on every pixel, as :meth:`~toolkit.train.TrainConfig.from_dict` loads them).
    """
    return {"downscale": int(meta.get("downscale", 1)), "upright": meta.get("upright", "off"),
            "masks": meta.get("masks", "off")}


def read_run_config(meta: dict, path: str | os.PathLike):
    """The :class:`~toolkit.train.TrainConfig` stored in a run's ``config.json`` (``path``, for messages).

    Raises:
        DarsError: the stored configuration is not one this version of dars can read.
    """
    from .config import TrainConfig

    try:
        return TrainConfig.from_dict(meta["config"])
    except (TypeError, KeyError, ValueError, AttributeError) as e:
        why = str(e) if isinstance(e, ConfigError) else f"{type(e).__name__}: {e}"
        raise DarsError(f"run config {path} holds a training configuration this version of dars cannot read ({why}); "
                        "it was written by another version or edited: train the run again") from e


def read_checkpoint(path: str | os.PathLike, map_location: Any = "cpu",
                    run_dir: str | os.PathLike | None = None) -> dict:
    """A run's checkpoint (``checkpoint.pt`` or a snapshot) as a dict.

    Raises:
        DarsError: missing, empty, truncated or not a dars checkpoint, naming the file and what to do.
    """
    path = Path(path)
    fix = _fix(Path(run_dir) if run_dir is not None else path.parent)
    ck = load_torch(path, "checkpoint", fix, map_location=map_location)
    missing = [k for k in CHECKPOINT_KEYS if not isinstance(ck, dict) or k not in ck]
    if missing:
        raise DarsError(f"checkpoint {path} is not a dars training checkpoint (no {', '.join(missing)}); {fix}")
    return ck


def check_priors_root(priors_root: str | os.PathLike | None, option: str = "--priors") -> None:
    """Raise :class:`DarsError` when a priors folder was given but does not exist or holds no prior stage."""
    if priors_root is None:
        return
    p = Path(priors_root)
    if not p.is_dir():
        raise DarsError(f"{option} {p}: folder not found; give the folder the prior stages wrote (default "
                        f"SCENE/priors, made by `dars priors STAGE SCENE`), or leave {option} out")
    stages = ("segment", "weights", "light", "colour", "layout")
    if not any((p / s).is_dir() for s in stages):
        here = [s for s in stages if p.name == s]
        hint = f" ({p} itself looks like the '{here[0]}' stage: give its parent {p.parent})" if here else ""
        raise DarsError(f"{option} {p} holds none of the prior stage folders ({', '.join(s + '/' for s in stages)})"
                        f"{hint}; give the folder that holds them, or leave {option} out")


def _same_path(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    try:
        return Path(a).resolve() == Path(b).resolve()
    except OSError:
        return str(a) == str(b)


def open_run_dir(out: str | os.PathLike, resume: bool = False, force: bool = False,
                 scene: str | os.PathLike | None = None,
                 priors_root: str | os.PathLike | None = None) -> tuple[OutputDir, dict | None]:
    """Check that a run may be written into ``out`` (before any work; nothing is written here).

    Returns:
        (the folder, checked — :meth:`~toolkit.outputs.OutputDir.begin` it before the first write; the saved
        ``config.json`` when resuming, else None).

    Raises:
        DarsError: ``resume`` without a run (or with a damaged one) or with another ``scene``; a folder holding a run
            without ``resume``/``force``; a folder dars may not write (see :mod:`toolkit.outputs`); a ``priors_root``
            that is missing.
    """
    out = Path(out)
    folder = OutputDir(out, "train", force=force)
    if resume:
        ck_path = out / "checkpoint.pt"
        if not out.is_dir():
            raise DarsError(f"--resume: run folder not found: {out}; start a run with `dars train SCENE --out {out}`")
        if not ck_path.is_file():
            raise DarsError(f"--resume: no checkpoint at {ck_path} (the run was stopped before its first checkpoint, "
                            f"or this is not a run folder); start it again with `dars train SCENE --out {out} --force`")
        meta = read_run_meta(out)
        check_torch_file(ck_path, "checkpoint", "the run cannot be resumed from it: copy it again if it was copied, "
                         f"copy a snapshot over it (cp {out}/snapshots/FILE {ck_path}) if there is one, or start "
                         f"again: `dars train SCENE --out {out} --force`")
        if scene is not None and not _same_path(scene, meta["scene"]):
            raise DarsError(f"--resume: {out} was trained on {meta['scene']}, not {scene}; resume it without a scene "
                            f"(`dars train --resume --out {out}`), or train {scene} into a new folder (another --out)")
        folder.check(RUN_FILES)
        folder.manifest = folder.manifest or read_manifest(out)
        return folder, meta
    check_priors_root(priors_root)
    man = read_manifest(out) if out.is_dir() else None
    holds_run = man is not None and any((out / f).exists() for f in ("checkpoint.pt", "config.json")
                                        if f in man["files"])
    if holds_run and not force:
        raise DarsError(f"{out} already holds a run (checkpoint.pt); pass --resume to continue it, --force to start "
                        "again (deletes that run's checkpoint, config and log), or choose another --out")
    folder.check(RUN_FILES)
    if holds_run:
        folder.stale = [f for f in RUN_FILES if f in man["files"]]
    return folder, None
