"""Stage 0 — camera poses from a folder of photos (pycolmap), written as an upright scene dars reads directly.

:func:`estimate_poses` runs COLMAP through its maintained Python bindings (``pycolmap``, CPU SIFT):

1. **check the photos**: every image is decoded (JPEGs at 1/8 scale, fast) so corrupt files are named before any
   work; sizes and EXIF camera (make, model, focal length) group the photos into cameras;
2. **features**: SIFT per photo on images shrunk to ``max_size`` (keypoints in full-resolution pixels);
3. **matching**: all pairs (``exhaustive``) or each photo with the next ``overlap`` photos in name order plus
   quadratically spaced ones (``sequential``); ``auto`` picks exhaustive up to ``exhaustive_limit`` photos. Loop
   closure for long sequential captures needs a COLMAP vocabulary tree file given by the user (``vocab_tree``:
   nothing is downloaded). Matches are geometrically verified (two-view geometry);
4. **incremental mapping**; the model with the most registered photos is kept;
5. **undistortion** to PINHOLE cameras (images shrunk to ``max_size`` again);
6. **upright**: world up from the cameras and the dominant near-horizontal plane of the sparse points
   (:mod:`toolkit.upright`) is rotated to +z (SPEC). Only a rotation: the scale and centre stay COLMAP's (its mapper
   keeps models at a size of roughly ten units, numerically sane); fitting the centre and scale for training is
   done later, by the training stage, from the cameras and points. The applied transform is recorded so results
   can be mapped back to COLMAP's frame.

Output layout of ``out_dir`` (``SCENE_DIR``)::

    transforms.json      OpenGL camera-to-world, world +z up; fl_x fl_y cx cy w h shared (per frame when
                         cameras differ); file_path -> images/...; "ply_file_path": "sparse_pc.ply";
                         "dars_transform" (rotation, translation, scale: x_dars = scale * R @ x_colmap + t) and
                         nerfstudio's "applied_transform" (the same as 3x4)
    images/              the undistorted photos (same names as in PHOTOS_DIR)
    sparse_pc.ply        the sparse points (x y z + rgb) in the transforms' (upright) frame
    sparse/0/            the undistorted COLMAP model (text), in COLMAP's own frame, for reference
    colmap/              working data for --resume: database.db (features, matches), sparse/<k> (distorted models)
    dars_manifest.json   marks the folder as made by dars poses: configuration, photos, status, figures

The folder is never shared with the user's files: a non-empty ``out_dir`` without ``dars_manifest.json`` is refused
(``force`` writes beside them but never over them), and nothing is ever written into ``photos_dir``.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Literal

import numpy as np

from ._checks import ConfigError, DarsError, check_choice, check_range
from .outputs import MANIFEST
from .upright import PLANE_MAX_REPROJ_PX, UprightConfig, estimate_world_up, rotation_between

__all__ = [
    "PosesConfig",
    "PosesResult",
    "PosesError",
    "estimate_poses",
    "list_photos",
    "transforms_from_cameras",
    "MANIFEST_NAME",
    "PHOTO_EXTENSIONS",
    "CAMERA_MODELS",
]

MANIFEST_NAME = MANIFEST
"""The folder's mark (:data:`toolkit.outputs.MANIFEST`): besides the shared ``files`` list it holds the configuration,
photos, status and figures of the run."""
PHOTO_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")
_UNSUPPORTED_HINT = {".heic": "convert HEIC to JPEG", ".heif": "convert HEIF to JPEG", ".dng": "develop RAW to JPEG",
                     ".cr2": "develop RAW to JPEG", ".nef": "develop RAW to JPEG", ".arw": "develop RAW to JPEG",
                     ".webp": "convert WebP to JPEG or PNG"}
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV",
                 "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "OPENCV_FISHEYE", "FOV", "THIN_PRISM_FISHEYE")
"""COLMAP camera models for the photos (they are undistorted to PINHOLE in the output)."""
_OUTPUTS = ("transforms.json", "images", "sparse_pc.ply", "sparse", "colmap")
"""What dars poses writes into out_dir (besides the manifest)."""

Log = Callable[[str], None]


class PosesError(DarsError):
    """The photos cannot be posed (none, one, corrupt, unmatched) or the output folder cannot be used."""


@dataclass(frozen=True)
class PosesConfig:
    """Options of :func:`estimate_poses`."""

    matcher: Literal["auto", "exhaustive", "sequential"] = "auto"
    """Which pairs are matched: all (``exhaustive``), neighbours in name order (``sequential``), or ``auto``:
    exhaustive up to ``exhaustive_limit`` photos, sequential beyond."""
    max_size: int = 1600
    """Longest image side (px) for feature extraction and for the written undistorted images; 0 = full size."""
    camera_model: str = "SIMPLE_RADIAL"
    """COLMAP camera model of the photos (one of :data:`CAMERA_MODELS`)."""
    single_camera: bool | None = None
    """One camera for all photos (True), one per photo (False), or None: one per group of photos with the same
    size and EXIF make/model/focal length (a folder from one camera gets one)."""
    exhaustive_limit: int = 150
    """``auto`` matches exhaustively up to this many photos."""
    overlap: int = 10
    """Sequential matching: each photo is matched with the next ``overlap`` photos (and quadratically spaced ones)."""
    vocab_tree: str | None = None
    """Sequential matching: a COLMAP vocabulary-tree file (FAISS format, COLMAP >= 3.11, e.g.
    ``vocab_tree_faiss_flickr100K_words32K.bin``; given by the user, never downloaded: COLMAP would fetch one when
    loop detection runs without a path, so dars enables it only with this file) for loop closure. Without it a long
    sequential capture has no loop closure."""
    max_num_features: int = 8192
    """SIFT features per photo at most."""
    min_registered: float = 0.8
    """Fail (PosesError, naming the unregistered photos) when fewer than this fraction of the photos register."""
    upright: bool = True
    """Rotate the scene so that world up is +z (else COLMAP's orientation is kept and recorded)."""
    upright_cfg: UprightConfig = field(default_factory=UprightConfig)
    """How world up is estimated."""
    jpeg_quality: int = 95
    """Quality of the written (undistorted) JPEG images."""
    resume: bool = False
    """Reuse the database (features, matches) and model already in ``out_dir`` (made by an earlier run)."""
    force: bool = False
    """Start again in a dars folder (deleting its outputs), or write beside the files of a non-empty folder that
    dars did not make (never over them)."""
    num_threads: int = -1
    """CPU threads for COLMAP (-1 = all cores)."""
    seed: int = 0
    """Random seed of the mapper (COLMAP's RANSAC) and of the upright estimate."""
    progress: bool = False
    """tqdm progress bars on stderr."""
    colmap_log: bool = False
    """Show COLMAP's own log (glog, on stderr)."""

    def check(self) -> None:
        """Raise :class:`ConfigError` on an invalid option."""
        check_choice(self.matcher, ("auto", "exhaustive", "sequential"), "matcher")
        check_choice(self.camera_model, CAMERA_MODELS, "camera_model")
        if not isinstance(self.max_size, int) or not (self.max_size == 0 or self.max_size >= 100):
            raise ConfigError(f"max_size={self.max_size!r}: give the longest image side in pixels (>= 100), or 0 for full size")
        check_range(self.min_registered, 0.0, 1.0, "min_registered")
        if self.overlap < 1 or self.exhaustive_limit < 2 or self.max_num_features < 100:
            raise ConfigError(f"overlap ({self.overlap}) must be >= 1, exhaustive_limit ({self.exhaustive_limit}) >= 2, "
                              f"max_num_features ({self.max_num_features}) >= 100")
        if self.vocab_tree is not None and not Path(self.vocab_tree).is_file():
            raise ConfigError(f"vocab_tree={self.vocab_tree}: file not found (a COLMAP vocabulary tree you downloaded; "
                              "dars never downloads one)")
        check_range(self.jpeg_quality, 1, 100, "jpeg_quality")


@dataclass(frozen=True)
class PosesResult:
    """What :func:`estimate_poses` produced.

    Attributes:
        scene_dir: the output folder. transforms_path: its ``transforms.json``.
        names: registered photo names (relative to the photos folder), in frame order.
        c2w: float [N, 4, 4] OpenGL camera-to-world of those photos, upright frame (as written).
        num_photos: photos found. unregistered: photo name -> why it did not register.
        mean_reprojection_error: px (in the photos' full resolution). num_points: sparse points.
        num_cameras: COLMAP cameras. matcher: the matcher used. up_from: ``cameras``, ``cameras+plane`` or ``none``.
        transform: float [4, 4] the applied similarity (x_dars = T @ x_colmap). seconds: wall time.
        timings: seconds per step.
    """

    scene_dir: Path
    transforms_path: Path
    names: tuple[str, ...]
    c2w: np.ndarray
    num_photos: int
    unregistered: dict[str, str]
    mean_reprojection_error: float
    num_points: int
    num_cameras: int
    matcher: str
    up_from: str
    transform: np.ndarray
    seconds: float
    timings: dict[str, float]

    @property
    def num_registered(self) -> int:
        return len(self.names)

    def to_json(self) -> dict:
        return {"scene_dir": str(self.scene_dir), "transforms": str(self.transforms_path),
                "registered": self.num_registered, "photos": self.num_photos, "unregistered": self.unregistered,
                "mean_reprojection_error_px": self.mean_reprojection_error, "points": self.num_points,
                "cameras": self.num_cameras, "matcher": self.matcher, "up_from": self.up_from,
                "transform": self.transform.tolist(), "seconds": self.seconds, "timings": self.timings}


# ------------------------------------------------------------------------------------------------- photos
def _natural_key(name: str):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def list_photos(photos_dir: str | Path) -> tuple[list[str], dict[str, int]]:
    """Photo names under ``photos_dir`` (recursively, relative, ``/``-separated, natural order) and a count of the
    other files by extension (hidden files and folders are ignored)."""
    root = Path(photos_dir)
    names, other = [], {}
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for f in filenames:
            if f.startswith("."):
                continue
            ext = os.path.splitext(f)[1].lower()
            rel = (Path(dirpath) / f).relative_to(root).as_posix()
            if ext in PHOTO_EXTENSIONS:
                names.append(rel)
            else:
                other[ext or "(none)"] = other.get(ext or "(none)", 0) + 1
    return sorted(names, key=_natural_key), other


def _inspect_photo(path: Path) -> tuple[tuple, str | None]:
    """((width, height, make, model, focal), None) or ((), reason) when the file cannot be decoded."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            w, h = im.size
            make = model = focal = None
            try:
                exif = im.getexif()
                make, model = exif.get(271), exif.get(272)
                focal = exif.get_ifd(0x8769).get(37386)
                focal = float(focal) if focal is not None else None
            except Exception:  # noqa: BLE001 - a broken EXIF block only loses the camera grouping hint
                pass
            if im.format == "JPEG":
                im.draft("RGB", (max(1, w // 8), max(1, h // 8)))  # decode every block at 1/8 scale: fast
            im.load()
    except UnidentifiedImageError:
        return (), "not an image (unrecognised format)"
    except (OSError, SyntaxError, ValueError) as e:
        return (), f"corrupt or truncated ({e})"
    if w < 16 or h < 16:
        return (), f"too small ({w}x{h} px)"
    return (w, h, make, model, focal), None


def _camera_groups(names: list[str], signatures: dict[str, tuple], single: bool | None) -> list[list[str]]:
    if single is True:
        sizes = {signatures[n][:2] for n in names}
        if len(sizes) > 1:
            listing = ", ".join(f"{w}x{h}" for w, h in sorted(sizes))
            raise PosesError(f"--single-camera: the photos have {len(sizes)} different sizes ({listing}); one camera "
                             "cannot have several sizes: drop --single-camera (one camera per size/EXIF camera is the default)")
        return [list(names)]
    if single is False:
        return [[n] for n in names]
    groups: dict[tuple, list[str]] = {}
    for n in names:
        groups.setdefault(signatures[n], []).append(n)
    return list(groups.values())


# ------------------------------------------------------------------------------------------ output folder
def _read_manifest(out_dir: Path) -> dict | None:
    f = out_dir / MANIFEST_NAME
    if not f.is_file():
        return None
    try:
        m = json.loads(f.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return m if isinstance(m, dict) and m.get("dars") == "poses" else None


def _write_manifest(out_dir: Path, manifest: dict) -> None:
    manifest["updated"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
    # what dars owns here, in the shared manifest form (toolkit.outputs): other commands may then write beside
    manifest["files"] = sorted(f"{n}/" if n in ("images", "sparse", "colmap") else n for n in _OUTPUTS)
    tmp = out_dir / (MANIFEST_NAME + ".tmp")
    tmp.write_text(json.dumps(manifest, indent=2))
    tmp.replace(out_dir / MANIFEST_NAME)


def _is_within(path: Path, parent: Path) -> bool:
    try:
        path.relative_to(parent)
        return True
    except ValueError:
        return False


def _check_out_dir(out_dir: Path, photos_dir: Path, cfg: PosesConfig) -> tuple[dict | None, list[Path]]:
    """Check that dars may write into ``out_dir`` (no side effects).

    Returns:
        the folder's previous manifest when resuming (else None), and the paths ``force`` will delete (dars's own
        outputs in a folder dars made).
    """
    out_r, photos_r = out_dir.resolve(), photos_dir.resolve()
    if out_r == photos_r or _is_within(out_r, photos_r):
        raise PosesError(f"--out {out_dir} is inside the photos folder {photos_dir}: dars never writes into the "
                         "photos' folder; choose an output folder outside it")
    if _is_within(photos_r, out_r):
        first = photos_r.relative_to(out_r).parts[0]
        if first in _OUTPUTS or first == MANIFEST_NAME:
            raise PosesError(f"the photos folder {photos_dir} is {out_dir}/{first}, which dars poses writes: move the "
                             f"photos to another folder (e.g. {out_dir}/photos) or choose another --out")
    if out_dir.exists() and not out_dir.is_dir():
        raise PosesError(f"--out {out_dir} exists and is not a folder")
    manifest = _read_manifest(out_dir) if out_dir.is_dir() else None
    if manifest is not None:
        if cfg.resume:
            return manifest, []
        if cfg.force:
            return None, [out_dir / n for n in _OUTPUTS if (out_dir / n).exists() or (out_dir / n).is_symlink()]
        raise PosesError(f"{out_dir} already holds a dars poses scene (status: {manifest.get('status', '?')}): "
                         "pass --resume to reuse its features, matches and model, or --force to start again "
                         f"(deletes its {', '.join(_OUTPUTS)})")
    entries = [p for p in out_dir.iterdir() if p.resolve() != photos_r] if out_dir.is_dir() else []
    if cfg.resume and out_dir.is_dir():
        raise PosesError(f"--resume: {out_dir} was not made by dars poses (no {MANIFEST_NAME}): nothing to resume")
    if entries:
        if not cfg.force:
            shown = ", ".join(sorted(p.name for p in entries)[:5]) + (", ..." if len(entries) > 5 else "")
            raise PosesError(f"--out {out_dir} is not empty ({shown}) and was not made by dars (no {MANIFEST_NAME}): "
                             "refusing to write there; choose a new or empty folder, or --force to add dars's files "
                             "beside the existing ones (existing files are never overwritten)")
        clash = [name for name in _OUTPUTS if (out_dir / name).exists()]
        if clash:
            raise PosesError(f"--force: {out_dir} already has {', '.join(clash)}, which dars poses would write, and "
                             f"was not made by dars (no {MANIFEST_NAME}); dars never overwrites your files: move them "
                             "away or choose another --out")
    return None, []


def _remove(paths: list[Path]) -> None:
    for p in paths:
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()


# ------------------------------------------------------------------------------------------ pycolmap helpers
def _import_pycolmap():
    try:
        import pycolmap
    except ImportError as e:
        raise PosesError("dars poses needs pycolmap (the COLMAP bindings): pip install 'dars-toolkit[poses]' "
                         f"or run `make install` ({e})") from e
    return pycolmap


def _bar(cfg: PosesConfig, desc: str, total: int | None, unit: str = "it"):
    import sys

    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, disable=not cfg.progress or total == 0, leave=False,
                dynamic_ncols=True)


def _run_cancellable(pycolmap, fn: Callable, bar=None, what: str = "COLMAP"):
    """Run ``fn(token)`` (a pycolmap call; it releases the GIL) in a thread so Ctrl-C cancels it and the bar ticks."""
    token = pycolmap.CancellationToken()
    box: dict = {}
    done = threading.Event()  # not Thread.join: on Python 3.11 a join interrupted by Ctrl-C may not wait again

    def target():
        try:
            box["value"] = fn(token)
        except BaseException as e:  # noqa: BLE001 - re-raised in the caller's thread
            box["error"] = e
        finally:
            done.set()

    threading.Thread(target=target, daemon=True, name=f"dars-{what}").start()
    try:
        while not done.wait(0.25):
            if bar is not None:
                bar.refresh()
    except KeyboardInterrupt:
        token.cancel()  # COLMAP stops at its next check; the interpreter must not exit while it runs
        while True:
            try:
                if done.wait(0.25):
                    break
            except KeyboardInterrupt:
                continue
        raise
    if "error" in box:
        e = box["error"]
        raise PosesError(f"{what} failed in pycolmap: {type(e).__name__}: {e}") from e
    return box.get("value")


def _db_images(pycolmap, db_path: Path) -> dict[str, tuple[int, int, int]]:
    """name -> (image_id, camera_id, number of keypoints) for the images in the database."""
    out = {}
    with pycolmap.Database.open(db_path) as db:
        for im in db.read_all_images():
            out[im.name] = (im.image_id, im.camera_id, db.num_keypoints_for_image(im.image_id))
    return out


def _extract(pycolmap, db_path, photos_dir, names, signatures, cfg: PosesConfig, log: Log) -> int:
    have = _db_images(pycolmap, db_path) if db_path.is_file() else {}
    todo = [n for n in names if have.get(n, (0, 0, 0))[2] == 0]
    groups = _camera_groups(names, signatures, cfg.single_camera)
    eo = pycolmap.FeatureExtractionOptions()
    eo.max_image_size = cfg.max_size if cfg.max_size > 0 else -1
    eo.num_threads = cfg.num_threads
    eo.sift.max_num_features = cfg.max_num_features
    if len(todo) < len(names):
        log(f"features: {len(names) - len(todo)} photos already in the database, extracting {len(todo)}")
    chunk = max(4, 2 * (os.cpu_count() or 1))
    todo_set = set(todo)
    with _bar(cfg, "features", len(todo), "photo") as bar:
        for group in groups:
            g_todo = [n for n in group if n in todo_set]
            shared = len(group) > 1
            cam_id = next((have[n][1] for n in group if n in have and have[n][2] > 0), -1) if shared else -1
            for k in range(0, len(g_todo), chunk):
                part = g_todo[k:k + chunk]
                ro = pycolmap.ImageReaderOptions()
                ro.camera_model = cfg.camera_model
                if cam_id >= 0:
                    ro.existing_camera_id = int(cam_id)
                mode = pycolmap.CameraMode.SINGLE if shared else pycolmap.CameraMode.PER_IMAGE
                _run_cancellable(pycolmap, lambda tok, part=part, ro=ro, mode=mode: pycolmap.extract_features(
                    db_path, photos_dir, image_names=part, camera_mode=mode, reader_options=ro,
                    extraction_options=eo, cancellation_token=tok), bar, "feature extraction")
                if shared and cam_id < 0:
                    got = _db_images(pycolmap, db_path)
                    cam_id = next((got[n][1] for n in part if n in got), -1)
                bar.update(len(part))
    return len(groups)


def _pairs(names: list[str], matcher: str, overlap: int) -> list[tuple[str, str]]:
    n = len(names)
    if matcher == "exhaustive":
        return [(names[i], names[j]) for i in range(n) for j in range(i + 1, n)]
    steps = sorted(set(range(1, overlap + 1)) | {2 ** k for k in range(overlap)})  # COLMAP's quadratic overlap
    return [(names[i], names[i + s]) for i in range(n) for s in steps if i + s < n]


def _match(pycolmap, db_path: Path, work: Path, names: list[str], matcher: str, cfg: PosesConfig, log: Log) -> int:
    ids = {n: v[0] for n, v in _db_images(pycolmap, db_path).items()}
    pairs = [(a, b) for a, b in _pairs(names, matcher, cfg.overlap) if a in ids and b in ids]
    with pycolmap.Database.open(db_path) as db:
        todo = [(a, b) for a, b in pairs if not db.exists_two_view_geometry(ids[a], ids[b])]
    if len(todo) < len(pairs):
        log(f"matching: {len(pairs) - len(todo)} of {len(pairs)} pairs already matched")
    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = cfg.num_threads
    sp = pycolmap.SequentialPairingOptions()
    sp.overlap = cfg.overlap
    if cfg.vocab_tree:
        sp.loop_detection = True
        sp.vocab_tree_path = Path(cfg.vocab_tree)
    if any(c.isspace() for n in names for c in n):
        # COLMAP's pair lists are space-separated: let its own matchers pair the photos (no per-pair progress; its
        # sequential order is the plain name order)
        with _bar(cfg, f"matching ({matcher}, COLMAP's pairing: names with spaces)", None) as bar:
            _run_cancellable(pycolmap, lambda tok: pycolmap.match_exhaustive(
                db_path, matching_options=mo, cancellation_token=tok) if matcher == "exhaustive" else
                pycolmap.match_sequential(db_path, matching_options=mo, pairing_options=sp, cancellation_token=tok),
                bar, "feature matching")
        return len(pairs)
    chunk = int(np.clip(len(todo) // 50, 32, 512))
    pairs_file = work / "pairs.txt"
    with _bar(cfg, f"matching ({matcher})", len(todo), "pair") as bar:
        for k in range(0, len(todo), chunk):
            part = todo[k:k + chunk]
            pairs_file.write_text("".join(f"{a} {b}\n" for a, b in part))
            po = pycolmap.ImportedPairingOptions()
            po.match_list_path = pairs_file
            _run_cancellable(pycolmap, lambda tok, po=po: pycolmap.match_image_pairs(
                db_path, matching_options=mo, pairing_options=po, cancellation_token=tok), bar, "feature matching")
            bar.update(len(part))
    pairs_file.unlink(missing_ok=True)
    if matcher == "sequential" and cfg.vocab_tree:  # the neighbours are matched: this adds the loop pairs
        with _bar(cfg, "loop closure (vocabulary tree)", None) as bar:
            _run_cancellable(pycolmap, lambda tok: pycolmap.match_sequential(
                db_path, matching_options=mo, pairing_options=sp, cancellation_token=tok), bar, "loop detection")
    return len(pairs)


def _map(pycolmap, db_path: Path, photos_dir: Path, sparse_dir: Path, n_photos: int, cfg: PosesConfig):
    if sparse_dir.exists():
        shutil.rmtree(sparse_dir)
    sparse_dir.mkdir(parents=True)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = cfg.num_threads
    opts.random_seed = cfg.seed
    opts.min_model_size = int(min(10, max(2, n_photos // 4)))
    with _bar(cfg, "mapping", n_photos, "photo") as bar:
        def on_image():
            bar.update(1)
        maps = _run_cancellable(pycolmap, lambda tok: pycolmap.incremental_mapping(
            db_path, photos_dir, sparse_dir, options=opts, next_image_callback=on_image, cancellation_token=tok),
            bar, "incremental mapping")
    return maps or {}


def _load_models(pycolmap, sparse_dir: Path) -> dict:
    models = {}
    if sparse_dir.is_dir():
        for d in sorted(sparse_dir.iterdir()):
            if d.is_dir() and d.name.isdigit() and any((d / f).is_file() for f in ("images.bin", "images.txt")):
                models[int(d.name)] = pycolmap.Reconstruction(d)
    return models


def _diagnose(pycolmap, db_path: Path, names: list[str], models: dict, best: int | None,
              min_inliers: int = 15, few_features: int = 200) -> dict[str, str]:
    """Why each photo outside the kept model did not register."""
    info = _db_images(pycolmap, db_path)
    by_id = {v[0]: n for n, v in info.items()}
    model_of: dict[str, int] = {}
    for k, rec in models.items():
        for im in rec.images.values():
            if im.has_pose:
                model_of.setdefault(im.name, k)
    with pycolmap.Database.open(db_path) as db:
        pair_ids, inliers = db.read_two_view_geometry_num_inliers()
    best_match: dict[str, tuple[int, str]] = {}
    links: dict[str, set[str]] = {n: set() for n in names}
    for pid, m in zip(pair_ids, inliers):
        a, b = (by_id.get(i) for i in pycolmap.pair_id_to_image_pair(pid))
        if a is None or b is None:
            continue
        for x, y in ((a, b), (b, a)):
            if m > best_match.get(x, (0, ""))[0]:
                best_match[x] = (int(m), y)
            if m >= min_inliers:
                links.setdefault(x, set()).add(y)
    reasons = {}
    for n in names:
        if best is not None and model_of.get(n) == best:
            continue
        kp = info.get(n, (0, 0, 0))[2]
        bm = best_match.get(n)
        best_txt = f"best: {bm[0]} inliers with {bm[1]}" if bm else "no match at all"
        if n not in info:
            reasons[n] = "not read by COLMAP (unsupported or corrupt image)"
        elif kp < few_features:
            reasons[n] = f"too few features ({kp} SIFT keypoints; blurred, dark, overexposed or textureless?)"
        elif not links.get(n):
            reasons[n] = f"no verified matches with any other photo ({kp} features; {best_txt})"
        elif n in model_of:
            size = sum(1 for v in model_of.values() if v == model_of[n])
            reasons[n] = (f"registered in a separate group of {size} photos (model {model_of[n]}) that shares too "
                          "few matches with the main one")
        elif best is not None and not any(model_of.get(m) == best for m in links[n]):
            others = sorted(links[n], key=_natural_key)
            shown = ", ".join(others[:3]) + (f" and {len(others) - 3} more" if len(others) > 3 else "")
            reasons[n] = f"matches only other unregistered photos ({shown}; {best_txt})"
        else:
            reasons[n] = (f"matched {len(links[n])} photos ({best_txt}) but its pose could not be estimated "
                          "(too few matches to triangulated points)")
    return reasons


def _undistort(pycolmap, model_dir: Path, photos_dir: Path, staging: Path, cfg: PosesConfig):
    if staging.exists():
        shutil.rmtree(staging)
    uo = pycolmap.UndistortCameraOptions()
    uo.max_image_size = cfg.max_size if cfg.max_size > 0 else -1
    names = sorted((im.name for im in pycolmap.Reconstruction(model_dir).images.values() if im.has_pose), key=_natural_key)
    chunk = max(4, 2 * (os.cpu_count() or 1))
    with _bar(cfg, "undistortion", len(names), "photo") as bar:
        for k in range(0, len(names), chunk):  # in chunks for the progress bar; every call writes the whole model
            part = names[k:k + chunk]
            _run_cancellable(pycolmap, lambda tok, part=part: pycolmap.undistort_images(
                staging, model_dir, photos_dir, image_names=part, output_type="COLMAP", undistort_options=uo,
                jpeg_quality=cfg.jpeg_quality, num_threads=cfg.num_threads, cancellation_token=tok), bar, "undistortion")
            bar.update(len(part))
    return pycolmap.Reconstruction(staging / "sparse")


# ----------------------------------------------------------------------------------------- transforms
_GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _reconstruction_arrays(rec):
    """Registered images of a (PINHOLE) reconstruction: names, OpenGL c2w [N,4,4], intrinsics [N,6]
    (fx fy cx cy w h), points [P,3], colours uint8 [P,3], reprojection errors [P] (px), in the reconstruction's
    frame and natural name order."""
    rows = []
    for im in rec.images.values():
        if not im.has_pose:
            continue
        cfw = im.cam_from_world()
        w2c = np.eye(4)
        w2c[:3, :3] = cfw.rotation.matrix()
        w2c[:3, 3] = cfw.translation
        cam = rec.cameras[im.camera_id]
        p = list(cam.params)
        if cam.model.name == "SIMPLE_PINHOLE":
            fx = fy = p[0]
            cx, cy = p[1], p[2]
        elif cam.model.name == "PINHOLE":
            fx, fy, cx, cy = p[:4]
        else:
            raise PosesError(f"internal: undistorted camera {im.camera_id} has model {cam.model.name}, expected PINHOLE")
        rows.append((im.name, np.linalg.inv(w2c) @ _GL_FROM_CV, (fx, fy, cx, cy, cam.width, cam.height)))
    rows.sort(key=lambda r: _natural_key(r[0]))
    names = [r[0] for r in rows]
    c2w = np.stack([r[1] for r in rows]) if rows else np.zeros((0, 4, 4))
    intr = np.array([r[2] for r in rows], dtype=np.float64).reshape(-1, 6)
    pts = list(rec.points3D.values())
    xyz = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3)
    err = np.array([p.error for p in pts], dtype=np.float64).reshape(-1)
    return names, c2w, intr, xyz, rgb, err


def transforms_from_cameras(names, c2w, intrinsics, image_dir: str = "images", extra: dict | None = None) -> dict:
    """A nerfstudio / instant-ngp ``transforms.json`` document for pinhole cameras.

    Args:
        names: N image names relative to ``image_dir``.
        c2w: float [N, 4, 4] OpenGL camera-to-world.
        intrinsics: float [N, 6] ``fx fy cx cy w h`` in pixels. Shared values go to the top level; when the cameras
            differ, every frame carries its own.
        image_dir: folder of the images, relative to the JSON.
        extra: more top-level keys (e.g. ``ply_file_path``, ``dars_transform``).

    Returns:
        the JSON-ready dict (``camera_model`` ``PINHOLE``, ``frames`` with ``file_path`` and ``transform_matrix``).
    """
    c2w = np.asarray(c2w, np.float64)
    intr = np.asarray(intrinsics, np.float64).reshape(-1, 6)
    if c2w.shape != (len(names), 4, 4) or len(intr) != len(names):
        raise PosesError(f"transforms_from_cameras: {len(names)} names, c2w {list(c2w.shape)}, intrinsics {list(intr.shape)}")
    keys = ("fl_x", "fl_y", "cx", "cy", "w", "h")

    def values(row):
        return {k: (int(round(v)) if k in ("w", "h") else float(v)) for k, v in zip(keys, row)}

    shared = len(intr) > 0 and bool(np.allclose(intr, intr[0], rtol=0, atol=1e-9))
    doc: dict = {"camera_model": "PINHOLE"}
    if shared:
        doc.update(values(intr[0]))
    frames = []
    for name, m, row in zip(names, c2w, intr):
        fm = {"file_path": f"{image_dir}/{name}" if image_dir else name}
        if not shared:
            fm.update(values(row))
        fm["transform_matrix"] = [[float(v) for v in r] for r in m]
        frames.append(fm)
    doc.update(extra or {})
    doc["frames"] = frames
    return doc


def _write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Binary little-endian PLY with float x y z and uchar red green blue (what nerfstudio's ply_file_path reads)."""
    rec = np.empty(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec["r"], rec["g"], rec["b"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(xyz)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(rec.tobytes())


# ----------------------------------------------------------------------------------------------- the stage
def _fmt_time(s: float) -> str:
    return f"{s:.1f} s" if s < 60 else f"{int(s // 60)} min {s % 60:02.0f} s"


def _advice(cfg: PosesConfig, matcher: str, longest_side: int) -> str:
    tips = ["photos with more overlap (each part of the scene in 3+ photos, consecutive shots sharing most of the view)"]
    if matcher != "exhaustive":
        tips.append("--matcher exhaustive (matches every pair, not only neighbours in name order)")
    if cfg.max_size and cfg.max_size < longest_side:
        tips.append(f"a larger --max-size (now {cfg.max_size}; 0 = full resolution) for more features")
    tips.append("removing photos of other scenes")
    return "what to try: " + "; ".join(tips)


def _listing(reasons: dict[str, str], limit: int = 20) -> str:
    lines = [f"  {n}: {r}" for n, r in list(reasons.items())[:limit]]
    if len(reasons) > limit:
        lines.append(f"  ... and {len(reasons) - limit} more (all in {MANIFEST_NAME})")
    return "\n".join(lines)


def estimate_poses(photos_dir: str | Path, out_dir: str | Path, cfg: PosesConfig = PosesConfig(),
                   log: Log | None = None) -> PosesResult:
    """Camera poses from a folder of photos: a scene dars reads directly (see the module docstring for the layout).

    Args:
        photos_dir: folder of photos (JPEG, PNG, TIFF, BMP; subfolders included). Never written to.
        out_dir: output folder; created, or empty, or made by an earlier ``dars poses`` (then ``resume`` or
            ``force``), or any folder with ``force`` (files written beside, never over, the existing ones).
        cfg: see :class:`PosesConfig`.
        log: called with one line per event (progress bars are separate: ``cfg.progress``).

    Returns:
        :class:`PosesResult`. Runs on the CPU (the PyPI pycolmap wheels have no GPU support).

    Raises:
        PosesError: no photos, one photo, corrupt photos (named), an output folder dars may not use, or fewer than
            ``cfg.min_registered`` of the photos registered (each unregistered photo named with the reason and what
            to try; the features and matches are kept for ``resume``).
        ConfigError: an invalid option.
    """
    t_start = time.perf_counter()
    log = log or (lambda msg: None)
    cfg.check()
    photos_dir, out_dir = Path(photos_dir), Path(out_dir)
    if not photos_dir.is_dir():
        raise PosesError(f"photos folder not found: {photos_dir}")
    names, other = list_photos(photos_dir)
    if not names:
        found = ", ".join(f"{c} {e}" for e, c in sorted(other.items())) or "no files"
        hints = sorted({_UNSUPPORTED_HINT[e] for e in other if e in _UNSUPPORTED_HINT})
        raise PosesError(f"no photos in {photos_dir} (looked for {' '.join(PHOTO_EXTENSIONS)}; found {found})"
                         + (f": {'; '.join(hints)}" if hints else ""))
    if len(names) == 1:
        raise PosesError(f"only one photo in {photos_dir} ({names[0]}): poses need at least 2 photos of the same "
                         "scene from different positions (20 or more, overlapping, for a room)")
    skipped = {e: c for e, c in other.items() if e in _UNSUPPORTED_HINT}
    if skipped:
        log("skipping " + ", ".join(f"{c} {e} files ({_UNSUPPORTED_HINT[e]})" for e, c in skipped.items()))

    previous, stale = _check_out_dir(out_dir, photos_dir, cfg)

    timings: dict[str, float] = {}
    t = time.perf_counter()
    signatures, bad = {}, {}
    with _bar(cfg, "checking photos", len(names), "photo") as bar:
        for n in names:
            sig, why = _inspect_photo(photos_dir / n)
            if why:
                bad[n] = why
            else:
                signatures[n] = sig
            bar.update(1)
    if bad:
        raise PosesError(f"{len(bad)} of {len(names)} photos in {photos_dir} cannot be read:\n{_listing(bad)}\n"
                         "re-export them or move them out of the folder")
    timings["check"] = time.perf_counter() - t

    pycolmap = _import_pycolmap()
    _remove(stale)  # --force in a dars folder: its own outputs only
    matcher = cfg.matcher if cfg.matcher != "auto" else ("exhaustive" if len(names) <= cfg.exhaustive_limit else "sequential")
    db_config = {"max_size": cfg.max_size, "camera_model": cfg.camera_model, "single_camera": cfg.single_camera,
                 "max_num_features": cfg.max_num_features}
    if previous is not None:
        old = previous.get("database_config", {})
        diff = {k: (old.get(k), v) for k, v in db_config.items() if k in old and old[k] != v}
        if diff:
            listing = ", ".join(f"{k}: {a} then, {b} now" for k, (a, b) in diff.items())
            raise PosesError(f"--resume: {out_dir} was made with other feature options ({listing}); pass the same "
                             "options, or --force to start again")
    out_dir.mkdir(parents=True, exist_ok=True)
    work = out_dir / "colmap"
    work.mkdir(exist_ok=True)
    manifest = {"dars": "poses", "format": 1, "status": "running",
                "created": (previous or {}).get("created", datetime.now(timezone.utc).isoformat(timespec="seconds")),
                "photos_dir": str(photos_dir.resolve()), "photos": names, "database_config": db_config,
                "config": {"matcher": matcher, "overlap": cfg.overlap, "vocab_tree": cfg.vocab_tree,
                           "min_registered": cfg.min_registered, "upright": cfg.upright, "seed": cfg.seed},
                "pycolmap": getattr(pycolmap, "__version__", "?")}
    _write_manifest(out_dir, manifest)
    log_level = pycolmap.logging.minloglevel
    if not cfg.colmap_log:
        pycolmap.logging.minloglevel = 2  # errors only: dars prints its own summary and progress
    try:
        return _pose_pipeline(pycolmap, photos_dir, out_dir, names, signatures, previous, manifest, matcher, cfg,
                              log, t_start, timings)
    except KeyboardInterrupt:
        manifest["status"] = "interrupted"
        _write_manifest(out_dir, manifest)
        log(f"interrupted: rerun with --resume to continue from the features and matches saved in {out_dir}")
        raise
    finally:
        pycolmap.logging.minloglevel = log_level


def _pose_pipeline(pycolmap, photos_dir: Path, out_dir: Path, names: list[str], signatures: dict, previous: dict | None,
                   manifest: dict, matcher: str, cfg: PosesConfig, log: Log, t_start: float,
                   timings: dict[str, float]) -> PosesResult:
    """Steps 2-6 of :func:`estimate_poses` (features to transforms.json), once the photos and the folder are checked."""
    work = out_dir / "colmap"
    db_path = work / "database.db"

    t = time.perf_counter()
    n_cameras = _extract(pycolmap, db_path, photos_dir, names, signatures, cfg, log)
    info = _db_images(pycolmap, db_path)
    missing = [n for n in names if n not in info]
    if missing:
        raise PosesError(f"COLMAP could not read {len(missing)} photos: {', '.join(missing[:20])}"
                         f"{' ...' if len(missing) > 20 else ''}; re-export them as JPEG or PNG or move them out")
    timings["features"] = time.perf_counter() - t
    kp = np.array([info[n][2] for n in names])
    log(f"features: {int(np.median(kp))} per photo (median; min {kp.min()} in {names[int(kp.argmin())]}), "
        f"{n_cameras} camera{'s' if n_cameras > 1 else ''} ({cfg.camera_model})")

    t = time.perf_counter()
    n_pairs = _match(pycolmap, db_path, work, names, matcher, cfg, log)
    timings["matching"] = time.perf_counter() - t
    if matcher == "sequential" and not cfg.vocab_tree:
        log(f"matching: sequential (overlap {cfg.overlap}) without loop closure; a COLMAP vocabulary-tree file "
            "(--vocab-tree) adds it")

    t = time.perf_counter()
    sparse_dir = work / "sparse"
    reuse = previous is not None and previous.get("photos") == names and previous.get("mapped", False)
    models = _load_models(pycolmap, sparse_dir) if (cfg.resume and reuse) else {}
    if models:
        log(f"mapping: reusing the {len(models)} model(s) in {sparse_dir}")
    else:
        _map(pycolmap, db_path, photos_dir, sparse_dir, len(names), cfg)
        models = _load_models(pycolmap, sparse_dir)
    timings["mapping"] = time.perf_counter() - t
    best = max(models, key=lambda k: models[k].num_reg_images()) if models else None
    longest = max(max(sig[:2]) for sig in signatures.values())
    reasons = _diagnose(pycolmap, db_path, names, models, best)
    n_reg = models[best].num_reg_images() if best is not None else 0
    manifest.update(unregistered=reasons, model=best, timings=timings, mapped=True)
    if n_reg < 2 or n_reg < cfg.min_registered * len(names):
        manifest["status"] = "failed"
        _write_manifest(out_dir, manifest)
        head = (f"no reconstruction from {len(names)} photos: no pair of photos had enough verified matches to start"
                if n_reg < 2 else
                f"registered only {n_reg} of {len(names)} photos ({100 * n_reg / len(names):.0f} % < "
                f"--min-registered {cfg.min_registered:g})")
        keep = (f"the features and matches are kept in {work}: rerun with --resume"
                + (f" --min-registered {math.floor(100 * n_reg / len(names)) / 100:g} to accept the {n_reg} registered photos"
                   if n_reg >= 2 else ""))
        raise PosesError(f"{head}; these did not register:\n{_listing(reasons)}\n{_advice(cfg, matcher, longest)}\n{keep}")
    rec = models[best]
    reproj = float(rec.compute_mean_reprojection_error())

    t = time.perf_counter()
    und = _undistort(pycolmap, sparse_dir / str(best), photos_dir, work / "undistorted", cfg)
    names_reg, c2w, intr, xyz, rgb, err = _reconstruction_arrays(und)
    timings["undistortion"] = time.perf_counter() - t

    transform = np.eye(4)
    up_from = "none"
    if cfg.upright:
        good = err < PLANE_MAX_REPROJ_PX  # drop badly triangulated points before the plane fit
        up = estimate_world_up(c2w, xyz[good] if good.sum() >= 3 else None, cfg.upright_cfg)
        transform[:3, :3] = rotation_between(up.up, [0.0, 0.0, 1.0])
        up_from = up.source
        plane = ""
        if up.plane_normal is not None:
            plane = (f"; floor/plane normal {up.plane_angle_deg:.1f} deg from the camera up, "
                     f"{100 * up.plane_fraction:.0f} % of the points")
            if up.source != "cameras+plane":
                plane += f", not used: level cameras allow {up.plane_tolerance_deg:.1f} deg"
        log(f"upright: world up from {up.source} ({up.camera_inliers}/{len(c2w)} cameras agree{plane})")
    c2w_out = transform[None] @ c2w
    xyz_out = xyz @ transform[:3, :3].T + transform[:3, 3]

    _remove([out_dir / n for n in ("images", "sparse", "transforms.json", "sparse_pc.ply")])  # ours (checked above)
    (work / "undistorted" / "images").rename(out_dir / "images")
    (out_dir / "sparse" / "0").mkdir(parents=True)
    und.write_text(out_dir / "sparse" / "0")
    shutil.rmtree(work / "undistorted")
    _write_ply(out_dir / "sparse_pc.ply", xyz_out, rgb)
    record = {"rotation": transform[:3, :3].tolist(), "translation": transform[:3, 3].tolist(), "scale": 1.0,
              "source": "colmap", "up_from": up_from, "colmap_model": "sparse/0",
              "maps": "x_dars = scale * rotation @ x_colmap + translation; c2w_dars = T @ c2w_colmap (OpenGL)"}
    doc = transforms_from_cameras(names_reg, c2w_out, intr, "images", extra={
        "ply_file_path": "sparse_pc.ply", "dars_transform": record, "applied_transform": transform[:3].tolist()})
    transforms_path = out_dir / "transforms.json"
    transforms_path.write_text(json.dumps(doc, indent=2))

    seconds = time.perf_counter() - t_start
    result = PosesResult(scene_dir=out_dir, transforms_path=transforms_path, names=tuple(names_reg), c2w=c2w_out,
                         num_photos=len(names), unregistered=reasons, mean_reprojection_error=reproj,
                         num_points=len(xyz), num_cameras=len(und.cameras), matcher=matcher, up_from=up_from,
                         transform=transform, seconds=seconds, timings=timings)
    manifest.update(status="done", result={k: v for k, v in result.to_json().items() if k != "unregistered"},
                    pairs=n_pairs)
    _write_manifest(out_dir, manifest)
    if reasons:
        log(f"{len(reasons)} photos did not register:\n{_listing(reasons)}\n{_advice(cfg, matcher, longest)}")
    h, w = int(intr[0, 5]), int(intr[0, 4])
    log(f"registered {len(names_reg)}/{len(names)} photos, mean reprojection error {reproj:.2f} px, "
        f"{len(xyz)} points, {_fmt_time(seconds)} ("
        + ", ".join(f"{k} {_fmt_time(v)}" for k, v in timings.items()) + ")")
    log(f"wrote {transforms_path} ({len(names_reg)} frames, PINHOLE {w}x{h}"
        f"{'' if len(und.cameras) == 1 else ', per-frame intrinsics'}), images/, sparse_pc.ply, sparse/0")
    return result
