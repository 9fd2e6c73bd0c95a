"""Stage 1 — load posed images into a :class:`Scene` (cameras, projection and rays: :mod:`toolkit.cameras`).

Supported inputs (``load_scene(path, split=...)``):

* a directory with ``transforms_{train,val,test}.json`` (NeRF "Blender" / nerfstudio / instant-ngp layout);
* a directory with one ``transforms.json`` (split: every ``test_every``-th frame, default 8, is ``test``; the
  rest is ``train``; ``val`` is the same as ``test``);
* a single transforms JSON file (all its frames form the split ``all``; ``train``/``test`` split it as above);
* a COLMAP text model: a directory holding ``cameras.txt`` and ``images.txt`` (at its root or under
  ``sparse/0/`` or ``sparse/``) and the photos under ``images/``;
* a tiny-NeRF ``.npz`` (keys ``images``, ``poses``, ``focal``): the first 100 frames are ``train``, the rest
  ``test`` (the classic tiny-NeRF convention; ``n_train`` overrides).

Conventions (SPEC): camera-to-world 4x4 in OpenGL convention (x right, y up, camera looks down −z);
world up +z. Pixel ``(u, v)`` = (column, row) has its centre at ``(u + 0.5, v + 0.5)`` in the pixel
coordinates that ``cx, cy`` use, so the camera-space ray through it is
``((u + 0.5 − cx) / fx, −(v + 0.5 − cy) / fy, −1)``. Images are float in [0, 1] as stored (sRGB for
PNG/JPEG photos; :attr:`Scene.srgb` says so). Images are decoded lazily, one file at a time: memory is what
the caller asks for (:meth:`Scene.load_image`, :meth:`Scene.load_images`), never the whole data set.

Upright on load: a COLMAP model's world frame is arbitrary (often y down), and a transforms JSON from another tool
need not be +z up. For a COLMAP model, and for a transforms JSON that has no ``aabb`` and was not written by
``dars poses`` (no ``dars_transform`` key), :func:`load_scene` estimates world up from the cameras of every split
(and COLMAP's sparse points; :func:`toolkit.upright.plan_upright_rotation`) and, when the tilt exceeds
:data:`toolkit.upright.LOAD_TILT_TOLERANCE_DEG`, rotates the world so that up is +z (rotation only: centre and scale
stay). ``scene.meta["upright"]`` records what was done; ``upright="off"`` keeps the input's frame.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable, Literal, Sequence

import numpy as np
import torch

from ._checks import SceneError, check_rigid_pose
from .cameras import Cameras, RayBundle, generate_rays, intersect_aabb, project_points
from .io import JPEG_REDUCTIONS, JPEG_SUFFIXES, read_image, read_map
from .upright import PLANE_MAX_REPROJ_PX, plan_upright_rotation

__all__ = [
    "Cameras",
    "Frame",
    "Scene",
    "photos_have_transparency",
    "RayBundle",
    "SEMANTIC_CLASSES",
    "UNLABELLED",
    "EXTRA_KEYS",
    "load_scene",
    "list_splits",
    "generate_rays",
    "project_points",
    "intersect_aabb",
    "scene_info",
]

SEMANTIC_CLASSES: tuple[str, ...] = ("painting", "frame", "display", "base", "wall", "floor", "other")
"""The 7 SPEC classes; a label image stores the index (0-6), 255 = unlabelled/background."""
UNLABELLED = 255

EXTRA_KEYS: dict[str, str] = {
    "mask": "mask_path",
    "depth": "depth_file_path",
    "semantic": "semantic_path",
    "normal": "normal_path",
    "albedo": "albedo_path",
    "roughness": "roughness_path",
    "metallic": "metallic_path",
    "metal": "metal_path",
    "radiance": "radiance_path",
}
"""Per-frame optional maps: name -> transforms-JSON key (paths relative to the JSON).

