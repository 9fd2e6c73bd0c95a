"""Viewer cameras: the glTF axis conversion, framing, ``SCENE:SPLIT:INDEX`` specs, orbit and walk controllers.

Conventions:

* Cameras are :class:`toolkit.pinhole.PinholeCamera` (the numpy camera ``export/`` uses too): camera-to-world 4x4
  in OpenGL convention (x right, y up, looking down −z) in the dars world (+z up, metres) and pinhole intrinsics in
  pixels with pixel ``(u, v)`` centred at ``(u + ½, v + ½)``, row 0 at the top.
* The viewers draw a GLB's vertex data as stored, in glTF's +y-up frame, so the camera is rotated into that frame with
  the exporter's map ``(x, y, z) → (x, z, −y)`` (:data:`export.gltf.WORLD_TO_GLTF`): ``c2w_gltf = R · c2w`` with
  ``R = diag(WORLD_TO_GLTF, 1)``. :meth:`PinholeCamera.projection` maps the intrinsics to an OpenGL clip matrix whose
  fragment centres coincide with :func:`toolkit.cameras.generate_rays`' pixel centres (window row 0 at the bottom:
  flip rows on read-back); :func:`view_projection_gltf` combines the two.
* Controllers (:class:`OrbitController`, :class:`WalkController`) work in the dars world (+z up) and produce a
  camera-to-world matrix; they are pure numpy (tested without a window).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from export.gltf import WORLD_TO_GLTF
from toolkit._checks import DarsError, check_shape
from toolkit.pinhole import PinholeCamera, look_at

__all__ = ["camera_from_spec", "default_camera", "OrbitController", "WalkController", "gltf_c2w",
           "view_matrix_gltf", "view_projection_gltf"]


def gltf_c2w(c2w_world: np.ndarray) -> np.ndarray:
    """float [4, 4] camera-to-world (dars world, +z up) → the same camera in glTF's +y-up frame."""
    r = np.eye(4)
    r[:3, :3] = WORLD_TO_GLTF
    return r @ np.asarray(c2w_world, dtype=np.float64)


def view_matrix_gltf(camera: PinholeCamera) -> np.ndarray:
    """float64 [4, 4] world-to-camera matrix of ``camera`` for vertices in glTF's +y-up frame."""
    return np.linalg.inv(gltf_c2w(camera.c2w))


def view_projection_gltf(camera: PinholeCamera) -> np.ndarray:
    """float64 [4, 4] clip-from-glTF-frame matrix of ``camera``."""
    return camera.projection() @ view_matrix_gltf(camera)


def _pinhole(width: int, height: int, fov_y_deg: float) -> tuple[float, float, float, float]:
    f = 0.5 * height / math.tan(math.radians(fov_y_deg) * 0.5)
    return f, f, width * 0.5, height * 0.5


def default_camera(vertices: np.ndarray, width: int = 1280, height: int = 720, fov_y_deg: float = 50.0) -> PinholeCamera:
    """A camera that frames a mesh: from the front-left, slightly above, looking at the bounding-box centre.

    Args:
        vertices: float [V, 3] world positions (+z up).
    """
    v = np.asarray(vertices, dtype=np.float64)
    check_shape(v, "V 3", "vertices")
    if v.shape[0] == 0:
        raise DarsError("default_camera: the mesh has no vertices")
    lo, hi = v.min(0), v.max(0)
    centre, radius = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 1e-3)
    dist = radius / math.sin(math.radians(fov_y_deg) * 0.5) * 1.05
    direction = np.array([-0.55, -0.75, 0.37])
    eye = centre + dist * direction / np.linalg.norm(direction)
    fx, fy, cx, cy = _pinhole(width, height, fov_y_deg)
    return PinholeCamera(look_at(eye, centre), fx, fy, cx, cy, width, height, near=dist * 1e-3, far=dist * 10 + radius)


def camera_from_spec(spec: str, width: int | None = None) -> PinholeCamera:
    """Parse ``SCENE:SPLIT:INDEX`` (a scene path, its split and a frame index) into a :class:`PinholeCamera`.

    The near/far planes come from the scene's bounds. ``width`` rescales the intrinsics (aspect kept).

    Raises:
        DarsError: malformed spec, unknown split or index out of range (naming the scene).
    """
    from toolkit.scene import load_scene

    parts = spec.rsplit(":", 2)
    if len(parts) != 3 or not parts[2].lstrip("-").isdigit():
        raise DarsError(f"--camera {spec!r}: expected SCENE:SPLIT:INDEX, e.g. samples/gallery:test:0")
    scene_path, split, index = parts[0], parts[1], int(parts[2])
    scene = load_scene(scene_path, split)
    if not 0 <= index < len(scene):
        raise DarsError(f"--camera {spec!r}: index {index} is out of range ({scene_path} split {split!r} has "
                        f"{len(scene)} frames)")
    extent = float(np.linalg.norm((scene.aabb[1] - scene.aabb[0]).numpy()))
    cam = PinholeCamera.from_cameras(scene.cameras, index, near=max(extent * 1e-3, 1e-3), far=extent * 10)
    return cam.resized(width) if width else cam


