"""One pinhole camera in numpy — the camera type of ``export/`` (ONNX Runtime inference) and ``viewers/``.

:class:`PinholeCamera` holds one camera exactly as the toolkit does (SPEC): camera-to-world 4x4 in OpenGL convention
(x right, y up, looking down −z) in the dars world (+z up, metres) and pinhole intrinsics in pixels with pixel
``(u, v)`` centred at ``(u + ½, v + ½)``, row 0 at the top. :class:`toolkit.cameras.Cameras` is the batched torch
form used for training and rendering; :meth:`PinholeCamera.from_cameras` and
:func:`toolkit.cameras.cameras_from_pinholes` convert between them. :func:`look_at` builds the camera-to-world
matrix of a camera looking at a point.

Importing this module loads numpy only (no torch): ``export.infer`` runs on devices without torch.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ._checks import ConfigError, DarsError, check_shape

__all__ = ["PinholeCamera", "look_at"]


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """float64 [4, 4] OpenGL camera-to-world at ``eye`` looking at ``target`` (world +z up by default).

    Args:
        eye: float [3] camera position, metres.
        target: float [3] point the camera looks at.
        up: float [3] world up (the image's up vector is its component orthogonal to the view direction).

    Raises:
        DarsError: ``eye`` equals ``target``.

    Example:
        >>> look_at([0.0, -2.0, 0.0], [0.0, 0.0, 0.0])[:3, 2]  # the camera looks down -z: +z points back
        array([ 0., -1.,  0.])
    """
    eye, target, up = (np.asarray(x, dtype=np.float64) for x in (eye, target, up))
    fwd = target - eye
    if np.linalg.norm(fwd) < 1e-12:
        raise DarsError("look_at: eye and target coincide")
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    if np.linalg.norm(right) < 1e-9:  # looking along ``up``: any horizontal right vector will do
        right = np.cross(fwd, np.array([0.0, 1.0, 0.0]) if abs(up[1]) < 0.9 else np.array([1.0, 0.0, 0.0]))
    right /= np.linalg.norm(right)
    true_up = np.cross(right, fwd)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, true_up, -fwd, eye
    return m


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole camera in the dars world (numpy).

    Attributes:
        c2w: float64 [4, 4] OpenGL camera-to-world (x right, y up, −z forward), world +z up, metres.
        fx, fy: focal lengths in pixels.
        cx, cy: principal point in pixels (from the top-left image corner).
        width, height: image size in pixels.
        near, far: clip distances in metres (the viewers' depth range; inference uses the scene's bounds).
    """

    c2w: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    near: float = 0.02
    far: float = 200.0

    def __post_init__(self) -> None:
        c2w = np.asarray(self.c2w, dtype=np.float64)
        check_shape(c2w, "4 4", "PinholeCamera.c2w")
        if not np.isfinite(c2w).all():
            raise DarsError("PinholeCamera.c2w contains NaN or inf")
        object.__setattr__(self, "c2w", c2w)
        if self.width < 1 or self.height < 1:
            raise ConfigError(f"PinholeCamera: image size {self.width}x{self.height} must be positive")
        if not (0 < self.near < self.far):
            raise ConfigError(f"PinholeCamera: need 0 < near ({self.near}) < far ({self.far})")

    @classmethod
    def from_cameras(cls, cameras, index: int, near: float = 0.02, far: float = 200.0) -> "PinholeCamera":
        """Camera ``index`` of a :class:`toolkit.cameras.Cameras` batch.

        Raises:
            DarsError: ``index`` is out of range.
        """
        if not 0 <= index < len(cameras):
            raise DarsError(f"camera index {index} is out of range (the split has {len(cameras)} cameras)")
        g = lambda t: float(t[index])  # noqa: E731
        return cls(cameras.c2w[index].detach().cpu().double().numpy(), g(cameras.fx), g(cameras.fy), g(cameras.cx),
                   g(cameras.cy), int(cameras.width[index]), int(cameras.height[index]), near, far)

    def resized(self, width: int, height: int | None = None) -> "PinholeCamera":
        """The same view at another resolution (intrinsics scaled; ``height`` keeps the aspect by default)."""
        height = height if height is not None else max(1, round(self.height * width / self.width))
        sx, sy = width / self.width, height / self.height
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy, width=width,
                       height=height)

    @property
    def position(self) -> np.ndarray:
        """float64 [3] camera centre, world."""
        return self.c2w[:3, 3].copy()

    def projection(self) -> np.ndarray:
        """float64 [4, 4] OpenGL projection from the pinhole intrinsics (NDC y up = image row 0 at the top)."""
        w, h, n, f = float(self.width), float(self.height), self.near, self.far
        p = np.zeros((4, 4))
        p[0, 0] = 2.0 * self.fx / w
        p[0, 2] = 1.0 - 2.0 * self.cx / w
        p[1, 1] = 2.0 * self.fy / h
        p[1, 2] = 2.0 * self.cy / h - 1.0
        p[2, 2] = -(f + n) / (f - n)
        p[2, 3] = -2.0 * f * n / (f - n)
        p[3, 2] = -1.0
        return p