Units and spaces: ``depth`` metres along the camera axis (−z_cam; 16-bit PNG values times the scene's
``depth_unit_scale_factor``, default 0.001, or ``.npy`` in metres; 0 = no hit); ``normal`` world-space unit
normals (PNG encodes (n+1)/2); ``albedo`` linear base colour; ``roughness``/``metallic`` in [0, 1];
``semantic`` uint8 class ids (:data:`SEMANTIC_CLASSES`, 255 unlabelled); ``metal`` the metal-subclass
annotation mask (non-zero = metal); ``mask`` foreground mask (non-zero = keep; a JPEG or WebP mask: above half its range); ``radiance`` linear
radiance (``.hdr``/``.exr``/``.npy``)."""

_RADIAL_CV_MODELS = {"SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV"}
_FISHEYE_MODELS = {"SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "OPENCV_FISHEYE", "FOV", "THIN_PRISM_FISHEYE"}

Split = Literal["train", "val", "test", "all"]


@dataclass(frozen=True)
class Frame:
    """One image record: where its files are, never their pixels.

    Attributes:
        name: the frame's name in the source (``file_path`` as written, or the COLMAP image name).
        image_path: resolved path of the photo (``None`` when pixels come from an in-memory array).
        extras: optional per-frame maps, name -> resolved path (keys of :data:`EXTRA_KEYS`).
        distortion: OpenCV distortion coefficients (k1, k2, p1, p2[, k3, ...]) applied by undistortion on load,
            or ``None`` for a pure pinhole image.
        native_size: (width, height) of the stored image before downscaling.
    """

    name: str
    image_path: Path | None
    extras: dict[str, Path] = field(default_factory=dict)
    distortion: tuple[float, ...] | None = None
    native_size: tuple[int, int] | None = None

    @property
    def distorted(self) -> bool:
        """True when the photo has lens distortion to undo on load (a non-zero coefficient)."""
        return self.distortion is not None and any(abs(c) > 0 for c in self.distortion)

    @property
    def key(self) -> str:
        """A file-name-safe identifier of the frame, stable across runs (``train/r_000.png`` -> ``train__r_000``).

        Prior stages name their per-frame outputs ``<key>.<ext>`` under ``<scene dir>/priors/<stage>/``.
        """
        stem = str(Path(self.name).with_suffix("")) if Path(self.name).suffix.lower() in (
            ".png", ".jpg", ".jpeg", ".exr", ".hdr", ".npy") else self.name
        return "".join(c if c.isalnum() or c in "-_." else "__" if c in "/\\" else "_" for c in stem).lstrip("._")


@dataclass(frozen=True)
class Scene:
    """Posed images of one split, loaded lazily.

    Attributes:
        source: the file or directory the scene was loaded from.
        split: ``"train"``, ``"val"``, ``"test"`` or ``"all"``.
        cameras: :class:`Cameras` of the split (intrinsics already scaled by ``downscale``).
        frames: one :class:`Frame` per camera.
        aabb: float [2, 3] scene bounds (min, max) in metres.
        near, far: scalar ray bounds from the file (``None``: rays are clipped to ``aabb``).
        sh: float [9, 3] ground-truth environment SH (SPEC convention) or ``None``.
        envmap_path: ground-truth environment map (lat-long, SPEC convention) or ``None``.
        background: RGB in [0, 1] that RGBA images are composited onto.
        downscale: integer factor images are reduced by on load.
        srgb: whether stored images are sRGB-encoded (PNG/JPEG photos) rather than linear.
        depth_unit_scale_factor: PNG depth value x factor = metres.
        masks: what a frame's ``mask_path`` means to :meth:`load_image`: ``ignore`` (nerfstudio's meaning, the
            default) — nothing here; the mask marks the pixels training may use (:meth:`valid_mask`), 0 = ignore
            (people, a tripod, glare); ``alpha`` — the mask is the photo's alpha: pixels outside it are composited
            onto :attr:`background`, as an RGBA photo's would be (an object captured with masks); ``off`` — masks
            are not read.
        meta: other top-level values of the source file (e.g. ``render``, ``scene`` blocks). ``meta["upright"]``
            (COLMAP and transforms inputs): ``rotation`` (float [3, 3] lists, ``x_loaded = rotation @ x_file``; the
            identity when nothing was rotated), ``tilt_deg``, ``source`` (``cameras`` / ``cameras+plane``, None when
            not estimated), ``applied`` and, when the frame was kept without estimating, ``kept`` (why). When applied,
            cameras, the box, :attr:`sh`, ``meta["sh"]``/``meta["sh_env"]`` and normal maps (on load) are in the
            rotated frame; other world-space values of the file (``envmap_path``'s map, ``scene`` blocks) are not.
    """

    source: Path
    split: str
    cameras: Cameras
    frames: tuple[Frame, ...]
    aabb: torch.Tensor
    near: float | None = None
    far: float | None = None
    sh: torch.Tensor | None = None
    envmap_path: Path | None = None
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    downscale: int = 1
    srgb: bool = True
    depth_unit_scale_factor: float = 0.001
    meta: dict = field(default_factory=dict)
    masks: Literal["ignore", "alpha", "off"] = "ignore"
    _array_images: np.ndarray | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def image_size(self) -> tuple[int, int]:
        """(height, width) of the first image (all images share it unless intrinsics are per frame)."""
        return int(self.cameras.height[0]), int(self.cameras.width[0])

    def extras_available(self) -> list[str]:
        """Names of per-frame maps present for every frame of the split."""
        if not self.frames:
            return []
        return [k for k in EXTRA_KEYS if all(k in f.extras for f in self.frames)]

    def has_extra(self, name: str) -> bool:
        return name in self.extras_available()

    @property
    def root(self) -> Path:
        """The scene directory (``source`` itself for a directory, else the folder holding the file)."""
        return self.source if self.source.is_dir() else self.source.parent

    def priors_dir(self, stage: str) -> Path:
        """Where prior stages write their outputs for this scene: ``<root>/priors/<stage>``.

        For a tiny-NeRF ``.npz`` the folder is named after the file (``<dir>/<stem>.priors/<stage>``) so
        scenes sharing a directory do not mix. Nothing the user owns lives there.
        """
        if self.source.suffix.lower() == ".npz":
            return self.source.parent / f"{self.source.stem}.priors" / stage
        if self.meta.get("format") == "colmap":
            return Path(self.meta["model"]).parent / "priors" / stage
        return self.root / "priors" / stage

    def subset(self, indices: Sequence[int]) -> "Scene":
        """The same scene restricted to some frames (still lazy)."""
        idx = list(indices)
        arr = None if self._array_images is None else self._array_images[idx]
        return replace(self, cameras=self.cameras[idx], frames=tuple(self.frames[i] for i in idx), _array_images=arr)

    # ------------------------------------------------------------------ pixels
    def _where(self, i: int) -> str:
        f = self.frames[i]
        return f"{self.source} frame {i} ('{f.name}')"

    def _expected_hw(self, i: int) -> tuple[int, int]:
        return int(self.cameras.height[i]), int(self.cameras.width[i])

    def _jpeg_reduction(self, i: int, path: Path | None = None) -> int:
        """The factor frame ``i``'s photo (or its map at ``path``) may be decoded at directly
        (:func:`toolkit.io.read_image`'s ``reduce``): the largest of 8, 4, 2 that divides the downscale and the
        stored size, for a JPEG; 1 otherwise. With lens distortion, half that: distortion is undone (bilinear) on
        the decoded pixels, and an area filter of at least 2 after it keeps the result as sharp as undoing it on
        the whole photo."""
        f = self.frames[i]
        path = f.image_path if path is None else path
        if (self.downscale == 1 or path is None or f.native_size is None
                or path.suffix.lower() not in JPEG_SUFFIXES):
            return 1
        k = next((k for k in JPEG_REDUCTIONS
                  if self.downscale % k == 0 and f.native_size[0] % k == 0 and f.native_size[1] % k == 0), 1)
        return k // 2 or 1 if f.distorted and k == self.downscale else k

    def _postprocess(self, i: int, img: np.ndarray, what: str, interp: str, reduced: int = 1) -> np.ndarray:
        """Undistort, downscale and size-check one decoded H-W-C map of frame ``i`` (decoded at 1/``reduced`` of
        its stored size)."""
        import cv2

        f = self.frames[i]
        if f.native_size is not None:
            nw, nh = f.native_size
            if img.shape[1] * reduced != nw or img.shape[0] * reduced != nh:
                size = (f"{img.shape[1]}x{img.shape[0]}" if reduced == 1 else
                        f"about {img.shape[1] * reduced}x{img.shape[0] * reduced} (decoded at 1/{reduced} of its size)")
                raise SceneError(f"{self._where(i)}: {what} is {size} but the camera intrinsics say {nw}x{nh}; fix w/h "
                                 "in the transforms file or resize the image")
        if f.distorted:
            s = self.downscale / reduced  # the intrinsics of the decoded pixels (the coefficients have no unit)
            K = np.array(
                [[float(self.cameras.fx[i]) * s, 0, float(self.cameras.cx[i]) * s],
                 [0, float(self.cameras.fy[i]) * s, float(self.cameras.cy[i]) * s],
                 [0, 0, 1]], dtype=np.float64)
            # The principal point of K is in pixel-centre-at-0.5 coordinates; OpenCV's is at 0: shift by 0.5.
            K_cv = K.copy()
            K_cv[0, 2] -= 0.5
            K_cv[1, 2] -= 0.5
            flag = cv2.INTER_NEAREST if interp == "nearest" else cv2.INTER_LINEAR
            map1, map2 = cv2.initUndistortRectifyMap(K_cv, np.array(f.distortion, np.float64), None, K_cv,
                                                     (img.shape[1], img.shape[0]), cv2.CV_32FC1)
            squeeze = img.ndim == 3 and img.shape[2] == 1
            img = cv2.remap(img, map1, map2, flag, borderMode=cv2.BORDER_CONSTANT)
            if squeeze and img.ndim == 2:
                img = img[..., None]
        if self.downscale > reduced:
            h, w = self._expected_hw(i)
            squeeze = img.ndim == 3 and img.shape[2] == 1
            flag = cv2.INTER_NEAREST if interp == "nearest" else cv2.INTER_AREA
            img = cv2.resize(img, (w, h), interpolation=flag)
            if squeeze or img.ndim == 2:
                img = img.reshape(h, w, -1)
        h, w = self._expected_hw(i)
        if img.shape[0] != h or img.shape[1] != w:
            raise SceneError(
                f"{self._where(i)}: {what} is {img.shape[1]}x{img.shape[0]} but the camera says {w}x{h}; "
                "all maps of a frame must match its image size"
            )
        return img

    def load_image(self, i: int, with_alpha: bool = False) -> torch.Tensor:
        """Decode image ``i`` to float [3, H, W] in [0, 1] (RGBA is composited onto :attr:`background`).

        Args:
            i: frame index within the split.
            with_alpha: return float [4, H, W] with the alpha channel (1 where the file has none) instead.

        Raises:
            SceneError: missing/corrupt file or a size that disagrees with the intrinsics (names the file).
        """
        if not 0 <= i < len(self):
            raise IndexError(f"frame index {i} out of range for split '{self.split}' with {len(self)} frames")
        k = 1
        if self._array_images is not None:
            img = np.asarray(self._array_images[i], dtype=np.float32)
            if img.ndim == 2:
                img = img[..., None].repeat(3, -1)
        else:
            k = self._jpeg_reduction(i)
            img = read_image(self.frames[i].image_path, what=f"image of {self._where(i)}", reduce=k)
        if img.shape[2] == 1:
            img = np.repeat(img, 3, axis=2)
        img = self._postprocess(i, img, "image", "area", reduced=k)
        rgb = img[..., :3]
        alpha = img[..., 3:4] if img.shape[2] >= 4 else np.ones_like(img[..., :1])
        if self.masks == "alpha" and "mask" in self.frames[i].extras:
            alpha = alpha * self._mask_alpha(i)
        if img.shape[2] >= 4 or self.masks == "alpha":
            rgb = rgb * alpha + np.asarray(self.background, np.float32) * (1.0 - alpha)
        out = np.concatenate([rgb, alpha], -1) if with_alpha else rgb
        return torch.from_numpy(np.ascontiguousarray(out.transpose(2, 0, 1))).float()

    def _mask_alpha(self, i: int) -> np.ndarray:
        """float [H, W, 1] in [0, 1]: frame ``i``'s mask as an alpha (area-filtered when downscaled)."""
        path = self.frames[i].extras["mask"]
        r = self._jpeg_reduction(i, path) // 2 or 1  # a JPEG at half the reduction its photo gets: soft 2x2 edges
        m = read_map(path, f"mask of {self._where(i)}", reduce=r)
        m = m[..., :1] if m.ndim == 3 else m[..., None]
        top = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(m.dtype, 1.0)
        if path.suffix.lower() in _LOSSY_SUFFIXES:  # compression noise: cut, then area-filter (lossless: soft as is)
            m = (m > _mask_cut(path, m)) * top
        m = np.ascontiguousarray(m.astype(np.float32) / top)
        m = self._postprocess(i, m, "mask", "area", reduced=r)
        return np.clip(m if m.ndim == 3 else m[..., None], 0.0, 1.0)

    def valid_mask(self, i: int) -> torch.Tensor | None:
        """bool [H, W]: the pixels of frame ``i`` that training and scoring may use under ``masks="ignore"`` (its
        ``mask_path`` > 0), or None when the frame has no mask or the masks are alpha."""
        if self.masks != "ignore" or "mask" not in self.frames[i].extras:
            return None
        return self.load_extra(i, "mask")

    def load_images(self, indices: Iterable[int] | None = None, with_alpha: bool = False) -> torch.Tensor:
        """Decode several images to float [B, 3, H, W] (or [B, 4, H, W]); all must share one size."""
        idx = list(range(len(self))) if indices is None else list(indices)
        imgs = [self.load_image(i, with_alpha) for i in idx]
        sizes = {tuple(x.shape) for x in imgs}
        if len(sizes) > 1:
            raise SceneError(f"{self.source}: images of split '{self.split}' differ in size {sorted(sizes)}; "
                             "load them one at a time with load_image")
        return torch.stack(imgs) if imgs else torch.zeros(0, 3 + with_alpha, *self.image_size)

    def load_extra(self, i: int, name: str) -> torch.Tensor:
        """Decode a per-frame map of frame ``i`` (see :data:`EXTRA_KEYS` for units).

        Returns:
            ``semantic``: int64 [H, W] class ids (255 unlabelled); ``mask``/``metal``: bool [H, W];
            ``depth``/``roughness``/``metallic``: float [H, W]; ``normal``: float [3, H, W] unit world normals
            (zero where there is no surface); ``albedo``/``radiance``: float [3, H, W].

        Raises:
            SceneError: the frame has no such map, the file is missing/corrupt, its size disagrees with the
                image, or labels contain class ids outside 0-6 and 255.
        """
        if name not in EXTRA_KEYS:
            raise SceneError(f"unknown per-frame map '{name}': choose one of {list(EXTRA_KEYS)}")
        f = self.frames[i]
        if name not in f.extras:
            raise SceneError(f"{self._where(i)} has no '{EXTRA_KEYS[name]}' ({name} map)")
        path = f.extras[name]
        what = f"{name} map of {self._where(i)}"
        if name == "semantic":
            lab = read_map(path, what)
            if lab.ndim == 3:
                lab = lab[..., 0]
            lab = self._postprocess(i, lab.astype(np.uint8)[..., None] if lab.dtype != np.uint8 else lab[..., None],
                                    "semantic labels", "nearest")[..., 0]
            bad = np.setdiff1d(np.unique(lab), np.array(list(range(len(SEMANTIC_CLASSES))) + [UNLABELLED]))
            if bad.size:
                raise SceneError(f"{what} ({path}) contains unknown class ids {bad.tolist()}: valid ids are "
                                 f"0-6 ({', '.join(SEMANTIC_CLASSES)}) and 255 (unlabelled)")
            return torch.from_numpy(lab.astype(np.int64))
        if name in ("mask", "metal"):
            r = self._jpeg_reduction(i, path)
            m = read_map(path, what, reduce=r)
            m = m[..., :1] if m.ndim == 3 else m[..., None]
            m = self._postprocess(i, (m > _mask_cut(path, m)).astype(np.uint8), name, "nearest", reduced=r)[..., 0]
            return torch.from_numpy(m > 0)
        if name == "depth":
            raw = read_map(path, what)
            raw = raw[..., :1] if raw.ndim == 3 else raw[..., None]
            if path.suffix.lower() == ".npy":
                d = raw.astype(np.float32)
            else:
                d = raw.astype(np.float32) * float(self.depth_unit_scale_factor)
            d = self._postprocess(i, d, "depth map", "nearest")[..., 0]
            return torch.from_numpy(np.ascontiguousarray(d))
        img = read_image(path, what)
        img = self._postprocess(i, img, f"{name} map", "nearest" if name == "normal" else "area")
        if name in ("roughness", "metallic"):
            return torch.from_numpy(np.ascontiguousarray(img[..., 0]))
        img = img[..., :3]
        if name == "normal" and path.suffix.lower() != ".npy":
            valid = img.sum(-1, keepdims=True) > 0
            n = img * 2.0 - 1.0
            n = n / np.clip(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6, None)
            img = np.where(valid, n, 0.0).astype(np.float32)
        if name == "normal" and self.meta.get("upright", {}).get("applied"):  # world-space: into the upright frame
            img = (img @ np.asarray(self.meta["upright"]["rotation"], np.float32).T).astype(np.float32)
        return torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))


