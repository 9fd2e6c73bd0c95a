"""Image and file I/O: reading PNG/JPEG/HDR/EXR/NPY maps, atomic writes.

Every writer in the toolkit goes through :func:`atomic_write` (write to a temporary file in the same
directory, then ``os.replace``; it lives in :mod:`toolkit.outputs` with the output-folder policy), so an interrupted
run never leaves a half-written file in place of a good one, and nothing is written over a file the caller did not
name. The readers turn a missing, empty, truncated or foreign file into a :class:`~toolkit._checks.DarsError` naming
it (:func:`read_json`, :func:`load_torch`, :func:`read_image`, :func:`read_hdr` ...).
"""

from __future__ import annotations

import io
import json
import os
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ._checks import SceneError
from .outputs import atomic_write

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
    "read_exr",
    "read_json",
    "load_torch",
    "check_torch_file",
    "srgb_to_linear",
    "linear_to_srgb",
]


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


def read_json(path: str | os.PathLike, what: str = "JSON file", fix: str = "", kind: type | None = dict) -> Any:
    """Parse a JSON file, turning every failure into a :class:`~toolkit._checks.DarsError` that names the file.

    Args:
        path: the file.
        what: what the file is, for messages (``"run config"``, ``"priors light.json"``).
        fix: what to do about a bad file (appended to the message).
        kind: the type the top level must have (``dict``, ``list``; None: any).

    Raises:
        DarsError: missing, unreadable, empty, not JSON, or another top-level type.
    """
    from ._checks import DarsError

    path = Path(path)
    tail = f"; {fix}" if fix else ""
    if not path.is_file():
        raise DarsError(f"{what} not found: {path}{tail}")
    try:
        text = path.read_bytes().decode("utf-8")
        obj = json.loads(text)
    except UnicodeDecodeError as e:
        raise DarsError(f"{what} {path} is not a text file (not UTF-8 JSON){tail}") from e
    except ValueError as e:
        detail = "it is empty" if not text.strip() else f"invalid JSON: {e}"
        raise DarsError(f"{what} {path} is corrupt ({detail}){tail}") from e
    if kind is not None and not isinstance(obj, kind):
        want = {dict: "an object {...}", list: "a list [...]"}.get(kind, kind.__name__)
        raise DarsError(f"{what} {path}: expected {want} at the top level, got {type(obj).__name__}{tail}")
    return obj


def load_torch(path: str | os.PathLike, what: str = "checkpoint", fix: str = "", map_location: Any = "cpu",
               weights_only: bool = False) -> Any:
    """``torch.load`` that turns a missing, empty, truncated or foreign file into a
    :class:`~toolkit._checks.DarsError` naming the file (``fix`` says what to do)."""
    import torch

    from ._checks import DarsError

    path = Path(path)
    check_torch_file(path, what, fix)
    try:
        return torch.load(path, map_location=map_location, weights_only=weights_only)
    except MemoryError:
        raise
    except Exception as e:  # noqa: BLE001 - pickle, zip and torch raise many types for a damaged file
        tail = f"; {fix}" if fix else ""
        raise DarsError(f"{what} {path} is corrupt ({path.stat().st_size} bytes; {_short(e)}){tail}") from e


def check_torch_file(path: str | os.PathLike, what: str = "checkpoint", fix: str = "") -> None:
    """A quick look (no tensors read) that ``path`` is a complete ``torch.save`` file: present, not empty, and its zip
    directory readable (a truncated file loses it). Lets a command refuse a damaged checkpoint before any work.

    Raises:
        DarsError: naming the file and ``fix``.
    """
    import zipfile

    from ._checks import DarsError

    path = Path(path)
    tail = f"; {fix}" if fix else ""
    if not path.is_file():
        raise DarsError(f"{what} not found: {path}{tail}")
    size = path.stat().st_size
    if size == 0:
        raise DarsError(f"{what} {path} is empty (0 bytes: the write was interrupted or the disk was full){tail}")
    try:
        with zipfile.ZipFile(path) as z:
            z.namelist()
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as e:
        raise DarsError(f"{what} {path} is truncated or corrupt ({size} bytes; {_short(e)}){tail}") from e