# ====================================================================================================== controllers
@dataclass
class OrbitController:
    """Turntable orbit around ``target`` (world +z up): left-drag rotates, right-drag pans, scroll zooms.

    Attributes:
        target: float [3] orbit centre, world.
        distance: metres from the target.
        azimuth: degrees about +z (0 looks along +y).
        elevation: degrees above the horizon, clamped to ±89.
    """

    target: np.ndarray
    distance: float
    azimuth: float = -35.0
    elevation: float = 20.0

    @classmethod
    def from_camera(cls, camera: PinholeCamera, target: np.ndarray) -> "OrbitController":
        """Orbit through ``camera``'s position around ``target``."""
        target = np.asarray(target, dtype=np.float64)
        d = camera.position - target
        dist = max(float(np.linalg.norm(d)), 1e-6)
        elev = math.degrees(math.asin(np.clip(d[2] / dist, -1, 1)))
        azim = math.degrees(math.atan2(-d[0], -d[1]))
        return cls(target.copy(), dist, azim, elev)

    def eye(self) -> np.ndarray:
        """float64 [3] camera position."""
        a, e = math.radians(self.azimuth), math.radians(self.elevation)
        forward = np.array([math.sin(a) * math.cos(e), math.cos(a) * math.cos(e), -math.sin(e)])  # looks down for e > 0
        return self.target - self.distance * forward

    def c2w(self) -> np.ndarray:
        return look_at(self.eye(), self.target)

    def rotate(self, dx_deg: float, dy_deg: float) -> None:
        self.azimuth = (self.azimuth + dx_deg) % 360.0
        self.elevation = float(np.clip(self.elevation + dy_deg, -89.0, 89.0))

    def zoom(self, factor: float) -> None:
        self.distance = float(np.clip(self.distance * factor, 1e-3, 1e5))

    def pan(self, dx: float, dy: float) -> None:
        """Move the target in the view plane by (dx, dy) × distance."""
        c2w = self.c2w()
        self.target = self.target + (c2w[:3, 0] * dx + c2w[:3, 1] * dy) * self.distance


@dataclass
class WalkController:
    """First-person walk-through (world +z up): W/S forward/back, A/D strafe, Q/E down/up, mouse-drag looks.

    Attributes:
        position: float [3] eye, world.
        yaw: degrees about +z (0 looks along +y).
        pitch: degrees above the horizon, clamped to ±89.
        speed: metres per second.
    """

    position: np.ndarray
    yaw: float = 0.0
    pitch: float = 0.0
    speed: float = 1.0

    @classmethod
    def from_camera(cls, camera: PinholeCamera, speed: float = 1.0) -> "WalkController":
        fwd = -camera.c2w[:3, 2]
        return cls(camera.position, math.degrees(math.atan2(fwd[0], fwd[1])),
                   math.degrees(math.asin(np.clip(fwd[2], -1, 1))), speed)

    def forward(self) -> np.ndarray:
        y, p = math.radians(self.yaw), math.radians(self.pitch)
        return np.array([math.sin(y) * math.cos(p), math.cos(y) * math.cos(p), math.sin(p)])

    def c2w(self) -> np.ndarray:
        return look_at(self.position, self.position + self.forward())

    def look(self, dx_deg: float, dy_deg: float) -> None:
        self.yaw = (self.yaw + dx_deg) % 360.0
        self.pitch = float(np.clip(self.pitch + dy_deg, -89.0, 89.0))

    def move(self, forward: float, right: float, up: float, seconds: float) -> None:
        """Move by unit-less intents (−1..1 each) for ``seconds`` at ``speed``; forward stays horizontal."""
        y = math.radians(self.yaw)
        f = np.array([math.sin(y), math.cos(y), 0.0])
        r = np.array([math.cos(y), -math.sin(y), 0.0])
        self.position = self.position + (f * forward + r * right + np.array([0, 0, 1.0]) * up) * self.speed * seconds