# ====================================================================== loading
def list_splits(path: str | Path) -> list[str]:
    """Splits available at ``path`` (see :func:`load_scene`)."""
    path = Path(path)
    if not path.exists():
        raise SceneError(f"scene not found: {path}")
    if path.is_dir():
        found = [s for s in ("train", "val", "test") if (path / f"transforms_{s}.json").is_file()]
        if found:
            return found
        if (path / "transforms.json").is_file() or _find_colmap(path) is not None or (path / LLFF_POSES).is_file():
            return ["train", "test", "all"]
        raise _not_a_scene(path, f"{path}: no transforms_*.json, transforms.json, COLMAP model (cameras.txt + "
                                 f"images.txt) or LLFF {LLFF_POSES} found")
    if path.suffix.lower() == ".npz":
        return ["train", "test", "all"]
    if path.suffix.lower() == ".json":
        return ["train", "test", "all"]
    raise _not_a_scene(path, f"{path}: not a scene directory, transforms JSON or tiny-NeRF .npz")


_PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".heic", ".heif", ".webp", ".dng")
_LOSSY_SUFFIXES = (".jpg", ".jpeg", ".webp")


def _mask_cut(path: Path, m: np.ndarray) -> float:
    """The value a mask (or metal-mask) pixel must exceed to count: 0 for a lossless file, half the range for a
    JPEG or WebP, whose compression leaves faint non-zero values along the edges and over the background."""
    if path.suffix.lower() not in _LOSSY_SUFFIXES:
        return 0
    return {np.dtype(np.uint8): 127, np.dtype(np.uint16): 32767}.get(m.dtype, 0.5)


def _not_a_scene(path: Path, message: str) -> SceneError:
    """The error for a path that is no scene; a folder of photos (or one photo) gets the way to make it one."""
    if path.is_file() and path.suffix.lower() in _PHOTO_SUFFIXES:
        return SceneError(f"{message}: {path.name} is a photo; a scene needs photos with camera poses: put the photos "
                          f"in a folder and estimate the poses with `dars poses PHOTOS_DIR --out SCENE_DIR`")
    if path.is_dir():
        try:
            photos = sum(1 for p in path.rglob("*") if p.suffix.lower() in _PHOTO_SUFFIXES and p.is_file())
        except OSError:
            photos = 0
        if photos:
            return SceneError(f"{message}. It holds {photos} photo{'s' if photos > 1 else ''} but no camera poses: "
                              f"estimate them with `dars poses {path} --out SCENE_DIR`, then give SCENE_DIR")
    return SceneError(message)