def _short(e: BaseException) -> str:
    """The first sentence of an exception's message (torch's run on for lines)."""
    text = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    return text.split(". ")[0][:120]


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as indented JSON, atomically."""
    with atomic_write(path, "w") as f:
        json.dump(obj, f, indent=2)
        f.write("\n")


def _cv2():
    import cv2

    return cv2


JPEG_REDUCTIONS = (8, 4, 2)
"""The factors libjpeg decodes a JPEG at directly (its scaled inverse DCT): ``read_image(..., reduce=k)``."""
JPEG_SUFFIXES = (".jpg", ".jpeg")
"""The files ``reduce`` applies to."""


def read_image(path: str | os.PathLike, what: str = "image", reduce: int = 1) -> np.ndarray:
    """Decode an image file to float32 H-W-C in [0, 1] (RGB or RGBA order; 8- or 16-bit aware).

    HDR formats (``.hdr``, ``.exr``) are returned unscaled (linear radiance). ``.npy`` files are loaded as is.

    Args:
        reduce: 2, 4 or 8 decodes a JPEG at that fraction of its size (``ceil(size / reduce)``; the DCT's own
            low-pass, several times faster than decoding 4000-px photos whole and shrinking them). Other files,
            and ``reduce=1``, decode whole. EXIF orientation is ignored either way, as the poses are for the
            stored pixels.

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
    img = cv2.imdecode(data, _decode_flag(cv2, path, reduce)) if data.size else None
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


def _decode_flag(cv2, path: Path, reduce: int) -> int:
    """OpenCV's imdecode flag: the file as stored, or a JPEG at 1/``reduce`` of its size."""
    if reduce == 1:
        return cv2.IMREAD_UNCHANGED
    if reduce not in JPEG_REDUCTIONS:
        raise ValueError(f"reduce must be 1 or one of {JPEG_REDUCTIONS}, got {reduce!r}")
    if path.suffix.lower() not in JPEG_SUFFIXES:
        return cv2.IMREAD_UNCHANGED
    return getattr(cv2, f"IMREAD_REDUCED_COLOR_{reduce}") | cv2.IMREAD_IGNORE_ORIENTATION


def read_map(path: str | os.PathLike, what: str = "map", reduce: int = 1) -> np.ndarray:
    """Read a per-pixel map keeping integer values (for labels): uint8/uint16 arrays H-W(-C) as stored.

    ``reduce`` (2, 4 or 8) decodes a JPEG (a mask) at that fraction of its size, as :func:`read_image` does; never
    use it on labels, whose values must not be blended."""
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
    img = cv2.imdecode(data, _decode_flag(cv2, path, reduce)) if data.size else None
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
    """Read a Radiance RGBE ``.hdr`` file to float32 H-W-3 linear RGB.

    Raises:
        SceneError: missing, empty or undecodable file, or one that is not Radiance HDR (an 8-bit PNG or JPEG renamed
            ``.hdr`` would otherwise decode to values in 0–255 with no light units), naming the file.
    """
    cv2 = _cv2()
    path = Path(path)
    data = np.fromfile(path, dtype=np.uint8) if path.is_file() else np.zeros(0, np.uint8)
    if data.size == 0:
        raise SceneError(f"HDR image not found or empty: {path}")
    head = data[:16].tobytes()
    if not head.startswith((b"#?RADIANCE", b"#?RGBE")):
        kind = _sniff_image_kind(head)
        what = f"{kind}, 8-bit: no light units" if kind else "no #?RADIANCE header"
        raise SceneError(f"{path} is not a Radiance HDR file ({what}); give a real .hdr or .exr environment map "
                         "(e.g. convert the original capture), not a renamed photo")
    img = cv2.imdecode(data, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
    if img is None:
        raise SceneError(f"HDR image {path} could not be decoded (a truncated or corrupt Radiance .hdr); re-export it")
    return img[..., ::-1].astype(np.float32).copy()


def _sniff_image_kind(head: bytes) -> str:
    """What the first bytes of a file say it is, for messages ("" when they say nothing known)."""
    for magic, name in ((b"\x89PNG", "it is a PNG image"), (b"\xff\xd8\xff", "it is a JPEG image"),
                        (b"BM", "it is a BMP image"), (b"II*\x00", "it is a TIFF image"),
                        (b"MM\x00*", "it is a TIFF image"), (b"v/1\x01", "it is an OpenEXR image")):
        if head.startswith(magic):
            return name
    return ""


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
    """Read an OpenEXR file to float32 H-W-C (OpenCV 5 has no EXR codec: uses ``OpenEXR`` or Mitsuba).

    Raises:
        SceneError: missing, empty, truncated or not OpenEXR, naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"EXR image not found: {path}")
    with open(path, "rb") as f:
        head = f.read(16)
    if not head.startswith(b"v/1\x01"):
        kind = "it is empty" if not head else _sniff_image_kind(head) or "no OpenEXR magic number"
        raise SceneError(f"{path} is not an OpenEXR file ({kind}); give a real .exr or .hdr environment map")
    try:
        return _read_exr(path)
    except SceneError:
        raise
    except Exception as e:  # noqa: BLE001 - the EXR libraries raise generic errors for damaged files
        raise SceneError(f"EXR image {path} could not be decoded ({e}); it may be truncated: re-export it") from e


def _read_exr(path: Path) -> np.ndarray:
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
