"""Where a command may write: one output-folder policy for every ``dars`` command.

Rules (README, "Outputs and safety"):

1. A command writes into its output folder only when the folder is new, empty, or was written by dars before: such a
   folder holds :data:`MANIFEST` (``dars_manifest.json``), which lists every file and folder dars wrote there.
2. dars replaces only what its manifest lists. A file the manifest does not list is the user's and is never
   overwritten or deleted, with or without ``--force``; a command whose output would replace one is refused, naming it.
3. ``--force`` lets a command write into a folder that holds other files: dars's files go beside them (and an earlier
   dars output there is replaced); the user's files are left as they are.
4. An output *file* named on the command line (``--out FILE.png``) is written when it does not exist; an existing one
   is replaced only with ``--force`` (the user named it).
5. Everything is checked before any heavy work (:meth:`OutputDir.check` has no side effects); a folder the command
   created is removed again when the command fails before writing anything into it (:meth:`OutputDir.abort`).
6. Temporary files left by an interrupted write (``.NAME.XXXXXXXX.tmp``, see :func:`atomic_write`) are
   removed from a dars folder when the next command starts there.

The manifest is JSON: ``{"dars": COMMAND, "format": 1, "files": [relative paths; "dir/" = a folder dars owns
entirely], "commands": [...], "updated": ISO time, ...}``. Folders written by earlier versions are recognised: the
priors' ``manifest.json`` (``"tool": "dars"``), a ``dars poses`` manifest, and a training run (``config.json`` with
``config`` and ``scene``).

This module imports nothing heavy (the command line's argument checks use it).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shutil
import tempfile
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterable, Iterator

from ._checks import DarsError

__all__ = ["MANIFEST", "OutputDir", "atomic_write", "check_output_file", "read_manifest", "active_dir_for",
           "is_temp_file", "RUN_FILES", "release_all"]

MANIFEST = "dars_manifest.json"
"""The file that marks a folder as written by dars and lists what dars wrote there."""
LEGACY_PRIORS_MANIFEST = "manifest.json"
RUN_FILES = ("config.json", "checkpoint.pt", "log.jsonl", "loss_curves.png", "snapshots/")
"""What ``dars train`` writes into a run folder."""
_LEGACY_RUN_EXTRA = ("eval/", "mesh/", "bake/")
"""Default output folders of ``dars eval`` / ``mesh`` / ``bake`` inside a run made before manifests existed."""
_LEGACY_POSES = ("transforms.json", "images/", "sparse_pc.ply", "sparse/", "colmap/")
_TEMP = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.(tmp|export\.onnx|export\.onnx\.data)$|^\..+\.tmp\.png$")
_OTHER_TEMPS = {"loss_curves.tmp.png", MANIFEST + ".tmp"}

_ACTIVE: list["OutputDir"] = []
"""Output folders being written now (innermost last): :func:`atomic_write` asks :func:`active_dir_for`."""


def is_temp_file(name: str) -> bool:
    """Whether ``name`` is a temporary file of an interrupted dars write."""
    return bool(_TEMP.match(name)) or name in _OTHER_TEMPS


def _shown(names: list[str], limit: int = 5) -> str:
    names = sorted(names)
    return ", ".join(names[:limit]) + (f" and {len(names) - limit} more" if len(names) > limit else "")


def read_manifest(folder: str | os.PathLike) -> dict | None:
    """The dars manifest of ``folder`` as ``{"files": [...], ...}``, or None when dars did not write the folder.

    Recognises :data:`MANIFEST` and the marks of earlier versions (see the module docstring).
    """
    folder = Path(folder)
    doc = _read_json_dict(folder / MANIFEST)
    if doc is not None and ("dars" in doc or doc.get("tool") == "dars"):
        files = doc.get("files")
        if not isinstance(files, list):
            files = list(_LEGACY_POSES) if doc.get("dars") == "poses" else []
        return {**doc, "files": [str(f) for f in files]}
    legacy = _read_json_dict(folder / LEGACY_PRIORS_MANIFEST)
    if legacy is not None and legacy.get("tool") == "dars" and isinstance(legacy.get("files"), list):
        return {"dars": f"priors {legacy.get('stage', '')}".strip(), "format": 0,
                "files": [str(f) for f in legacy["files"]] + [LEGACY_PRIORS_MANIFEST]}
    run = _read_json_dict(folder / "config.json")
    if run is not None and "config" in run and "scene" in run:
        return {"dars": "train", "format": 0, "files": list(RUN_FILES + _LEGACY_RUN_EXTRA)}
    return None


def _read_json_dict(path: Path) -> dict | None:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def _owned(rel: str, ours: set[str]) -> bool:
    """Whether the relative path ``rel`` is listed in ``ours`` (itself, or a folder above it ending in ``/``)."""
    rel = rel.rstrip("/")
    if rel in ours or rel + "/" in ours:
        return True
    parts = rel.split("/")
    return any("/".join(parts[:k]) + "/" in ours for k in range(1, len(parts)))


def _nearest_existing(path: Path) -> Path:
    anc = path
    while not anc.exists() and not anc.is_symlink():
        if anc.parent == anc:
            break
        anc = anc.parent
    return anc


def _check_parent_writable(path: Path, option: str, kind: str, another: str | None = None) -> None:
    """Raise :class:`DarsError` unless ``path`` can be created or written (nothing is created)."""
    another = another or option
    anc = _nearest_existing(path.absolute().parent if kind == "file" else path.absolute())
    if anc != path.absolute() and not anc.is_dir():
        raise DarsError(f"{option} {path}: {anc} is a file, not a folder; choose another {another}")
    if anc.is_dir():
        st = anc.stat()
        # root bypasses permission bits: honour a folder marked read-only (no write bit) anyway
        if not os.access(anc, os.W_OK | os.X_OK) or not (st.st_mode & 0o222):
            raise DarsError(f"{option} {path}: cannot write there ({anc} is read-only); choose another {another}")


class OutputDir:
    """An output folder of one command: checks it before any work, records what dars writes in :data:`MANIFEST`.

    Example:
        >>> out = OutputDir("out/render", "render").check(["view_rgb.png"])   # doctest: +SKIP
        >>> with out:                                                         # doctest: +SKIP
        ...     write_png(out.file("view_rgb.png"), img)

    Args:
        path: the folder.
        command: the command that writes it (recorded in the manifest).
        force: write into a folder that holds other files (beside them; see the module docstring).
        option: how the user gave the folder, for messages (``--out``, ``OUTDIR``).
    """

    def __init__(self, path: str | os.PathLike, command: str, force: bool = False, option: str = "--out"):
        self.path = Path(path)
        self.command = command
        self.force = force
        self.option = option
        self.another = option if option.startswith("-") or option.isupper() else "--out"
        """What to choose instead, in messages (``--out`` for a default folder the user did not name)."""
        self.planned: list[str] = []
        self.ours: set[str] = set()
        self.manifest: dict | None = None
        self.written: set[str] = set()
        self.stale: list[str] = []
        """dars's own earlier outputs to delete when writing begins (a ``--force`` restart); only listed ones go."""
        self._created: list[Path] = []
        self._checked = False
        self._begun = False

    # ------------------------------------------------------------------------------------------------ checking
    def check(self, planned: Iterable[str] = ()) -> "OutputDir":
        """Raise :class:`DarsError` unless the command may write ``planned`` (paths relative to the folder; ``dir/``
        for a whole folder) here; no side effects.

        Refused: a path that is a file, a read-only place, a non-empty folder dars did not write (unless ``force``),
        and any planned path that exists but is not dars's (always).
        """
        p = self.path
        planned = [str(x).replace(os.sep, "/") for x in planned]
        self.planned = list(dict.fromkeys(self.planned + [x for x in planned if x.rstrip("/") != MANIFEST]))
        if p.exists() and not p.is_dir():
            raise DarsError(f"{self.option} {p} is a file, not a folder; give a folder (a new one is created), "
                            f"or choose another {self.another}")
        _check_parent_writable(p, self.option, "dir", self.another)
        if p.is_dir():
            self.manifest = read_manifest(p)
            self.ours = set(self.manifest["files"]) if self.manifest is not None else set()
            if self.manifest is None and (p / MANIFEST).exists():
                raise DarsError(f"{self.option} {p} holds a {MANIFEST} that dars did not write; refusing to write "
                                f"there: choose another {self.another}")
            if self.manifest is None and not self.force:
                entries = [e.name for e in p.iterdir()]
                if entries:
                    raise DarsError(
                        f"{self.option} {p} is not empty ({_shown(entries)}) and was not written by dars (no "
                        f"{MANIFEST}): refusing to write there; choose a new or empty folder, or pass --force to add "
                        "dars's files beside these (dars never overwrites or deletes files it did not write)")
            clash = [x.rstrip("/") for x in self.planned
                     if ((p / x).exists() or (p / x).is_symlink()) and not _owned(x, self.ours)]
            if clash:
                raise DarsError(
                    f"{self.option} {p} holds {_shown(clash)}, which dars did not write and `dars {self.command}` "
                    "would replace; dars never overwrites your files (not even with --force): move them away or "
                    f"choose another {self.another}")
        self._checked = True
        return self

    def owns(self, rel: str) -> bool:
        """Whether dars wrote (or is writing) ``rel`` here."""
        return _owned(rel, self.ours | self.written | set(self.planned))

    # ------------------------------------------------------------------------------------------------ writing
    def begin(self) -> "OutputDir":
        """Create the folder, remove stale temporary files of dars's, record the planned files in the manifest
        (before they are written: a crash leaves them listed as dars's), and route :func:`atomic_write`
        calls under the folder through :meth:`claim`."""
        if self._begun:
            return self
        if not self._checked:
            self.check()
        missing = []
        anc = self.path.absolute()
        while not anc.exists():
            missing.append(anc)
            anc = anc.parent
        self.path.mkdir(parents=True, exist_ok=True)
        self._created = missing  # deepest first
        if self.manifest is not None:
            self._remove_stale_temps()
            self.remove_previous(self.stale)
        self._begun = True
        self._write_manifest(self.ours | set(self.planned))
        _ACTIVE.append(self)
        return self

    def file(self, rel: str) -> Path:
        """The path of output ``rel`` (relative to the folder), recorded as dars's."""
        self.claim(self.path / rel)
        return self.path / rel

    def claim(self, path: str | os.PathLike) -> None:
        """Record ``path`` (inside the folder) as written by dars; refuse it when it exists and is the user's.

        Raises:
            DarsError: ``path`` exists and is not dars's (a planned-files list that missed it; never overwritten).
        """
        if not self._begun:
            self.begin()
        try:
            rel = Path(os.path.abspath(path)).relative_to(self.path.absolute()).as_posix()
        except ValueError:
            return
        if rel == MANIFEST or rel in self.written or _owned(rel, self.ours | set(self.planned)):
            self.written.add(rel)
            return
        if Path(path).exists() or Path(path).is_symlink():
            raise DarsError(f"{path} exists and was not written by dars; refusing to overwrite it (move it away or "
                            f"choose another {self.another})")
        self.written.add(rel)
        self._write_manifest(self.ours | set(self.planned) | self.written)

    def remove_previous(self, names: Iterable[str]) -> None:
        """Delete dars's own earlier outputs ``names`` (those the manifest lists; a ``--force`` restart)."""
        for rel in names:
            if not _owned(rel, self.ours):
                continue
            p = self.path / rel.rstrip("/")
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            elif p.exists() or p.is_symlink():
                p.unlink()

    def finish(self, extra: dict | None = None) -> None:
        """Write the final manifest: what dars wrote here (this command and earlier ones) that still exists."""
        if not self._begun:
            self.begin()
        files = {f for f in self.ours | set(self.planned) | self.written
                 if (self.path / f.rstrip("/")).exists() or f == LEGACY_PRIORS_MANIFEST}
        if (self.path / LEGACY_PRIORS_MANIFEST).is_file() and LEGACY_PRIORS_MANIFEST in self.ours:
            (self.path / LEGACY_PRIORS_MANIFEST).unlink()  # superseded by ours
            files.discard(LEGACY_PRIORS_MANIFEST)
        self._write_manifest(files, extra)
        self._deactivate()

    def abort(self) -> None:
        """After a failure: stop routing writes here; remove the folder again if this command created it and wrote
        nothing into it (only the manifest)."""
        self._deactivate()
        if not self._created:
            return
        try:
            left = [e for e in self.path.iterdir() if e.name != MANIFEST]
        except OSError:
            return
        if left:
            return
        (self.path / MANIFEST).unlink(missing_ok=True)
        for d in self._created:  # deepest first; only the folders this command made, and only when empty
            try:
                d.rmdir()
            except OSError:
                break

    @contextlib.contextmanager
    def guard(self) -> Iterator["OutputDir"]:
        """Run a block that writes through this folder (which calls :meth:`finish` itself): :meth:`abort` when it
        fails. Unlike ``with out:``, writing (the folder, the manifest) starts only at the block's first write."""
        try:
            yield self
        except BaseException:
            self.abort()
            raise

    def __enter__(self) -> "OutputDir":
        return self.begin()

    def __exit__(self, kind, value, tb) -> None:
        if kind is None:
            self.finish()
        else:
            self.abort()

    # ------------------------------------------------------------------------------------------------ internals
    def _deactivate(self) -> None:
        if self in _ACTIVE:
            _ACTIVE.remove(self)

    def _write_manifest(self, files: set[str], extra: dict | None = None) -> None:
        doc = dict(self.manifest or {})
        if doc.get("format", 1) == 0:  # an earlier version's mark: start a manifest of our own
            doc = {}
        doc.setdefault("dars", self.command)
        doc["format"] = 1
        doc["files"] = sorted(files)
        doc["commands"] = sorted(set(doc.get("commands", [])) | {self.command})
        doc["updated"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        doc.update(extra or {})
        self.manifest = doc
        with atomic_write(self.path / MANIFEST, "w") as f:
            json.dump(doc, f, indent=2)
            f.write("\n")

    def _remove_stale_temps(self) -> None:
        folders = [self.path] + [self.path / f.rstrip("/") for f in self.ours | set(self.planned) if f.endswith("/")]
        for folder in folders:
            if not folder.is_dir() or folder.is_symlink():
                continue
            for e in folder.iterdir():
                if e.is_file() and is_temp_file(e.name):
                    e.unlink(missing_ok=True)


def release_all() -> None:
    """Forget every folder being written (the command line calls this when a command ends, however it ends)."""
    _ACTIVE.clear()


def active_dir_for(path: str | os.PathLike) -> OutputDir | None:
    """The innermost output folder being written that contains ``path`` (None: not inside one)."""
    if not _ACTIVE:
        return None
    p = Path(os.path.abspath(path))
    for d in reversed(_ACTIVE):
        try:
            p.relative_to(d.path.absolute())
            return d
        except ValueError:
            continue
    return None


def _umask() -> int:
    """The process's umask (read from /proc where possible: ``os.umask`` can only be read by setting it)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    old = os.umask(0o022)
    os.umask(old)
    return old


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb") -> Iterator[io.IOBase]:
    """Open a temporary file beside ``path`` and move it over ``path`` only when the block succeeds.

    The file gets the usual permissions (0666 less the umask, e.g. 0644), not the temporary file's 0600. Inside an
    output folder being written (:class:`toolkit.outputs.OutputDir`) the path is recorded in its manifest, and a file
    there that dars did not write is refused (:meth:`toolkit.outputs.OutputDir.claim`). An OS error (disk full,
    permission denied) names ``path``.

    Example:
        >>> with atomic_write("/tmp/x.txt", "w") as f:
        ...     _ = f.write("hello")
    """
    path = Path(path)
    guard = active_dir_for(path)
    if guard is not None:
        guard.claim(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        if tmp is not None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
        if isinstance(e, OSError) and e.filename is None and e.errno is not None:
            raise OSError(e.errno, e.strerror or str(e), str(path)) from e
        raise


def check_output_file(path: str | os.PathLike, force: bool = False, option: str = "--out",
                      suffixes: Iterable[str] = (), siblings: Iterable[str | os.PathLike] = ()) -> Path:
    """Check an output file named on the command line before any work (no side effects); returns it as a Path.

    Args:
        path: the file.
        force: replace it (and ``siblings``) when it exists.
        option: how the user gave it, for messages.
        suffixes: accepted endings (e.g. ``(".png",)``; empty: any).
        siblings: other files the command writes beside it (checked the same way).

    Raises:
        DarsError: a folder, another suffix, an unwritable place, or an existing file without ``force``.
    """
    path = Path(path)
    suffixes = tuple(s.lower() for s in suffixes)
    if path.is_dir():
        want = f" ending in {' or '.join(suffixes)}" if suffixes else ""
        example = path / ("out" + (suffixes or ("",))[0])
        raise DarsError(f"{option} {path} is a folder; give a file name{want} (e.g. {example})")
    if suffixes and path.suffix.lower() not in suffixes:
        raise DarsError(f"{option} {path}: give a {' or '.join(suffixes)} file")
    _check_parent_writable(path, option, "file")
    existing = [str(q) for q in [path, *map(Path, siblings)] if q.exists()]
    if existing and not force:
        raise DarsError(f"{option}: {_shown(existing)} already exist{'s' if len(existing) == 1 else ''}; pass --force "
                        "to replace, or choose another file name")
    return path