def load_scene(
    path: str | Path,
    split: Split = "train",
    downscale: int = 1,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    test_every: int = 8,
    n_train: int = 100,
    aabb: Sequence[Sequence[float]] | None = None,
    distortion: Literal["undistort", "reject"] = "undistort",
    upright: Literal["auto", "off"] = "auto",
    masks: Literal["ignore", "alpha", "off"] = "ignore",
) -> Scene:
    """Load one split of a scene (lazily: only headers are read here).

    Args:
        path: scene directory, transforms JSON, COLMAP model directory or tiny-NeRF ``.npz``.
        split: ``train``, ``val``, ``test`` or ``all``.
        downscale: integer factor to shrink images and intrinsics by (area filter; nearest for labels/depth).
        background: RGB in [0, 1] that RGBA images are composited onto.
        test_every: for a single ``transforms.json`` or COLMAP model, frame ``i`` is ``test`` when
            ``i % test_every == 0`` (``val`` = ``test``).
        n_train: for a tiny-NeRF ``.npz``, the first ``n_train`` frames are ``train``, the rest ``test``.
        aabb: override the scene bounds ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]`` (metres).
        distortion: images with radial/tangential distortion are undistorted on load (``undistort``) or
            refused (``reject``). Fisheye models are always refused.
        upright: ``auto``: a COLMAP model, or a transforms JSON without ``aabb`` that ``dars poses`` did not write,
            is rotated so that its estimated world up is +z when it is tilted by more than
            :data:`toolkit.upright.LOAD_TILT_TOLERANCE_DEG` (the same rotation for every split; see the module
            docstring and ``meta["upright"]``). ``off``: keep the input's frame. ``aabb`` is in the loaded frame.

    Raises:
        SceneError: naming the file, frame and value for missing/corrupt images, missing, non-finite or
            non-rigid poses, size mismatches, empty splits and unsupported camera models.
    """
    path = Path(path)
    if not path.exists():
        raise SceneError(f"scene not found: {path}")
    if split not in ("train", "val", "test", "all"):
        raise SceneError(f"unknown split '{split}': choose train, val, test or all")
    if not isinstance(downscale, int) or downscale < 1:
        raise SceneError(f"downscale must be a positive integer, got {downscale!r}")
    if upright not in ("auto", "off"):
        raise SceneError(f"upright must be 'auto' or 'off', got {upright!r}")
    if masks not in ("ignore", "alpha", "off"):
        raise SceneError(f"masks must be 'ignore', 'alpha' or 'off', got {masks!r}")
    bg = tuple(float(c) for c in background)
    if len(bg) != 3 or not all(0.0 <= c <= 1.0 for c in bg):
        raise SceneError(f"background must be 3 values in [0, 1], got {list(background)}")
    if path.is_file() and path.suffix.lower() == ".npz":
        scene = _load_npz(path, split, n_train, bg, downscale)
    elif path.is_file() and path.suffix.lower() in _PHOTO_SUFFIXES:
        raise _not_a_scene(path, f"{path}: not a scene directory, transforms JSON or tiny-NeRF .npz")
    elif path.is_file():
        scene = _load_transforms(path, split, test_every, bg, downscale, distortion, upright, single=True)
    elif any((path / f"transforms_{s}.json").is_file() for s in ("train", "val", "test")):
        file = path / f"transforms_{split}.json"
        if split == "all":
            parts = [load_scene(path, s, downscale, bg, test_every, n_train, aabb, distortion, upright, masks)
                     for s in list_splits(path)]
            return _concat(parts)
        if not file.is_file():
            avail = [s for s in ("train", "val", "test") if (path / f"transforms_{s}.json").is_file()]
            raise SceneError(f"{path}: split '{split}' not found (no {file.name}); available splits: {avail}")
        siblings = [path / f"transforms_{s}.json" for s in ("train", "val", "test")]
        scene = _load_transforms(file, split, test_every, bg, downscale, distortion, upright, single=False,
                                 bounds_files=[f for f in siblings if f.is_file()])
    elif (path / "transforms.json").is_file():
        scene = _load_transforms(path / "transforms.json", split, test_every, bg, downscale, distortion, upright,
                                 single=True)
    elif _find_colmap(path) is not None:
        scene = _load_colmap(path, split, test_every, bg, downscale, distortion, upright)
    elif (path / LLFF_POSES).is_file():
        meta = _llff_meta(path)
        scene = _load_transforms(path / LLFF_POSES, split, test_every, bg, downscale, distortion, upright,
                                 single=True, meta=meta)
    else:
        raise _not_a_scene(path, f"{path}: no transforms_*.json, transforms.json, COLMAP model (cameras.txt + "
                                 f"images.txt), LLFF {LLFF_POSES} or .npz found")
    if len(scene) == 0:
        raise SceneError(f"{scene.source}: split '{split}' is empty (no frames); check the file or the split rule")
    if aabb is not None:
        box = torch.tensor(aabb, dtype=torch.float32)
        if box.shape != (2, 3) or not bool((box[1] > box[0]).all()):
            raise SceneError(f"aabb must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with max > min, got {aabb}")
        scene = replace(scene, aabb=box, meta={**scene.meta, "aabb_source": "file"})
    if masks != "ignore":
        if masks == "alpha" and not any("mask" in f.extras for f in scene.frames):
            raise SceneError(f"{scene.source}: masks='alpha' (dars train --masks alpha) but no frame of split "
                             f"'{split}' has a mask_path; add the masks to the transforms JSON or drop --masks alpha")
        scene = replace(scene, masks=masks)
    return scene


def _concat(parts: list[Scene]) -> Scene:
    cams = Cameras(*(torch.cat([getattr(p.cameras, f) for p in parts]) for f in
                     ("c2w", "fx", "fy", "cx", "cy", "width", "height")))
    frames = tuple(f for p in parts for f in p.frames)
    return replace(parts[0], split="all", cameras=cams, frames=frames)


def _split_indices(n: int, split: str, test_every: int) -> list[int]:
    if split == "all":
        return list(range(n))
    if test_every < 2:
        raise SceneError(f"test_every must be >= 2, got {test_every}")
    if split in ("test", "val"):
        return [i for i in range(n) if i % test_every == 0]
    return [i for i in range(n) if i % test_every != 0]


def _image_size(path: Path, where: str) -> tuple[int, int]:
    """(width, height) from the image header (fast; no decode)."""
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise SceneError(f"{where}: image not found: {path}")
    try:
        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except (UnidentifiedImageError, OSError) as e:
        raise SceneError(f"{where}: image {path} is corrupt or not an image ({e}); re-export it") from e


def _resolve_image(base: Path, file_path: str, where: str) -> Path:
    p = (base / file_path)
    if p.is_file():
        return p
    if p.suffix == "":
        for ext in (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".exr"):
            if p.with_suffix(ext).is_file():
                return p.with_suffix(ext)
    raise SceneError(f"{where}: image not found: {p}")


