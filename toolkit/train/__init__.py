"""Stage 11 — two-stage training of the decoupled field (paper eqs. 21–23), presets, checkpoints.

Training state is explicit (:class:`TrainState`; ``state = init_state(cfg, data)``, ``train_step(state, ...)``)
so resume is exact: a checkpoint holds the field, optimiser, l_env, occupancy grid, RNG state and the step, and
a resumed ``--steps`` run reproduces an uninterrupted one bit for bit on CPU.

Stages:
  (a) pretrain (first ``pretrain_fraction`` of the run): the light estimate l_env is frozen; the field is
      optimised on L_rgb + λ L_ssim + λ L_mat (eq. 21);
  (b) alternate, every ``light_period`` steps: ``light_steps`` steps that fix the field and optimise l_env on
      the L1 reprojection error (eq. 22), then field steps with l_env fixed on eq. 23 (+ L_psnr, L_eikonal).
  ``fixed_light`` skips the l_env steps (the "fixed lighting" ablation).

A run directory holds ``config.json``, ``checkpoint.pt``, ``log.jsonl``, ``loss_curves.png`` and
``snapshots/`` (field states at the ``snapshot_minutes`` milestones).

Modules: :mod:`~toolkit.train.config` (:class:`TrainConfig`, presets, :func:`resolve_config`),
:mod:`~toolkit.train.data` (:func:`prepare_data`, through :func:`toolkit.priors.read_priors`),
:mod:`~toolkit.train.step` (state, batches, the field and light steps), :mod:`~toolkit.train.loop` (:func:`train`,
checkpoints) and :mod:`~toolkit.train.run` (a finished run: :func:`load_run`, :meth:`Run.render`, the field as
callables for meshing and baking). Every public name is importable from :mod:`toolkit.train`.
"""

from __future__ import annotations

from .config import PRESETS, SHELL_FADE, TrainConfig, make_config, photos_have_transparency, resolve_config, resolve_scene_box
from .data import TrainData, grey_ambient_sh, prepare_data
from .loop import load_checkpoint, save_checkpoint, train
from .run import FieldCallables, Run, field_callables, load_field_callables, load_run, render_views
from .step import (MAX_BAD_STEPS, TrainingDiverged, TrainState, calibrate_steps, field_steps, init_state, is_light_step,
                   light_step, lr_progress, progress, sample_batch, train_step)

__all__ = ["TrainConfig", "make_config", "PRESETS", "TrainData", "TrainState", "prepare_data", "init_state",
           "train_step", "light_step", "train", "save_checkpoint", "load_checkpoint", "Run", "load_run",
           "render_views", "TrainingDiverged", "grey_ambient_sh", "resolve_config", "FieldCallables", "field_callables",
           "load_field_callables", "SHELL_FADE", "MAX_BAD_STEPS", "progress", "lr_progress", "calibrate_steps",
           "is_light_step", "field_steps",
           "sample_batch", "resolve_scene_box", "photos_have_transparency"]
