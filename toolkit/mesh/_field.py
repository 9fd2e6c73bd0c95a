"""Calling the field callables on numpy points, box checks and progress bars (shared by the mesh stages)."""

from __future__ import annotations

import sys
from typing import Callable

import numpy as np
import torch

from .._checks import DarsError, ShapeError, check_shape
from .types import DensityFn


def _call_field(fn: Callable, points: np.ndarray, device: str | torch.device, *extra) -> object:
    """Call a field callable on float32 torch points (no grad) and return its raw output."""
    pts = torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32)).to(device)
    args = [None if e is None else torch.from_numpy(np.ascontiguousarray(e, dtype=np.float32)).to(device) for e in extra]
    with torch.no_grad():
        return fn(pts, *args)


def _to_numpy(x, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach()
        x = x.float() if x.is_floating_point() else x
        return x.cpu().numpy()
    return np.asarray(x)


def _density(density_fn: DensityFn, points: np.ndarray, device) -> np.ndarray:
    out = _to_numpy(_call_field(density_fn, points, device), "density")
    out = out.reshape(-1) if out.size == points.shape[0] else out
    if out.shape != (points.shape[0],):
        raise ShapeError(f"density_fn returned shape {list(out.shape)} for {points.shape[0]} points; expected [N] (or [N, 1])")
    return out.astype(np.float32, copy=False)


def _progress(total: int, desc: str, enabled: bool, unit: str = "it"):
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit=unit, disable=not enabled, file=sys.stderr, leave=False, dynamic_ncols=True)


def _check_aabb(aabb) -> np.ndarray:
    a = _to_numpy(aabb, "aabb").astype(np.float64)
    check_shape(a, "2 3", "aabb")
    if not np.isfinite(a).all() or not (a[1] > a[0]).all():
        raise DarsError(f"aabb must be finite with max > min on every axis, got {a.tolist()}")
    return a


def _iter_progress(it, desc: str, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(it, desc=desc, disable=not enabled, file=sys.stderr, leave=False, dynamic_ncols=True)
