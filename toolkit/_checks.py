"""Input checks used at public boundaries.

Every check raises a :class:`DarsError` subclass (never ``assert``: ``python -O`` strips those) with a
message that names the file, frame and value that is wrong and says what to do about it.

Importing this module loads neither torch nor numpy (the command line's ``--help`` imports it): both are
imported inside the checks that need them.
"""

from __future__ import annotations

import math
import re
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

if TYPE_CHECKING:
    import numpy as np
    import torch


class DarsError(ValueError):
    """Base class of every error the toolkit raises on bad input (a ``ValueError``)."""


class SceneError(DarsError):
    """A scene file, image or pose is missing, corrupt or inconsistent."""


class ShapeError(DarsError):
    """A tensor has the wrong shape."""


class ConfigError(DarsError):
    """A configuration value is out of range or inconsistent."""


def check_shape(x: torch.Tensor | np.ndarray, spec: str, name: str = "tensor") -> dict[str, int]:
    """Check ``x`` against a space-separated shape spec and return the bound dimension sizes.

    Tokens are integers (must match exactly), letters (bind a size, must agree on reuse) or ``...``
    (any number of leading dimensions).

    Args:
        x: tensor or array to check.
        spec: e.g. ``"B 3 H W"`` or ``"... 3"``.
        name: what the caller calls ``x`` (used in the message).

    Returns:
        mapping from dimension letter to size.

    Raises:
        ShapeError: with the expected and actual shape.

    Example:
        >>> check_shape(torch.zeros(2, 3, 4, 5), "B 3 H W")
        {'B': 2, 'H': 4, 'W': 5}
    """
    tokens = spec.split()
    shape = tuple(x.shape)
    bound: dict[str, int] = {}
    if tokens and tokens[0] == "...":
        tokens = tokens[1:]
        if len(shape) < len(tokens):
            raise ShapeError(f"{name}: expected shape [{spec}], got {list(shape)}")
        shape = shape[len(shape) - len(tokens):]
    elif len(shape) != len(tokens):
        raise ShapeError(f"{name}: expected shape [{spec}], got {list(x.shape)}")
    for tok, size in zip(tokens, shape):
        if re.fullmatch(r"\d+", tok):
            if size != int(tok):
                raise ShapeError(f"{name}: expected shape [{spec}], got {list(x.shape)}")
        else:
            if tok in bound and bound[tok] != size:
                raise ShapeError(f"{name}: expected shape [{spec}] with consistent '{tok}', got {list(x.shape)}")
            bound[tok] = size
    return bound


def check_finite(x: torch.Tensor | np.ndarray, name: str) -> None:
    """Raise :class:`DarsError` if ``x`` contains NaN or inf."""
    import numpy as np

    torch = sys.modules.get("torch")  # a tensor implies torch is loaded; never import it for a numpy array
    is_tensor = torch is not None and isinstance(x, torch.Tensor)
    ok = bool(torch.isfinite(x).all()) if is_tensor else bool(np.isfinite(x).all())
    if not ok:
        raise DarsError(f"{name} contains NaN or inf values")


def check_range(value: float, lo: float, hi: float, name: str) -> None:
    """Raise :class:`ConfigError` unless ``lo <= value <= hi`` (and finite)."""
    if not (isinstance(value, (int, float)) and math.isfinite(value) and lo <= value <= hi):
        raise ConfigError(f"{name}={value!r} is out of range: expected a number in [{lo}, {hi}]")


def check_choice(value: Any, choices: Sequence[Any], name: str) -> None:
    """Raise :class:`ConfigError` unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise ConfigError(f"{name}={value!r} is not valid: choose one of {list(choices)}")


def check_file(path: Path, what: str, hint: str = "") -> Path:
    """Return ``path`` if it is an existing file, else raise :class:`SceneError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{what} not found: {path}" + (f" ({hint})" if hint else ""))
    return path


def check_rigid_pose(c2w: np.ndarray, where: str, tol: float = 1e-3) -> None:
    """Check that a 4x4 (or 3x4) camera-to-world matrix is finite and its rotation orthonormal.

    Raises:
        SceneError: naming ``where`` (file and frame) and the offending value.
    """
    import numpy as np

    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.shape not in ((4, 4), (3, 4)):
        raise SceneError(f"{where}: transform_matrix must be 4x4 (or 3x4), got shape {list(c2w.shape)}")
    if not np.isfinite(c2w).all():
        raise SceneError(f"{where}: transform_matrix contains NaN or inf: {c2w.tolist()}")
    rot = c2w[:3, :3]
    err = float(np.abs(rot.T @ rot - np.eye(3)).max())
    if err > tol:
        raise SceneError(
            f"{where}: rotation part of transform_matrix is not orthonormal (max |R^T R - I| = {err:.3g} > {tol}); "
            "poses must be rigid camera-to-world transforms without scale or shear"
        )
    det = float(np.linalg.det(rot))
    if det < 0:
        raise SceneError(f"{where}: rotation part of transform_matrix is a reflection (det = {det:.3f}); expected det = +1")