def _scene_aabb(c2w: np.ndarray, fx: np.ndarray, width: np.ndarray, meta: dict) -> np.ndarray:
    """Scene bounds: the file's ``aabb`` if present, else an estimate from the cameras.

    The estimate: the point closest (least squares) to all optical axes is the centre; the half-size is the
    half-width that the median camera sees at that distance, i.e. median(dist) * tan(half horizontal FOV)
    (for Blender Lego: cameras at 4.03 m, FOV 39.6 deg -> [-1.45, 1.45]^3). Pass ``aabb=`` to override.
    """
    if "aabb" in meta:
        box = np.asarray(meta["aabb"], dtype=np.float64)
        if box.shape != (2, 3) or not (box[1] > box[0]).all():
            raise SceneError(f"'aabb' must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with max > min, got {meta['aabb']}")
        return box
    origins = c2w[:, :3, 3]
    axes = -c2w[:, :3, 2]
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for o, d in zip(origins, axes):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ o
    if np.linalg.cond(A) < 1e6:
        centre = np.linalg.solve(A, b)
    else:  # parallel axes (forward-facing capture): look 1 median spacing ahead of the mean camera
        centre = origins.mean(0) + axes.mean(0)
    dist = np.linalg.norm(origins - centre, axis=1)
    half_fov = np.arctan(0.5 * width / fx)
    half = float(np.median(dist) * np.tan(np.median(half_fov)))
    if not np.isfinite(half) or half <= 0:
        half = 1.0
    return np.stack([centre - half, centre + half])


def _read_transforms(file: Path) -> dict:
    try:
        text = file.read_bytes().decode("utf-8")
        meta = json.loads(text)
    except UnicodeDecodeError as e:
        raise SceneError(f"{file} is not a transforms JSON (not a text file); give the scene folder or its "
                         "transforms_*.json") from e
    except json.JSONDecodeError as e:
        what = "it is empty" if not text.strip() else f"invalid JSON: {e}"
        raise SceneError(f"{file}: not a valid transforms JSON ({what}); fix or re-export it") from e
    if not isinstance(meta, dict):
        raise SceneError(f"{file}: expected a JSON object with a 'frames' list at the top level (the Blender / "
                         f"nerfstudio transforms format), got a {type(meta).__name__}")
    if not isinstance(meta.get("frames"), list):
        raise SceneError(f"{file}: missing 'frames' list")
    return meta


