"""Image and file I/O: reading PNG/JPEG/HDR/EXR/NPY maps, atomic writes.

Every writer in the toolkit goes through :func:`atomic_write` (write to a temporary file in the same
directory, then ``os.replace``), so an interrupted run never leaves a half-written file in place of a good
one, and nothing is written over a file the caller did not name.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ._checks import SceneError

__all__ = [
    "atomic_write",
    "save_torch",
    "read_image",
    "read_map",
    "write_png",
    "encode_png",
    "write_json",
    "write_hdr",
    "read_hdr",
    "srgb_to_linear",
    "linear_to_srgb",
]


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb") -> Iterator[io.IOBase]:
    """Open a temporary file beside ``path`` and move it over ``path`` only when the block succeeds.

    Example:
        >>> with atomic_write("/tmp/x.txt", "w") as f:
        ...     _ = f.write("hello")
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def save_torch(path: str | os.PathLike, payload: Any) -> Path:
    """Write ``payload`` with ``torch.save``, atomically (serialised in memory first, so a failing pickle leaves
    nothing behind); returns the path. Every checkpoint and network file of the toolkit is written here.
    """
    import torch

    buf = io.BytesIO()
    torch.save(payload, buf)
    path = Path(path)
    with atomic_write(path) as f:
        f.write(buf.getvalue())
    return path


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as indented JSON, atomically."""
    with atomic_write(path, "w") as f:
        json.dump(obj, f, indent=2)
        f.write("\n")


def _cv2():
    import cv2

    return cv2


def read_image(path: str | os.PathLike, what: str = "image") -> np.ndarray:
    """Decode an image file to float32 H-W-C in [0, 1] (RGB or RGBA order; 8- or 16-bit aware).

    HDR formats (``.hdr``, ``.exr``) are returned unscaled (linear radiance). ``.npy`` files are loaded as is.

    Raises:
        SceneError: if the file is missing or cannot be decoded, naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{what} not found: {path}")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        try:
            arr = np.load(path)
        except Exception as e:  # noqa: BLE001 - any decode failure is a corrupt file
            raise SceneError(f"{what} {path} could not be read as .npy: {e}") from e
        arr = np.asarray(arr, dtype=np.float32)
        return arr[..., None] if arr.ndim == 2 else arr
    if suffix == ".hdr":
        return read_hdr(path)
    if suffix == ".exr":
        return read_exr(path)
    cv2 = _cv2()
    data = np.fromfile(path, dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise SceneError(f"{what} {path} is corrupt or not an image (could not decode {data.size} bytes); re-export it")
    if img.dtype == np.uint8:
        out = img.astype(np.float32) / 255.0
    elif img.dtype == np.uint16:
        out = img.astype(np.float32) / 65535.0
    else:
        out = img.astype(np.float32)
    if out.ndim == 2:
        return out[..., None]
    if out.shape[2] == 3:
        return out[..., ::-1].copy()
    if out.shape[2] == 4:
        return out[..., [2, 1, 0, 3]].copy()
    return out


def read_map(path: str | os.PathLike, what: str = "map") -> np.ndarray:
    """Read a per-pixel map keeping integer values (for labels): uint8/uint16 arrays H-W(-C) as stored."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{what} not found: {path}")
    if path.suffix.lower() == ".npy":
        try:
            return np.load(path)
        except Exception as e:  # noqa: BLE001
            raise SceneError(f"{what} {path} could not be read as .npy: {e}") from e
    cv2 = _cv2()
    data = np.fromfile(path, dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise SceneError(f"{what} {path} is corrupt or not an image; re-export it")
    if img.ndim == 3 and img.shape[2] >= 3:
        img = img[..., [2, 1, 0] + list(range(3, img.shape[2]))]
    return img


def encode_png(image_hwc: np.ndarray, bits: int = 8) -> bytes:
    """PNG bytes of an image (float in [0, 1] or integer; RGB(A) or grey). ``bits`` is 8 or 16 for float input."""
    cv2 = _cv2()
    img = np.asarray(image_hwc)
    if img.dtype.kind == "f":
        img = np.clip(np.nan_to_num(img), 0.0, 1.0)
        img = (img * (255 if bits == 8 else 65535) + 0.5).astype(np.uint8 if bits == 8 else np.uint16)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.ndim == 3 and img.shape[2] == 3:
        img = img[..., ::-1]
    elif img.ndim == 3 and img.shape[2] == 4:
        img = img[..., [2, 1, 0, 3]]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:
        raise OSError(f"could not encode a PNG of shape {list(np.shape(image_hwc))}")
    return buf.tobytes()


def write_png(path: str | os.PathLike, image_hwc: np.ndarray, bits: int = 8) -> None:
    """Write an image (float in [0, 1] or integer) as PNG, atomically. ``bits`` is 8 or 16 for float input."""
    data = encode_png(image_hwc, bits)
    with atomic_write(path) as f:
        f.write(data)


def read_hdr(path: str | os.PathLike) -> np.ndarray:
    """Read a Radiance RGBE ``.hdr`` file to float32 H-W-3 linear RGB."""
    cv2 = _cv2()
    path = Path(path)
    data = np.fromfile(path, dtype=np.uint8) if path.is_file() else np.zeros(0, np.uint8)
    if data.size == 0:
        raise SceneError(f"HDR image not found or empty: {path}")
    img = cv2.imdecode(data, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
    if img is None:
        raise SceneError(f"HDR image {path} could not be decoded (expected Radiance RGBE .hdr)")
    return img[..., ::-1].astype(np.float32).copy()


def write_hdr(path: str | os.PathLike, image_hwc: np.ndarray) -> None:
    """Write float linear RGB as a Radiance RGBE ``.hdr`` file, atomically."""
    cv2 = _cv2()
    img = np.ascontiguousarray(np.asarray(image_hwc, dtype=np.float32)[..., ::-1])
    ok, buf = cv2.imencode(".hdr", img)
    if not ok:
        raise OSError(f"could not encode HDR for {path}")
    with atomic_write(path) as f:
        f.write(buf.tobytes())


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """Read an OpenEXR file to float32 H-W-C (OpenCV 5 has no EXR codec: uses ``OpenEXR`` or Mitsuba)."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"EXR image not found: {path}")
    try:
        import OpenEXR  # type: ignore

        with OpenEXR.File(str(path)) as f:
            channels = f.channels()
            if "RGB" in channels:
                return np.asarray(channels["RGB"].pixels, dtype=np.float32)
            if "RGBA" in channels:
                return np.asarray(channels["RGBA"].pixels, dtype=np.float32)[..., :3]
            names = [n for n in ("R", "G", "B") if n in channels]
            if names:
                return np.stack([np.asarray(channels[n].pixels, dtype=np.float32) for n in names], -1)
            first = next(iter(channels.values()))
            arr = np.asarray(first.pixels, dtype=np.float32)
            return arr[..., None] if arr.ndim == 2 else arr
    except ImportError:
        pass
    try:
        import mitsuba as mi  # type: ignore

        mi.set_variant("scalar_rgb")
        return np.asarray(mi.Bitmap(str(path)).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32), dtype=np.float32)
    except ImportError as e:
        raise SceneError(f"reading {path} needs the OpenEXR or mitsuba package: pip install OpenEXR") from e


def srgb_to_linear(x):
    """sRGB transfer (IEC 61966-2-1) to linear; works on numpy arrays and torch tensors."""
    if isinstance(x, np.ndarray):
        x = np.clip(x, 0.0, None)
        return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
    import torch

    x = x.clamp_min(0.0)
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055).clamp_min(1e-8) ** 2.4)


def linear_to_srgb(x):
    """Linear to sRGB transfer (IEC 61966-2-1), clamped below at 0; numpy or torch."""
    if isinstance(x, np.ndarray):
        x = np.clip(x, 0.0, None)
        return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 1e-8), 1 / 2.4) - 0.055)
    import torch

    x = x.clamp_min(0.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-8) ** (1 / 2.4) - 0.055)