def _all_poses_for_bounds(files: list[Path | dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray, set[str]]:
    """Poses, focal lengths and widths of every frame of every split (the scene box and the upright rotation must
    not depend on the split), and the top-level keys of the files (each a transforms JSON's path or its parsed
    content).

    Unparseable poses are skipped here; the split that holds them reports them when it is loaded.
    """
    c2ws, fxs, ws, keys = [], [], [], set()
    for f in files:
        meta = f if isinstance(f, dict) else _read_transforms(f)
        keys.update(meta)
        for fm in meta["frames"]:
            try:
                m = np.asarray(fm["transform_matrix"], dtype=np.float64)
                if m.shape == (3, 4):
                    m = np.vstack([m, [0, 0, 0, 1]])
                if m.shape != (4, 4) or not np.isfinite(m).all():
                    continue
            except (KeyError, TypeError, ValueError):
                continue
            try:
                w = float(fm.get("w", meta.get("w", 0)) or 0)
                if fm.get("fl_x", meta.get("fl_x")) is not None and w > 0:
                    fx = float(fm.get("fl_x", meta.get("fl_x")))
                else:
                    ang = float(fm.get("camera_angle_x", meta.get("camera_angle_x", 0.69)))
                    w, fx = 1.0, 0.5 / math.tan(0.5 * ang)
            except (AttributeError, TypeError, ValueError, ZeroDivisionError):
                continue  # reported when its split is loaded
            c2ws.append(m); fxs.append(fx); ws.append(w)  # noqa: E702
    return np.stack(c2ws) if c2ws else np.zeros((0, 4, 4)), np.array(fxs), np.array(ws), keys


def _plan_upright(upright: str, c2w_all: np.ndarray, points: np.ndarray | None = None,
                  kept: str | None = None) -> dict:
    """``meta["upright"]`` of a loaded scene: :func:`toolkit.upright.plan_upright_rotation` on every frame's pose (and
    the sparse points), or a not-applied record saying why the input's frame is kept without estimating."""
    if upright == "off" or kept is not None or len(c2w_all) == 0:
        return {"rotation": np.eye(3).tolist(), "tilt_deg": None, "source": None, "applied": False,
                "kept": "upright='off'" if upright == "off" else kept or "no valid poses"}
    return plan_upright_rotation(c2w_all, points)


def _rotate_world(c2w: np.ndarray, record: dict) -> np.ndarray:
    """float [N, 4, 4] camera-to-world matrices in the upright frame of ``record`` (``c2w`` itself when not applied)."""
    if not record["applied"]:
        return c2w
    T = np.eye(4)
    T[:3, :3] = record["rotation"]
    return T @ c2w


def _rotate_sh_coeffs(coeffs, record: dict) -> torch.Tensor:
    """float [9, 3] SH coefficients (SPEC convention) in the upright frame of an applied ``record``."""
    from .sh import rotate_sh

    c = torch.as_tensor(np.asarray(coeffs, dtype=np.float64).reshape(9, 3))
    return rotate_sh(c, np.asarray(record["rotation"], np.float64))


def _load_transforms(file: Path, split: str, test_every: int, bg, downscale: int, distortion: str, upright: str,
                     single: bool, bounds_files: list[Path] | None = None, meta: dict | None = None) -> Scene:
    """One split of a transforms JSON (``meta``: its content already parsed, or built from another layout such as
    :func:`_llff_meta`; ``file`` then names the source in messages and its folder resolves the frames' paths)."""
    meta = _read_transforms(file) if meta is None else meta
    frames_meta = meta["frames"]
    if single:
        order = _split_indices(len(frames_meta), split, test_every)
        frames_meta = [frames_meta[i] for i in order]
    base = file.parent
    c2ws, fxs, fys, cxs, cys, ws, hs, frames = [], [], [], [], [], [], [], []
    dist_keys = ("k1", "k2", "p1", "p2", "k3")
    for i, fm in enumerate(frames_meta):
        where = f"{file} frame {i}"
        if not isinstance(fm, dict):
            raise SceneError(f"{where}: expected an object {{\"file_path\": ..., \"transform_matrix\": ...}}, "
                             f"got {type(fm).__name__} {str(fm)[:40]!r}")
        if "file_path" not in fm:
            raise SceneError(f"{where}: missing 'file_path'")
        if not isinstance(fm["file_path"], str) or not fm["file_path"]:
            raise SceneError(f"{where}: 'file_path' must be an image path (a string), got {fm['file_path']!r}")
        where = f"{file} frame {i} ('{fm['file_path']}')"
        if "transform_matrix" not in fm:
            raise SceneError(f"{where}: missing 'transform_matrix' (camera pose)")
        try:
            m = np.asarray(fm["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise SceneError(f"{where}: transform_matrix is not a numeric matrix ({e})") from e
        check_rigid_pose(m, where)
        if m.shape == (3, 4):
            m = np.vstack([m, [0, 0, 0, 1]])
        img_path = _resolve_image(base, fm["file_path"], where)
        w_img, h_img = _image_size(img_path, where)
        def get(k, d=None, kind=float):  # per-frame values override the shared ones; numbers checked, key named
            v = fm.get(k, meta.get(k))
            return d if v is None else _number(v, k, where, kind)

        w = get("w", w_img, int)
        h = get("h", h_img, int)
        if (w, h) != (w_img, h_img):
            raise SceneError(f"{where}: image {img_path.name} is {w_img}x{h_img} but the intrinsics say w={w}, h={h}; "
                             "fix w/h (or fl_x, cx, ...) in the transforms file or resize the image")
        if get("fl_x") is not None:
            fx = get("fl_x")
            fy = get("fl_y", fx)
        elif get("camera_angle_x") is not None:
            for k in ("camera_angle_x", "camera_angle_y"):
                if get(k) is not None and not 0.0 < get(k) < math.pi:
                    raise SceneError(f"{where}: '{k}' must be a field of view in radians in (0, pi), got {get(k)}")
            fx = 0.5 * w / math.tan(0.5 * get("camera_angle_x"))
            fy = 0.5 * h / math.tan(0.5 * get("camera_angle_y")) if get("camera_angle_y") is not None else fx
            if get("fl_y") is not None:
                fy = get("fl_y")
        else:
            raise SceneError(f"{where}: no intrinsics: give 'camera_angle_x' or 'fl_x' (and optionally fl_y, cx, cy)")
        cx = get("cx", w / 2.0)
        cy = get("cy", h / 2.0)
        if not all(math.isfinite(v) and v > 0 for v in (fx, fy)):
            raise SceneError(f"{where}: focal length must be positive and finite, got fl_x={fx}, fl_y={fy}")
        coeffs = tuple(get(k, 0.0) for k in dist_keys)
        if fm.get("k4", meta.get("k4")) is not None or get("camera_model", None, str) in ("OPENCV_FISHEYE", "FISHEYE"):
            raise SceneError(f"{where}: fisheye distortion is not supported; undistort the images first "
                             "(e.g. `colmap image_undistorter`) and drop k1..k4")
        has_dist = any(abs(c) > 0 for c in coeffs)
        if has_dist and distortion == "reject":
            raise SceneError(f"{where}: images are distorted (k1..p2 = {coeffs[:4]}) and distortion='reject'; "
                             "pass distortion='undistort' or undistort them first")
        extras = {}
        for name, key in EXTRA_KEYS.items():
            if fm.get(key):
                extras[name] = base / fm[key]
        c2ws.append(m)
        fxs.append(fx); fys.append(fy); cxs.append(cx); cys.append(cy); ws.append(w); hs.append(h)  # noqa: E702
        frames.append(Frame(name=str(fm["file_path"]), image_path=img_path, extras=extras,
                            distortion=coeffs if has_dist else None, native_size=(w, h)))
    c2w = np.stack(c2ws) if c2ws else np.zeros((0, 4, 4))
    all_c2w, all_fx, all_w, keys = _all_poses_for_bounds(bounds_files or [meta])
    kept = ("the file has an 'aabb' (its frame is the box's)" if "aabb" in keys
            else "written by dars poses (already upright)" if "dars_transform" in keys else None)
    record = _plan_upright(upright, all_c2w, kept=kept)
    c2w, all_c2w = _rotate_world(c2w, record), _rotate_world(all_c2w, record)
    box = _scene_aabb(all_c2w, all_fx, all_w, meta) if len(all_c2w) else np.array([[-1.0] * 3, [1.0] * 3])
    sh = _read_sh(meta, base, file)
    envmap = base / meta["envmap"] if meta.get("envmap") else None
    cams = _make_cameras(c2w, fxs, fys, cxs, cys, ws, hs, downscale)
    extra_meta = {k: v for k, v in meta.items() if k != "frames"}
    extra_meta["aabb_source"] = "file" if "aabb" in meta else "cameras"
    extra_meta["upright"] = record
    if record["applied"]:
        sh = None if sh is None else _rotate_sh_coeffs(sh, record).float()
        for k in ("sh", "sh_env"):  # the ground-truth light as written in the file: 9 x [r, g, b]
            if np.size(extra_meta.get(k)) == 27:
                extra_meta[k] = _rotate_sh_coeffs(extra_meta[k], record).tolist()
    return Scene(source=file, split=split, cameras=cams, frames=tuple(frames), aabb=torch.tensor(box, dtype=torch.float32),
                 near=_opt_number(meta, "near", file), far=_opt_number(meta, "far", file), sh=sh, envmap_path=envmap,
                 background=bg, downscale=downscale, srgb=True,
                 depth_unit_scale_factor=_number(meta.get("depth_unit_scale_factor", 0.001), "depth_unit_scale_factor",
                                                 str(file)), meta=extra_meta)


def _number(value, key: str, where: str, kind: type = float):
    """``value`` of ``key`` as a finite ``kind`` (float, int or str), else a :class:`SceneError` naming file, frame,
    key and value (``"w": "abc"`` in a transforms file)."""
    if kind is str:
        return str(value)
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise SceneError(f"{where}: '{key}' must be a number, got {value!r}; fix it in the transforms file")
    try:
        v = float(value)
    except ValueError:
        raise SceneError(f"{where}: '{key}' must be a number, got {value!r}; fix it in the transforms file") from None
    if not math.isfinite(v):
        raise SceneError(f"{where}: '{key}' must be finite, got {value!r}; fix it in the transforms file")
    if kind is int:
        if v != int(v) or v <= 0:
            raise SceneError(f"{where}: '{key}' must be a positive whole number of pixels, got {value!r}")
        return int(v)
    return v


def _opt_number(meta: dict, key: str, file: Path) -> float | None:
    return None if meta.get(key) is None else _number(meta[key], key, str(file))


def _read_sh(meta: dict, base: Path, file: Path) -> torch.Tensor | None:
    sh = meta.get("sh")
    if sh is None and meta.get("sh_path"):
        p = base / meta["sh_path"]
        if not p.is_file():
            raise SceneError(f"{file}: sh_path {p} not found")
        try:
            loaded = json.loads(p.read_text())
        except (ValueError, UnicodeDecodeError) as e:
            raise SceneError(f"{file}: sh_path {p} is not valid JSON ({e})") from e
        sh = loaded.get("coeffs", loaded) if isinstance(loaded, dict) else loaded
    if sh is None:
        return None
    try:
        arr = np.asarray(sh, dtype=np.float32)
    except (TypeError, ValueError) as e:
        raise SceneError(f"{file}: 'sh' must hold 9 x [r, g, b] = 27 numbers ({e})") from e
    if arr.size != 27:
        raise SceneError(f"{file}: 'sh' must hold 9 x [r, g, b] = 27 numbers, got shape {list(arr.shape)}")
    arr = arr.reshape(9, 3)
    if not np.isfinite(arr).all():
        raise SceneError(f"{file}: 'sh' contains NaN or inf")
    return torch.from_numpy(arr)


def _make_cameras(c2w, fxs, fys, cxs, cys, ws, hs, downscale: int) -> Cameras:
    d = float(downscale)
    t = lambda x: torch.tensor(np.asarray(x, dtype=np.float64), dtype=torch.float32)  # noqa: E731
    w = torch.tensor([int(x) // downscale for x in ws], dtype=torch.long)
    h = torch.tensor([int(x) // downscale for x in hs], dtype=torch.long)
    # With pixel centres at +0.5, scaling pixel coordinates by 1/d maps cx -> cx/d exactly (edges to edges).
    return Cameras(c2w=t(c2w).reshape(-1, 4, 4), fx=t(fxs) / d, fy=t(fys) / d, cx=t(cxs) / d, cy=t(cys) / d,
                   width=w, height=h)


def _load_npz(file: Path, split: str, n_train: int, bg, downscale: int) -> Scene:
    try:
        data = np.load(file)
        images, poses, focal = data["images"], data["poses"], float(data["focal"])
    except KeyError as e:
        raise SceneError(f"{file}: tiny-NeRF .npz needs keys 'images', 'poses', 'focal' (missing {e})") from e
    except Exception as e:  # noqa: BLE001
        raise SceneError(f"{file}: could not read .npz ({e})") from e
    if images.ndim != 4 or images.shape[-1] not in (3, 4):
        raise SceneError(f"{file}: 'images' must be [N, H, W, 3|4], got {list(images.shape)}")
    if poses.shape[0] != images.shape[0]:
        raise SceneError(f"{file}: {images.shape[0]} images but {poses.shape[0]} poses")
    if images.dtype == np.uint8:
        images = images.astype(np.float32) / 255.0
    n = images.shape[0]
    idx = {"train": list(range(min(n_train, n))), "test": list(range(min(n_train, n), n)),
           "val": list(range(min(n_train, n), n)), "all": list(range(n))}[split]
    names = data["source_frames"] if "source_frames" in data.files else [f"{file.name}[{i}]" for i in range(n)]
    h, w = images.shape[1:3]
    c2ws = []
    for i in idx:
        check_rigid_pose(poses[i], f"{file} frame {i}")
        p = np.asarray(poses[i], dtype=np.float64)
        c2ws.append(np.vstack([p, [0, 0, 0, 1]]) if p.shape == (3, 4) else p)
    c2w = np.stack(c2ws) if c2ws else np.zeros((0, 4, 4))
    k = len(idx)
    cams = _make_cameras(c2w, [focal] * k, [focal] * k, [w / 2] * k, [h / 2] * k, [w] * k, [h] * k, downscale)
    frames = tuple(Frame(name=str(names[i]), image_path=None, native_size=(w, h)) for i in idx)
    all_c2w = np.stack([np.vstack([p, [0, 0, 0, 1]]) if p.shape == (3, 4) else p for p in poses.astype(np.float64)])
    box = _scene_aabb(all_c2w, np.full(n, focal), np.full(n, w), {})
    if not np.isfinite(images[idx]).all():
        bad = [i for i in idx if not np.isfinite(images[i]).all()]
        raise SceneError(f"{file}: images {bad[:5]} contain NaN or inf")
    return Scene(source=file, split=split, cameras=cams, frames=frames, aabb=torch.tensor(box, dtype=torch.float32),
                 near=2.0 if "near" not in data.files else float(data["near"]),
                 far=6.0 if "far" not in data.files else float(data["far"]),
                 background=bg, downscale=downscale, srgb=True, meta={"format": "tiny-nerf npz"},
                 _array_images=images[idx])


# ---------------------------------------------------------------------- LLFF
LLFF_POSES = "poses_bounds.npy"
"""The file that marks an LLFF capture (LLFF's ``imgs2poses.py``, NeRD's and many forward-facing datasets): per photo
a 3x5 pose-and-``[h, w, focal]`` matrix and the near/far depths, with the photos in ``images/``."""


def _llff_meta(path: Path) -> dict:
    """The transforms-JSON form of an LLFF capture at ``path``: ``poses_bounds.npy`` (float [N, 17]: a 3x5 matrix
    ``[R | t | (h, w, focal)]`` per photo, rotation columns (down, right, backwards), then near and far), the photos
    in ``images/`` paired with the rows in sorted file-name order (as LLFF writes them), and their masks in
    ``masks/`` (same file stem, any image type; NeRD's layout) when that folder exists. The focal length is scaled to
    the photos' actual width; the principal point is the image centre (LLFF's assumption)."""
    file = path / LLFF_POSES
    try:
        arr = np.load(file, allow_pickle=False)
    except Exception as e:  # noqa: BLE001
        raise SceneError(f"{file} could not be read as a .npy array ({e}); re-export it with LLFF's imgs2poses.py") from e
    if arr.ndim != 2 or arr.shape[1] not in (15, 17) or len(arr) == 0:
        raise SceneError(f"{file}: expected an [N, 17] array (per photo a 3x5 pose/[h, w, focal] matrix, then near "
                         f"and far), got shape {list(arr.shape)}")
    img_dir = path / "images"
    if not img_dir.is_dir():
        raise SceneError(f"{file}: an LLFF capture needs its photos in {img_dir}/ (LLFF's images_4/, images_8/ are "
                         "downscaled copies: keep images/ and use --downscale)")
    photos = sorted(p for p in img_dir.iterdir() if p.is_file() and p.suffix.lower() in _PHOTO_SUFFIXES)
    if len(photos) != len(arr):
        raise SceneError(f"{file}: {len(arr)} poses but {len(photos)} photos in {img_dir}; LLFF pairs them in sorted "
                         "file-name order, so the folder must hold exactly the photos that were posed")
    mask_dir = path / "masks"
    masks = {}
    if mask_dir.is_dir():
        masks = {p.stem: p for p in sorted(mask_dir.iterdir()) if p.is_file() and p.suffix.lower() in
                 _PHOTO_SUFFIXES + (".npy",)}
    frames = []
    for k, (photo, row) in enumerate(zip(photos, arr)):
        where = f"{file} row {k} ({photo.name})"
        P = np.asarray(row[:15], np.float64).reshape(3, 5)
        if not np.isfinite(P).all():
            raise SceneError(f"{where}: the pose is not finite: {P.tolist()}")
        h, w, focal = (float(v) for v in P[:, 4])
        if not (h > 0 and w > 0 and focal > 0):
            raise SceneError(f"{where}: h, w, focal must be positive, got {h}, {w}, {focal}")
        w_img, h_img = _image_size(photo, where)
        scale = w_img / w
        if abs(h_img / h - scale) > 0.01 * scale:
            raise SceneError(f"{where}: the photo is {w_img}x{h_img} but the poses say {w:g}x{h:g}, a different "
                             "aspect ratio; use the photos the poses were made from")
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = P[:, 1], -P[:, 0], P[:, 2], P[:, 3]
        fm = {"file_path": f"images/{photo.name}", "transform_matrix": c2w.tolist(), "fl_x": focal * scale,
              "fl_y": focal * scale, "cx": w_img / 2.0, "cy": h_img / 2.0, "w": w_img, "h": h_img}
        if masks:
            if photo.stem not in masks:
                raise SceneError(f"{where}: {mask_dir} has no mask for {photo.name} (a file named {photo.stem}.*); "
                                 "give every photo a mask or remove the folder")
            fm["mask_path"] = f"masks/{masks[photo.stem].name}"
        frames.append(fm)
    meta = {"frames": frames, "format": "llff"}
    if arr.shape[1] == 17:
        meta["llff_near_far"] = [float(arr[:, 15].min()), float(arr[:, 16].max())]
    return meta


# ---------------------------------------------------------------------- COLMAP
def _find_colmap(path: Path) -> Path | None:
    for sub in ("", "sparse/0", "sparse", "colmap/sparse/0"):
        d = path / sub if sub else path
        if (d / "cameras.txt").is_file() and (d / "images.txt").is_file():
            return d
    return None


def _qvec_to_rotmat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * y * y - 2 * z * z, 2 * x * y - 2 * w * z, 2 * x * z + 2 * w * y],
        [2 * x * y + 2 * w * z, 1 - 2 * x * x - 2 * z * z, 2 * y * z - 2 * w * x],
        [2 * x * z - 2 * w * y, 2 * y * z + 2 * w * x, 1 - 2 * x * x - 2 * y * y]])


def _load_colmap(path: Path, split: str, test_every: int, bg, downscale: int, distortion: str, upright: str) -> Scene:
    model = _find_colmap(path)
    cams_txt = model / "cameras.txt"
    cameras: dict[int, tuple[str, int, int, list[float]]] = {}
    for ln, line in enumerate(cams_txt.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            cam_id, model_name, w, h = int(parts[0]), parts[1], int(parts[2]), int(parts[3])
            params = [float(p) for p in parts[4:]]
        except (ValueError, IndexError) as e:
            raise SceneError(f"{cams_txt}:{ln}: malformed camera line '{line}'") from e
        cameras[cam_id] = (model_name, w, h, params)
    imgs_txt = model / "images.txt"
    lines = [ln for ln in imgs_txt.read_text().splitlines() if not ln.startswith("#")]
    records = []
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        if not line:
            i += 1
            continue
        parts = line.split()
        if len(parts) < 10:
            raise SceneError(f"{imgs_txt}: malformed image line '{line}' (expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME)")
        records.append(parts)
        i += 2  # skip the POINTS2D line
    records.sort(key=lambda p: p[9])
    image_dir = path / "images"
    if not image_dir.is_dir():
        image_dir = model.parent / "images" if (model.parent / "images").is_dir() else path
    order = _split_indices(len(records), split, test_every)
    c2ws, fxs, fys, cxs, cys, ws, hs, frames = [], [], [], [], [], [], [], []
    bounds_c2w, bounds_fx, bounds_w = [], [], []
    for parts in records:  # the scene box must not depend on the split
        try:
            q = np.array([float(x) for x in parts[1:5]]); t = np.array([float(x) for x in parts[5:8]])  # noqa: E702
            cam = cameras[int(parts[8])]
        except (ValueError, KeyError):
            continue
        if np.isfinite(q).all() and np.isfinite(t).all() and np.linalg.norm(q) > 1e-8:
            w2c = np.eye(4); w2c[:3, :3], w2c[:3, 3] = _qvec_to_rotmat(q), t  # noqa: E702
            bounds_c2w.append(np.linalg.inv(w2c) @ np.diag([1.0, -1.0, -1.0, 1.0]))
            bounds_fx.append(cam[3][0]); bounds_w.append(cam[1])  # noqa: E702
    for k in order:
        parts = records[k]
        name = parts[9]
        where = f"{imgs_txt} image '{name}'"
        q = np.array([float(x) for x in parts[1:5]])
        t = np.array([float(x) for x in parts[5:8]])
        if not (np.isfinite(q).all() and np.isfinite(t).all()) or np.linalg.norm(q) < 1e-8:
            raise SceneError(f"{where}: pose is not finite or the quaternion is zero: q={q.tolist()}, t={t.tolist()}")
        cam_id = int(parts[8])
        if cam_id not in cameras:
            raise SceneError(f"{where}: camera id {cam_id} not in {cams_txt}")
        model_name, w, h, params = cameras[cam_id]
        R = _qvec_to_rotmat(q)
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, t
        c2w = np.linalg.inv(w2c) @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera -> OpenGL camera
        coeffs: tuple[float, ...] | None = None
        if model_name == "SIMPLE_PINHOLE":
            fx = fy = params[0]; cx, cy = params[1], params[2]  # noqa: E702
        elif model_name == "PINHOLE":
            fx, fy, cx, cy = params[:4]
        elif model_name in _RADIAL_CV_MODELS:
            if model_name == "SIMPLE_RADIAL":
                fx = fy = params[0]; cx, cy = params[1], params[2]; coeffs = (params[3], 0.0, 0.0, 0.0)  # noqa: E702
            elif model_name == "RADIAL":
                fx = fy = params[0]; cx, cy = params[1], params[2]; coeffs = (params[3], params[4], 0.0, 0.0)  # noqa: E702
            elif model_name == "OPENCV":
                fx, fy, cx, cy = params[:4]; coeffs = tuple(params[4:8])  # noqa: E702
            else:  # FULL_OPENCV: k1 k2 p1 p2 k3 k4 k5 k6 (OpenCV's rational model order)
                fx, fy, cx, cy = params[:4]; coeffs = tuple(params[4:12])  # noqa: E702
            if distortion == "reject" and any(abs(c) > 0 for c in coeffs):
                raise SceneError(f"{cams_txt}: camera {cam_id} uses the distorted model {model_name} and "
                                 "distortion='reject'; undistort with `colmap image_undistorter` or pass distortion='undistort'")
        elif model_name in _FISHEYE_MODELS:
            raise SceneError(f"{cams_txt}: camera {cam_id} uses the fisheye model {model_name}, which is not supported; "
                             "run `colmap image_undistorter` and load the undistorted (PINHOLE) model")
        else:
            raise SceneError(f"{cams_txt}: camera {cam_id} has unknown model {model_name}")
        img_path = _resolve_image(image_dir, name, where)
        w_img, h_img = _image_size(img_path, where)
        if (w_img, h_img) != (w, h):
            raise SceneError(f"{where}: image {img_path} is {w_img}x{h_img} but camera {cam_id} in {cams_txt} is {w}x{h}")
        check_rigid_pose(c2w, where)
        c2ws.append(c2w)
        fxs.append(fx); fys.append(fy); cxs.append(cx); cys.append(cy); ws.append(w); hs.append(h)  # noqa: E702
        frames.append(Frame(name=name, image_path=img_path, distortion=coeffs if coeffs and any(coeffs) else None,
                            native_size=(w, h)))
    c2w = np.stack(c2ws) if c2ws else np.zeros((0, 4, 4))
    meta: dict = {"format": "colmap", "model": str(model)}
    pts = model / "points3D.txt"
    xyz, err = np.zeros((0, 3)), np.zeros(0)
    if pts.is_file():  # POINT3D_ID X Y Z R G B ERROR TRACK[]
        rows = [ln.split() for ln in pts.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
        xyz = np.array([[float(v) for v in r[1:4]] for r in rows]).reshape(-1, 3)
        err = np.array([float(r[7]) if len(r) > 7 else 0.0 for r in rows])
    good = np.isfinite(xyz).all(1) & (err < PLANE_MAX_REPROJ_PX)  # as dars poses: badly triangulated points
    record = _plan_upright(upright, np.stack(bounds_c2w) if bounds_c2w else np.zeros((0, 4, 4)),
                           xyz[good] if good.sum() >= 3 else None)
    meta["upright"] = record
    if record["applied"]:
        c2w = _rotate_world(c2w, record)
        bounds_c2w = list(_rotate_world(np.stack(bounds_c2w), record))
        xyz = xyz @ np.asarray(record["rotation"]).T
    if len(xyz) >= 10:
        lo, hi = np.percentile(xyz, 1, axis=0), np.percentile(xyz, 99, axis=0)
        pad = 0.1 * (hi - lo)
        meta["aabb"] = [(lo - pad).tolist(), (hi + pad).tolist()]
    box = (_scene_aabb(np.stack(bounds_c2w), np.array(bounds_fx), np.array(bounds_w), meta) if bounds_c2w
           else np.array([[-1.0] * 3, [1.0] * 3]))
    cams = _make_cameras(c2w, fxs, fys, cxs, cys, ws, hs, downscale)
    return Scene(source=model, split=split, cameras=cams, frames=tuple(frames), aabb=torch.tensor(box, dtype=torch.float32),
                 background=bg, downscale=downscale, srgb=True, meta=meta)


# ====================================================================== summary
def scene_info(path: str | Path) -> dict:
    """Everything ``dars info`` reports about a scene, as a dict (no pixels are decoded): frames, image size and
    ground-truth maps per split, format, intrinsics, box, near/far, the ground-truth light, the upright record."""
    path = Path(path)
    splits = list_splits(path)
    info: dict = {"scene": str(path), "splits": {}}
    first = None
    for s in splits:
        if s == "all" and len(splits) > 1 and "train" in splits:
            continue
        sc = load_scene(path, s)
        first = first or sc
        h, w = sc.image_size
        info["splits"][s] = {
            "frames": len(sc),
            "image_size": [w, h],
            "ground_truth": sc.extras_available(),
        }
    cams = first.cameras
    info["format"] = first.meta.get("format", "transforms json")
    info["source"] = str(first.source)
    info["intrinsics"] = {
        "fx": float(cams.fx[0]), "fy": float(cams.fy[0]), "cx": float(cams.cx[0]), "cy": float(cams.cy[0]),
        "shared": bool((cams.fx == cams.fx[0]).all() and (cams.cx == cams.cx[0]).all()),
        "distortion": first.frames[0].distortion is not None,
    }
    info["aabb"] = first.aabb.tolist()
    info["near_far"] = [first.near, first.far] if first.near is not None else None
    info["sh"] = first.sh.tolist() if first.sh is not None else None
    info["envmap"] = str(first.envmap_path) if first.envmap_path else None
    info["upright"] = first.meta.get("upright")
    return info


def photos_have_transparency(scene: "Scene", n: int = 3) -> bool:
    """Whether the photos are RGBA with real transparency (alpha < 1 somewhere in the first, middle or last
    photo): an object rendered on a known background. An alpha channel that is 255 everywhere does not count. With
    ``scene.masks == "alpha"`` the frames' masks are that alpha."""
    idx = sorted({0, len(scene) // 2, len(scene) - 1})[:n]
    if scene.masks == "alpha":
        return any(bool((scene.load_image(i, with_alpha=True)[3] < 0.999).any()) for i in idx)
    f0 = scene.frames[0]
    if f0.image_path is None or f0.image_path.suffix.lower() != ".png":
        return False
    from PIL import Image

    with Image.open(f0.image_path) as im:
        if im.mode not in ("RGBA", "LA"):
            return False
    return any(bool((scene.load_image(i, with_alpha=True)[3] < 0.999).any()) for i in idx)
