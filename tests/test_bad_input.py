"""Bad input as a careless or unlucky user gives it (issue 21), command by command.

Every case in :data:`CASES` runs ``dars`` in-process and asserts: the exit code, the key words of the one-line message
(the file or value, and a fix), no traceback, and that every file it was given — the scene, the run, the user's files
in the way — is byte-identical afterwards and nothing was created (no empty ``--out`` folder either). The tests after
the table check the output-folder policy of :mod:`toolkit.outputs` where a command succeeds (``--force`` beside a
user's file, reruns into dars's own folder, stale temporary files, permissions), the early first checkpoint, and
the one-line OS errors.

Fast: one 6-view 16 px scene and one 2-step run (a 2^12 hash grid) per module; the refusals all come before any
heavy work.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import stat
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import numpy as np
import pytest

from synthetic import make_scene
from toolkit.cli import main
from toolkit.defaults import DARS_DEFAULT
from toolkit.train import make_config

ROOT = Path(__file__).resolve().parents[1]


def tiny_config(**kw):
    """A ``fast`` config for a run that trains in seconds (a 4-level 2^12 hash grid, 256-ray batches)."""
    from toolkit.encoding import HashGridConfig
    from toolkit.field import FieldConfig
    from toolkit.train import make_config

    base = dict(steps=2, batch_rays=256, ssim_patches=0, occupancy_resolution=16, occupancy_warmup=2,
                occupancy_every=4, log_every=1,
                field=FieldConfig(encoding="grid", grid=HashGridConfig(n_levels=4, log2_table_size=12)))
    base.update(kw)
    return make_config("fast", **base)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """What the cases are given: a scene, a run (trained with ``force`` beside the user's ``notes.txt``), a GLB, an
    HDR probe, an SH JSON, a folder of photos without poses and a fake ONNX export folder."""
    from _viewer_assets import textured_cube
    from toolkit.io import write_hdr, write_png
    from toolkit.train import train

    root = tmp_path_factory.mktemp("bad_input")
    scene = make_scene(root / "scene", n_train=6, n_test=2, size=16)
    run = root / "run"
    run.mkdir()
    (run / "notes.txt").write_text("my notes\n")
    train(scene, run, tiny_config(), progress_bar=False, log=lambda m: None, force=True)
    glb = textured_cube(root / "cube.glb", cell=8)
    probe = root / "probe.hdr"
    write_hdr(probe, np.full((8, 16, 3), 0.5, np.float32))
    sh = root / "sh.json"
    sh.write_text(json.dumps({"coeffs": [[1.0, 1.0, 1.0]] + [[0.0, 0.0, 0.0]] * 8}))
    photos = root / "photos"
    rng = np.random.default_rng(0)
    for k in range(2):
        write_png(photos / f"p{k}.png", rng.random((24, 24, 3)))
    onnx = root / "onnx"  # what `dars infer` checks before reading anything
    onnx.mkdir()
    (onnx / "metadata.json").write_text(json.dumps({"format": "dars-onnx", "srgb": True}))
    (onnx / "field.onnx").write_bytes(b"not onnx")
    np.savez(onnx / "occupancy.npz", resolution=np.int64(4), aabb=np.zeros((2, 3), np.float32),
             mask_bits=np.packbits(np.ones(64, bool)))
    np.savez(onnx / "background.npz", mode=np.array("constant"), colour=np.ones(3, np.float32))
    return SimpleNamespace(root=root, scene=scene, run=run, glb=glb, probe=probe, sh=sh, photos=photos, onnx=onnx)


def tree(*roots: Path) -> dict[str, str]:
    """Every file and folder under ``roots``: path -> sha256 (folders: 'dir')."""
    out = {}
    for r in roots:
        for p in [r, *sorted(r.rglob("*"))]:
            out[str(p)] = "dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def run_cli(argv: list, capsys) -> tuple[int, str, str]:
    """``dars argv`` in-process: (exit code, stdout, stderr); an exception escaping ``main`` (a traceback) fails."""
    argv = [str(a) for a in argv]
    try:
        code = main(argv)
    except BaseException as e:  # noqa: BLE001 - this is the traceback the issue is about
        pytest.fail(f"`dars {' '.join(argv)}` raised {type(e).__name__}: {e}")
    out, err = capsys.readouterr()
    return code, out, err


# ============================================================================================== the case table
@dataclass
class Case:
    id: str
    argv: Callable[[SimpleNamespace], list]
    words: tuple[str, ...]
    """All in the message (case-insensitive): the file or value that is wrong, and the way out."""
    setup: Callable[[SimpleNamespace], None] | None = None
    code: int = 2


def _write(rel: str, content: str | bytes = "mine\n"):
    """Setup: a file of the user's at ``tmp/rel``."""
    def setup(c):
        p = c.t / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(content if isinstance(content, bytes) else content.encode())
    return setup


def _both(*setups):
    def setup(c):
        for s in setups:
            s(c)
    return setup


def _copy_run(c) -> None:
    shutil.copytree(c.w.run, c.t / "r")


def _damage(rel: str, how: str):
    """Setup: a copy of the run (``tmp/r``) with ``rel`` truncated to half, emptied, or replaced by text."""
    def setup(c):
        _copy_run(c)
        p = c.t / "r" / rel
        data = p.read_bytes()
        p.write_bytes({"half": data[:len(data) // 2], "empty": b"", "text": b"hello, not a checkpoint\n"}[how])
    return setup


def _edit_config(edit: Callable[[dict], object]):
    """Setup: a copy of the run whose config.json is ``edit(doc)`` (a dict, list or raw text)."""
    def setup(c):
        _copy_run(c)
        p = c.t / "r" / "config.json"
        doc = edit(json.loads(p.read_text()))
        p.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return setup


def _with(d: dict, **kw) -> dict:
    return {**d, **kw}


def _transforms(frame: dict | None = None, top: object = None, raw: bytes | None = None):
    """Setup: ``tmp/s/transforms.json`` (one 8 px frame) with ``frame`` keys overridden, or ``top`` as the whole
    document, or ``raw`` bytes."""
    def setup(c):
        from toolkit.io import write_png

        s = c.t / "s"
        write_png(s / "a.png", np.full((8, 8, 3), 0.5, np.float32))
        fr = {"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}
        fr.update(frame or {})
        doc = top if top is not None else {"camera_angle_x": 0.8, "frames": [fr, dict(fr)]}
        (s / "transforms.json").write_bytes(raw if raw is not None else json.dumps(doc).encode())
    return setup


def _priors(stage: str, rel: str, content: bytes | str):
    """Setup: a priors folder ``tmp/P`` whose ``stage/rel`` is damaged."""
    def setup(c):
        p = c.t / "P" / stage / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(content if isinstance(content, bytes) else content.encode())
    return setup


def _weights_npy(c) -> None:
    for f in ("train__r_000", "train__r_001", "train__r_002", "train__r_003", "train__r_004", "train__r_005"):
        p = c.t / "P" / "weights" / f"{f}.npy"
        p.parent.mkdir(parents=True, exist_ok=True)
        np.save(p, np.zeros((16, 16), np.float16))
    (c.t / "P" / "weights" / "train__r_003.npy").write_bytes(b"\x93NUMPY")


PNG_AS_HDR = _write("fake.hdr", b"\x89PNG\r\n\x1a\n" + bytes(64))
HALF_GLB = "half.glb"


def _half_glb(c) -> None:
    data = c.w.glb.read_bytes()
    (c.t / HALF_GLB).write_bytes(data[:len(data) // 2])


def _half_npz(name: str):
    def setup(c):
        shutil.copytree(c.w.onnx, c.t / "x")
        p = c.t / "x" / name
        p.write_bytes(p.read_bytes()[:40])
    return setup


O = "out"  # the output folder of the policy cases (under tmp)

# --- 1. output folders: a file of the user's that a command would write ------------------------------------------
#     (command, argv after the command, the file in the way); each without --force (refused: not a dars folder) and
#     with --force (refused: dars never replaces a file it did not write)
_POLICY = [
    ("train", lambda c: ["train", c.w.scene, "--out", c.t / O, "--steps", 1], "config.json"),
    ("train-log", lambda c: ["train", c.w.scene, "--out", c.t / O, "--steps", 1], "log.jsonl"),
    ("render", lambda c: ["render", c.w.run, "--out", c.t / O, "--limit", 1], "test__r_000_rgb.png"),
    ("relight", lambda c: ["relight", c.w.run, "--sh", c.w.sh, "--out", c.t / O, "--limit", 1], "relight.json"),
    ("eval", lambda c: ["eval", c.w.run, "--out", c.t / O], "metrics.json"),
    ("eval-report", lambda c: ["eval", c.w.run, "--out", c.t / O], "report.md"),
    ("mesh", lambda c: ["mesh", c.w.run, "--out", c.t / O], "mesh.ply"),
    ("bake", lambda c: ["bake", c.w.run, "--mesh", c.w.glb, "--out", c.t / O], "base_color.png"),
    ("export-asset", lambda c: ["export-asset", c.w.run, "--out", c.t / O], "scene.glb"),
    ("export-asset-textures", lambda c: ["export-asset", c.w.run, "--out", c.t / O], "textures/orm.png"),
    ("export-onnx", lambda c: ["export-onnx", c.w.run, "--out", c.t / O], "field.onnx"),
    ("export-onnx-meta", lambda c: ["export-onnx", c.w.run, "--out", c.t / O], "metadata.json"),
    ("export-web", lambda c: ["export-web", c.w.glb, c.t / O], "index.html"),
    ("export-web-main", lambda c: ["export-web", c.w.glb, c.t / O], "main.js"),
    ("export-web-vendor", lambda c: ["export-web", c.w.glb, c.t / O], "vendor/three/mine.js"),
    ("infer-segment", lambda c: ["infer", c.w.onnx, "--segment", c.w.photos / "p0.png", "--out", c.t / O],
     "p0_labels.png"),
    ("ablate", lambda c: ["ablate", c.w.scene, "--out", c.t / O, "--steps", 1], "ablation.json"),
    ("priors-colour", lambda c: ["priors", "colour", c.w.scene, "--out", c.t / O], "colour.json"),
    ("priors-weights", lambda c: ["priors", "weights", c.w.scene, "--out", c.t / O], "weights.json"),
    ("priors-light", lambda c: ["priors", "light", c.w.scene, "--out", c.t / O], "light.json"),
    ("priors-segment", lambda c: ["priors", "segment", c.w.scene, "--out", c.t / O], "segment.json"),
    ("poses", lambda c: ["poses", c.w.photos, "--out", c.t / O], "transforms.json"),
]
CASES = [Case(f"policy-{name}", argv, (Path(rel).parts[0], "--force"), _write(f"{O}/{rel}"))
         for name, argv, rel in _POLICY]
CASES += [Case(f"policy-force-{name}", lambda c, a=argv: a(c) + ["--force"], (Path(rel).parts[0], "another"),
               _write(f"{O}/{rel}"))
          for name, argv, rel in _POLICY]
CASES += [
    Case("policy-eval-default-folder", lambda c: ["eval", c.t / "r"], ("eval", "metrics.json", "--force"),
         _both(_copy_run, _write("r/eval/metrics.json"))),
    Case("policy-mesh-default-folder", lambda c: ["mesh", c.t / "r"], ("mesh", "notes.txt", "--force"),
         _both(_copy_run, _write("r/mesh/notes.txt"))),
    Case("policy-unrelated-file", lambda c: ["render", c.w.run, "--out", c.t / O], ("notes.txt", "--force"),
         _write(f"{O}/notes.txt")),
    Case("policy-foreign-manifest", lambda c: ["render", c.w.run, "--out", c.t / O, "--force"],
         ("dars_manifest.json", "another --out"), _write(f"{O}/dars_manifest.json", '{"mine": 1}')),
    Case("policy-out-is-file-render", lambda c: ["render", c.w.run, "--out", c.t / "f.txt"], ("f.txt", "is a file"),
         _write("f.txt")),
    Case("policy-out-is-file-train", lambda c: ["train", c.w.scene, "--out", c.t / "f.txt", "--steps", 1],
         ("f.txt", "is a file"), _write("f.txt")),
    Case("policy-outdir-is-file-web", lambda c: ["export-web", c.w.glb, c.t / "f.txt"], ("OUTDIR", "f.txt", "file"),
         _write("f.txt")),
    Case("policy-out-below-file", lambda c: ["eval", c.w.run, "--out", c.t / "f.txt" / "sub"],
         ("f.txt", "not a folder"), _write("f.txt")),
    Case("policy-train-existing-run", lambda c: ["train", c.w.scene, "--out", c.t / "r", "--steps", 1],
         ("already holds a run", "--resume", "--force"), _copy_run),
    # output files named on the command line
    Case("file-view-exists", lambda c: ["view", c.w.glb, "--out", c.t / "shot.png"], ("shot.png", "--force"),
         _write("shot.png")),
    Case("file-view-not-png", lambda c: ["view", c.w.glb, "--out", c.t / "shot.jpg"], ("shot.jpg", ".png")),
    Case("file-contact-sheet-exists", lambda c: ["contact-sheet", c.w.scene, "--out", c.t / "sheet.png"],
         ("sheet.png", "--force"), _write("sheet.png")),
    Case("file-contact-sheet-dir", lambda c: ["contact-sheet", c.w.scene, "--out", c.t / "d"], ("is a folder", ".png"),
         _write("d/keep.txt")),
    Case("file-infer-camera-exists", lambda c: ["infer", c.w.onnx, "--camera", f"{c.w.scene}:test:0", "--out",
                                                c.t / "v.png"], ("v.png", "--force"), _write("v.png")),
    Case("file-infer-camera-sibling", lambda c: ["infer", c.w.onnx, "--camera", f"{c.w.scene}:test:0", "--out",
                                                 c.t / "v.png"], ("v_depth.png", "--force"), _write("v_depth.png")),
    Case("file-sh-probe-exists", lambda c: ["priors", "sh-probe", c.w.probe, "--out", c.t / "sh.json"],
         ("sh.json", "--force"), _write("sh.json")),
]

# --- 2. damaged run files: every command that reads a run --------------------------------------------------------
_RUN_READERS = [
    ("render", lambda c: ["render", c.t / "r", "--out", c.t / O]),
    ("relight", lambda c: ["relight", c.t / "r", "--sh", c.w.sh, "--out", c.t / O]),
    ("eval", lambda c: ["eval", c.t / "r", "--out", c.t / O]),
    ("mesh", lambda c: ["mesh", c.t / "r", "--out", c.t / O]),
    ("bake", lambda c: ["bake", c.t / "r", "--mesh", c.w.glb, "--out", c.t / O]),
    ("export-asset", lambda c: ["export-asset", c.t / "r", "--out", c.t / O]),
    ("export-onnx", lambda c: ["export-onnx", c.t / "r", "--out", c.t / O]),
    ("export-web", lambda c: ["export-web", c.t / "r", c.t / O]),
    ("resume", lambda c: ["train", "--resume", "--out", c.t / "r", "--steps", 4]),
]
for how, word in (("half", "truncated"), ("empty", "empty"), ("text", "corrupt")):
    CASES += [Case(f"checkpoint-{how}-{name}", argv, ("checkpoint.pt", word, "--force"), _damage("checkpoint.pt", how))
              for name, argv in _RUN_READERS]
CASES += [
    Case("config-invalid-render", _RUN_READERS[0][1], ("config.json", "corrupt", "--force"),
         _edit_config(lambda d: "{not json")),
    Case("config-empty-eval", _RUN_READERS[2][1], ("config.json", "empty"), _edit_config(lambda d: "")),
    Case("config-list-mesh", _RUN_READERS[3][1], ("config.json", "list"), _edit_config(lambda d: [d])),
    Case("config-no-scene-export-onnx", _RUN_READERS[6][1], ("config.json", "scene"),
         _edit_config(lambda d: {k: v for k, v in d.items() if k != "scene"})),
    Case("config-unknown-field-render", _RUN_READERS[0][1], ("config.json", "version"),
         _edit_config(lambda d: _with(d, config=_with(d["config"], warp_drive=True)))),
    Case("config-invalid-resume", _RUN_READERS[8][1], ("config.json", "corrupt"), _edit_config(lambda d: "[1, 2")),
    Case("config-user-file-resume", _RUN_READERS[8][1], ("config.json", "not written by"),
         _edit_config(lambda d: {"theme": "dark"})),
    Case("run-scene-moved", _RUN_READERS[0][1], ("missing_scene", "put the scene back"),
         _edit_config(lambda d: _with(d, scene="/nonexistent/missing_scene"))),
    Case("run-not-a-folder", lambda c: ["render", c.t / "nope", "--out", c.t / O], ("nope", "not found")),
    Case("run-not-a-run", lambda c: ["eval", c.t / "d", "--out", c.t / O], ("not a training run", "dars train"),
         _write("d/notes.txt")),
    Case("snapshot-missing", lambda c: ["render", c.w.run, "--checkpoint", c.t / "snap.pt", "--out", c.t / O],
         ("snap.pt", "not found")),
    Case("snapshot-truncated", lambda c: ["eval", c.w.run, "--checkpoint", c.t / "snap.pt", "--out", c.t / O],
         ("snap.pt", "corrupt"), _write("snap.pt", b"PK\x03\x04 truncated")),
    Case("export-web-not-a-run", lambda c: ["export-web", c.t / "d", c.t / O], ("expected a .glb", "RUN"),
         _write("d/notes.txt")),
]

# --- 3. damaged scene, photo, model and light files --------------------------------------------------------------
_INFO = lambda c: ["info", c.t / "s"]  # noqa: E731
_TRAIN_P = lambda c: ["train", c.w.scene, "--priors", c.t / "P", "--out", c.t / O, "--steps", 1]  # noqa: E731
CASES += [
    Case("transforms-w-text", _INFO, ("transforms.json", "frame 0", "'w'", "abc"), _transforms({"w": "abc"})),
    Case("transforms-fl_x-text", _INFO, ("'fl_x'", "x1"), _transforms({"fl_x": "x1"})),
    Case("transforms-h-negative", _INFO, ("'h'", "-3"), _transforms({"h": -3})),
    Case("transforms-cx-list", _INFO, ("'cx'", "[1, 2]"), _transforms({"cx": [1, 2]})),
    Case("transforms-angle-zero", _INFO, ("camera_angle_x", "(0, pi)"), _transforms({"camera_angle_x": 0})),
    Case("transforms-near-text", _INFO, ("'near'", "close"), _transforms(top={
        "camera_angle_x": 0.8, "near": "close",
        "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}] * 2})),
    Case("transforms-top-level-list", _INFO, ("transforms.json", "got a list"), _transforms(top=[1, 2])),
    Case("transforms-empty", _INFO, ("transforms.json", "empty"), _transforms(raw=b"")),
    Case("transforms-binary", _INFO, ("transforms.json", "not a text file"), _transforms(raw=b"\xff\xfe\x00\x01")),
    Case("transforms-frame-string", _INFO, ("frame 0", "expected an object"),
         _transforms(top={"frames": ["a.png", "b.png"]})),
    Case("transforms-file-path-null", _INFO, ("file_path", "None"), _transforms({"file_path": None})),
    Case("transforms-matrix-text", _INFO, ("transform_matrix", "numeric"), _transforms({"transform_matrix": "eye"})),
    Case("photos-without-poses-info", lambda c: ["info", c.w.photos], ("2 photos", "dars poses")),
    Case("photos-without-poses-train", lambda c: ["train", c.w.photos, "--out", c.t / O, "--steps", 1],
         ("no camera poses", "dars poses")),
    Case("photo-as-scene", lambda c: ["info", c.w.photos / "p0.png"], ("p0.png", "dars poses")),
    Case("scene-missing", lambda c: ["train", c.t / "nope", "--out", c.t / O, "--steps", 1], ("nope", "not found")),
    # GLB
    Case("glb-truncated-view", lambda c: ["view", c.t / HALF_GLB, "--out", c.t / "v.png"], (HALF_GLB, "truncated"),
         _half_glb),
    Case("glb-empty-view", lambda c: ["view", c.t / "e.glb", "--out", c.t / "v.png"], ("e.glb", "glTF"),
         _write("e.glb", b"")),
    Case("glb-garbage-view", lambda c: ["view", c.t / "g.glb", "--out", c.t / "v.png"], ("g.glb", "glTF"),
         _write("g.glb", b"glTF\x02\x00\x00\x00\x0e\x00\x00\x00\xff\xff")),
    Case("glb-truncated-export-web", lambda c: ["export-web", c.t / HALF_GLB, c.t / O], (HALF_GLB, "truncated"),
         _half_glb),
    Case("glb-text-export-web", lambda c: ["export-web", c.t / "g.glb", c.t / O], ("g.glb", "glTF"),
         _write("g.glb", "hello")),
    # the device bundle
    Case("infer-occupancy-truncated", lambda c: ["infer", c.t / "x", "--camera", f"{c.w.scene}:test:0", "--out",
                                                 c.t / "v.png"], ("occupancy.npz", "truncated", "export-onnx"),
         _half_npz("occupancy.npz")),
    Case("infer-background-truncated", lambda c: ["infer", c.t / "x", "--camera", f"{c.w.scene}:test:0", "--out",
                                                  c.t / "v.png"], ("background.npz", "export-onnx"),
         _half_npz("background.npz")),
    Case("infer-metadata-list", lambda c: ["infer", c.t / "x", "--camera", f"{c.w.scene}:test:0", "--out",
                                           c.t / "v.png"], ("metadata.json", "list"),
         _both(_half_npz("background.npz"), lambda c: (c.t / "x" / "metadata.json").write_text("[]"))),
    Case("infer-field-onnx-corrupt", lambda c: ["infer", c.w.onnx, "--camera", f"{c.w.scene}:test:0", "--out",
                                                c.t / "v.png"], ("field.onnx", "could not load")),
    Case("infer-dir-missing", lambda c: ["infer", c.t / "nope", "--camera", f"{c.w.scene}:test:0", "--out",
                                         c.t / "v.png"], ("nope", "export-onnx")),
    Case("infer-sh-corrupt", lambda c: ["infer", c.w.onnx, "--camera", f"{c.w.scene}:test:0", "--out", c.t / "v.png",
                                        "--sh", c.t / "bad.json"], ("bad.json", "JSON"), _write("bad.json", "{")),
    # HDR / EXR probes and SH files
    Case("hdr-png-renamed-sh-probe", lambda c: ["priors", "sh-probe", c.t / "fake.hdr"], ("fake.hdr", "PNG", "8-bit"),
         PNG_AS_HDR),
    Case("hdr-png-renamed-relight", lambda c: ["relight", c.w.run, "--probe", c.t / "fake.hdr", "--out", c.t / O],
         ("fake.hdr", "PNG"), PNG_AS_HDR),
    Case("hdr-png-renamed-export-web", lambda c: ["export-web", c.w.glb, c.t / O, "--probe", c.t / "fake.hdr"],
         ("fake.hdr", "PNG"), PNG_AS_HDR),
    Case("hdr-truncated", lambda c: ["priors", "sh-probe", c.t / "t.hdr"], ("t.hdr", "truncated"),
         lambda c: (c.t / "t.hdr").write_bytes(c.w.probe.read_bytes()[:80])),
    Case("hdr-empty", lambda c: ["priors", "sh-probe", c.t / "e.hdr"], ("e.hdr", "empty"), _write("e.hdr", b"")),
    Case("exr-garbage", lambda c: ["priors", "sh-probe", c.t / "g.exr"], ("g.exr", "OpenEXR"), _write("g.exr", "x")),
    Case("probe-wrong-format", lambda c: ["priors", "sh-probe", c.t / "p.png"], ("p.png", ".hdr"),
         _write("p.png", b"\x89PNG")),
    Case("sh-json-corrupt-relight", lambda c: ["relight", c.w.run, "--sh", c.t / "b.json", "--out", c.t / O],
         ("b.json", "JSON"), _write("b.json", "{'coeffs': ")),
    Case("sh-json-shape-export-web", lambda c: ["export-web", c.w.glb, c.t / O, "--sh", c.t / "b.json"],
         ("b.json", "9 x [r, g, b]"), _write("b.json", '{"coeffs": [1, 2, 3]}')),
    Case("sh-json-no-coeffs-view", lambda c: ["view", c.w.glb, "--out", c.t / "v.png", "--sh", c.t / "b.json"],
         ("b.json", "coeffs"), _write("b.json", '{"light": 1}')),
    Case("material-edit-bad", lambda c: ["relight", c.w.run, "--edit", "frame:shiny=1", "--out", c.t / O],
         ("frame:shiny=1",)),
    # meshes, networks, metric weights
    Case("bake-mesh-corrupt", lambda c: ["bake", c.w.run, "--mesh", c.t / "m.ply", "--out", c.t / O],
         ("m.ply", "could not be read"), _write("m.ply", "ply\nformat nonsense\n")),
    Case("bake-mesh-missing", lambda c: ["bake", c.w.run, "--mesh", c.t / "m.ply", "--out", c.t / O],
         ("m.ply", "dars mesh")),
    Case("eval-reference-mesh-missing", lambda c: ["eval", c.w.run, "--reference-mesh", c.t / "ref.ply", "--out",
                                                   c.t / O], ("ref.ply", "not found")),
    Case("eval-lpips-missing", lambda c: ["eval", c.w.run, "--lpips-weights", c.t / "alex.pth", "--out", c.t / O],
         ("alex.pth", "not found")),
    Case("lightnet-weights-corrupt", lambda c: ["priors", "light", c.w.scene, "--weights", c.t / "w.pt", "--out",
                                                c.t / O], ("w.pt", "not a readable"), _write("w.pt", "junk")),
    Case("segmenter-missing", lambda c: ["priors", "segment", c.w.scene, "--backend", "builtin", "--model",
                                         c.t / "s.pt", "--out", c.t / O], ("s.pt", "not found")),
    Case("export-onnx-segmenter-missing", lambda c: ["export-onnx", c.w.run, "--segmenter", c.t / "s.pt", "--out",
                                                     c.t / O], ("--segmenter", "s.pt")),
    # priors the trainer reads
    Case("priors-light-json-corrupt", _TRAIN_P, ("light.json", "corrupt", "dars priors light"),
         _priors("light", "light.json", "{")),
    Case("priors-light-json-shape", _TRAIN_P, ("light.json", "coeffs"),
         _priors("light", "light.json", '{"coeffs": [1]}')),
    Case("priors-colour-json-corrupt", _TRAIN_P, ("colour.json", "dars priors colour"),
         _priors("colour", "colour.json", "")),
    Case("priors-colour-json-list", _TRAIN_P, ("colour.json", "list"), _priors("colour", "colour.json", "[]")),
    Case("priors-weights-npy-truncated", _TRAIN_P, ("train__r_003.npy", "dars priors weights"), _weights_npy),
    Case("priors-weights-json-corrupt", _TRAIN_P, ("weights.json", "corrupt"),
         _both(_weights_npy, lambda c: np.save(c.t / "P" / "weights" / "train__r_003.npy", np.zeros((16, 16))),
               _priors("weights", "weights.json", "{"))),
    Case("priors-folder-missing", lambda c: ["train", c.w.scene, "--priors", c.t / "Prios", "--out", c.t / O,
                                             "--steps", 1], ("Prios", "not found")),
    Case("priors-folder-is-a-stage", lambda c: ["train", c.w.scene, "--priors", c.t / "P" / "light", "--out",
                                                c.t / O, "--steps", 1], ("light", "parent"),
         _priors("light", "light.json", '{"coeffs": []}')),
    Case("train-many-manifest-not-json", lambda c: ["train-many", c.t / "museum.json", "--out", c.t / O],
         ("museum.json", "not valid JSON"), _write("museum.json", "{\n")),
    Case("train-many-entry-without-scene", lambda c: ["train-many", c.t / "museum.json", "--out", c.t / O],
         ("entry 1", "'scene'", "'photos'"), _write("museum.json", '[{"name": "hall"}]')),
    Case("ablate-priors-missing", lambda c: ["ablate", c.w.scene, "--priors", c.t / "nope", "--out", c.t / O,
                                             "--steps", 1], ("nope", "not found")),
]

# --- 4. arguments: checked while parsing or before any work, named as the user typed them -----------------------
_ARGS = [
    ("train-minutes-nan", lambda c: ["train", c.w.scene, "--out", c.t / O, "--minutes", "nan"], ("--minutes", "nan")),
    ("train-minutes-inf", lambda c: ["train", c.w.scene, "--out", c.t / O, "--minutes", "inf"], ("--minutes", "inf")),
    ("train-minutes-negative", lambda c: ["train", c.w.scene, "--out", c.t / O, "--minutes", "-1"], ("--minutes",)),
    ("train-minutes-text", lambda c: ["train", c.w.scene, "--out", c.t / O, "--minutes", "ten"], ("--minutes", "ten")),
    ("train-steps-negative", lambda c: ["train", c.w.scene, "--out", c.t / O, "--steps", "-5"], ("--steps", "-5")),
    ("train-no-length", lambda c: ["train", c.w.scene, "--out", c.t / O], ("--steps", "--minutes")),
    ("train-batch-rays-small", lambda c: ["train", c.w.scene, "--out", c.t / O, "--steps", 1, "--batch-rays", 8],
     ("--batch-rays", "16")),
    ("train-sparse-depth-negative", lambda c: ["train", c.w.scene, "--out", c.t / O, "--steps", 1, "--sparse-depth",
                                               "-0.1"], ("--sparse-depth",)),
    ("train-opacity-loss-negative", lambda c: ["train", c.w.scene, "--out", c.t / O, "--steps", 1, "--opacity-loss",
                                               "-1"], ("--opacity-loss",)),
    ("train-depth-normal-negative", lambda c: ["train", c.w.scene, "--out", c.t / O, "--steps", 1, "--depth-normal",
                                               "-0.5"], ("--depth-normal",)),
    ("train-orientation-negative", lambda c: ["train", c.w.scene, "--out", c.t / O, "--steps", 1, "--orientation",
                                              "-0.1"], ("--orientation",)),
    ("train-sparse-depth-nan", lambda c: ["train", c.w.scene, "--out", c.t / O, "--steps", 1, "--sparse-depth", "nan"],
     ("--sparse-depth", "nan")),
    ("train-seed-negative", lambda c: ["train", c.w.scene, "--out", c.t / O, "--steps", 1, "--seed", "-1"],
     ("--seed",)),
    ("train-threads-negative", lambda c: ["train", c.w.scene, "--out", c.t / O, "--steps", 1, "--threads", "-2"],
     ("--threads",)),
    ("train-snapshots-text", lambda c: ["train", c.w.scene, "--out", c.t / O, "--steps", 1, "--snapshots", "a,b"],
     ("--snapshots", "a,b")),
    ("train-snapshots-nan", lambda c: ["train", c.w.scene, "--out", c.t / O, "--steps", 1, "--snapshots", "2,nan"],
     ("--snapshots", "finite")),
    ("train-no-scene", lambda c: ["train", "--out", c.t / O, "--steps", 1], ("SCENE", "--resume")),
    ("train-knots-without-steps", lambda c: ["train", c.w.scene, "--out", c.t / O, "--minutes", 1,
                                             "--schedule-knots", "300:900"], ("--schedule-knots", "--steps")),
    ("train-knots-text", lambda c: ["train", c.w.scene, "--out", c.t / O, "--steps", 1000, "--schedule-knots",
                                    "300-900"], ("--schedule-knots", "300-900", "STEP:STEPS")),
    ("train-knots-past-the-end", lambda c: ["train", c.w.scene, "--out", c.t / O, "--steps", 100,
                                            "--schedule-knots", "300:900"], ("300:900", "steps=100")),
    ("render-limit-negative", lambda c: ["render", c.w.run, "--out", c.t / O, "--limit", "-1"], ("--limit",)),
    ("render-orbit-negative", lambda c: ["render", c.w.run, "--out", c.t / O, "--orbit", "-3"], ("--orbit",)),
    ("relight-intensity-nan", lambda c: ["relight", c.w.run, "--sh", c.w.sh, "--out", c.t / O, "--intensity", "nan"],
     ("--intensity", "nan")),
    ("relight-rotate-inf", lambda c: ["relight", c.w.run, "--probe", c.w.probe, "--out", c.t / O,
                                      "--probe-rotate-x", "inf"], ("--probe-rotate-x",)),
    ("relight-nothing", lambda c: ["relight", c.w.run, "--out", c.t / O], ("--probe", "--edit")),
    ("mesh-resolution-small", lambda c: ["mesh", c.w.run, "--resolution", 4], ("--resolution", "8")),
    ("mesh-level-nan", lambda c: ["mesh", c.w.run, "--level", "nan"], ("--level", "nan")),
    ("mesh-level-quantile", lambda c: ["mesh", c.w.run, "--level-quantile", 2], ("--level-quantile",)),
    ("mesh-faces-negative", lambda c: ["mesh", c.w.run, "--faces", "-1"], ("--faces",)),
    ("mesh-min-component", lambda c: ["mesh", c.w.run, "--min-component", "1.5"], ("--min-component",)),
    ("bake-texture-small", lambda c: ["bake", c.w.run, "--texture", 10], ("--texture", "16")),
    ("bake-ao-negative", lambda c: ["bake", c.w.run, "--ao-samples", "-4"], ("--ao-samples",)),
    ("export-asset-texture-huge", lambda c: ["export-asset", c.w.run, "--out", c.t / O, "--texture", 100000],
     ("--texture",)),
    ("export-asset-depth-samples", lambda c: ["export-asset", c.w.run, "--out", c.t / O, "--depth-samples", 0],
     ("--depth-samples",)),
    ("export-asset-depth-min-opacity", lambda c: ["export-asset", c.w.run, "--out", c.t / O, "--depth-min-opacity", 0.7],
     ("--depth-min-opacity", "0.5")),
    ("export-onnx-opset", lambda c: ["export-onnx", c.w.run, "--out", c.t / O, "--opset", 20], ("--opset", "17")),
    ("export-onnx-precision", lambda c: ["export-onnx", c.w.run, "--out", c.t / O, "--precision", "fp32,fp64"],
     ("--precision", "fp64")),
    ("export-onnx-view", lambda c: ["export-onnx", c.w.run, "--out", c.t / O, "--view", "test:first"],
     ("--view", "SPLIT:INDEX")),
    ("view-width-zero", lambda c: ["view", c.w.glb, "--out", c.t / "v.png", "--width", 0], ("--width",)),
    ("view-exposure-nan", lambda c: ["view", c.w.glb, "--out", c.t / "v.png", "--exposure", "nan"], ("--exposure",)),
    ("view-headless-no-out", lambda c: ["view", c.w.glb, "--headless"], ("--out",)),
    ("export-web-exposure-inf", lambda c: ["export-web", c.w.glb, c.t / O, "--exposure", "inf"], ("--exposure",)),
    ("eval-limit-negative", lambda c: ["eval", c.w.run, "--limit", "-3"], ("--limit",)),
    ("eval-mesh-resolution", lambda c: ["eval", c.w.run, "--mesh-resolution", 2], ("--mesh-resolution",)),
    ("eval-lux-zero", lambda c: ["eval", c.w.run, "--lux-factor", 0], ("--lux-factor",)),
    ("priors-weights-alpha-nan", lambda c: ["priors", "weights", c.w.scene, "--alpha", "nan"], ("--alpha",)),
    ("priors-weights-beta-negative", lambda c: ["priors", "weights", c.w.scene, "--beta", "-1"], ("--beta",)),
    ("priors-segment-train-every", lambda c: ["priors", "segment", c.w.scene, "--train-every", 0], ("--train-every",)),
    ("priors-light-batch-size", lambda c: ["priors", "light", c.w.scene, "--batch-size", 0], ("--batch-size",)),
    ("priors-colour-reference", lambda c: ["priors", "colour", c.w.scene, "--reference", 99, "--out", c.t / O],
     ("--reference", "99")),
    ("sh-probe-rotate-nan", lambda c: ["priors", "sh-probe", c.w.probe, "--rotate-x", "nan"], ("--rotate-x",)),
    ("contact-sheet-n-zero", lambda c: ["contact-sheet", c.w.scene, "--out", c.t / "s.png", "-n", 0], ("-n",)),
    ("ablate-steps-zero", lambda c: ["ablate", c.w.scene, "--out", c.t / O, "--steps", 0], ("--steps",)),
    ("ablate-minutes-nan", lambda c: ["ablate", c.w.scene, "--out", c.t / O, "--minutes", "nan"], ("--minutes",)),
    ("infer-threads-negative", lambda c: ["infer", c.w.onnx, "--light", c.w.photos / "p0.png", "--threads", "-1"],
     ("--threads",)),
    ("infer-camera-spec", lambda c: ["infer", c.w.onnx, "--camera", "scene-0", "--out", c.t / "v.png"],
     ("--camera", "SCENE:SPLIT:INDEX")),
    ("unknown-command", lambda c: ["trian", c.w.scene], ("trian",)),
    ("train-many-manifest-missing", lambda c: ["train-many", c.t / "museum.json", "--out", c.t / O],
     ("museum.json", "not found")),
]
CASES += [Case(f"arg-{name}", argv, words) for name, argv, words in _ARGS]

# --- 5. resume: the run continues as it was started -------------------------------------------------------------
_OTHER_SAMPLER = "--no-dars" if DARS_DEFAULT else "--dars"  # the copied run was trained with the default sampler
_RESUME = lambda *extra: (lambda c: ["train", *extra, "--resume", "--out", c.t / "r", "--steps", 4])  # noqa: E731
# the copied run shades where the preset does: None (by scene type) shades this RGB scene, a room, once per ray
_OTHER_SHADE = "rays" if make_config("fast").deferred is False else "samples"
CASES += [
    Case("resume-other-scene", lambda c: ["train", c.t / "s2", "--resume", "--out", c.t / "r", "--steps", 4],
         ("s2", "scene", "another --out"), _both(_copy_run, lambda c: shutil.copytree(c.w.scene, c.t / "s2"))),
    Case("resume-other-preset", _RESUME("--preset", "paper"), ("--preset paper", "fast", "--force"), _copy_run),
    Case("resume-other-seed", _RESUME("--seed", "7"), ("--seed 7", "the run's: 0"), _copy_run),
    Case("resume-ablation-switch", _RESUME(_OTHER_SAMPLER), (_OTHER_SAMPLER,), _copy_run),  # not the run's sampler
    Case("resume-other-priors", _RESUME("--priors", "."), ("--priors",), _copy_run),
    Case("resume-other-light-residual", _RESUME("--light-residual", "off"), ("--light-residual off", "the run's: "),
         _copy_run),
    Case("resume-other-shade", _RESUME("--shade", _OTHER_SHADE), (f"--shade {_OTHER_SHADE}", "the run's: "),
         _copy_run),
    Case("resume-and-force", _RESUME("--force"), ("--resume", "--force"), _copy_run),
    Case("resume-no-checkpoint", lambda c: ["train", "--resume", "--out", c.t / "r", "--steps", 4],
         ("no checkpoint", "--force"), _both(_copy_run, lambda c: (c.t / "r" / "checkpoint.pt").unlink())),
    Case("resume-no-folder", lambda c: ["train", "--resume", "--out", c.t / "r", "--steps", 4], ("not found", "r")),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input(case, world, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ctx = SimpleNamespace(w=world, t=tmp_path)
    if case.setup is not None:
        case.setup(ctx)
    before = tree(tmp_path, world.root)
    code, out, err = run_cli(case.argv(ctx), capsys)
    assert code == case.code, err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1].startswith("dars"), err
    for word in case.words:
        assert word.lower() in err.lower(), f"{word!r} not in: {err}"
    assert out == ""
    assert tree(tmp_path, world.root) == before, "a file changed, or something was created"


def test_the_table_covers_every_command():
    from toolkit.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    covered = {str(a) for c in CASES for a in c.argv(SimpleNamespace(w=SimpleNamespace(
        **{k: Path(k) for k in ("scene", "run", "glb", "probe", "sh", "photos", "onnx", "root")}), t=Path("t")))[:1]}
    assert set(sub.choices) - covered == set()


# ============================================================================================== what succeeds
def test_train_force_beside_a_user_file(world):
    """The module's run was trained with force into a folder holding the user's notes: notes untouched, every file dars
    wrote listed in the manifest, normal permissions."""
    run = world.run
    assert (run / "notes.txt").read_text() == "my notes\n"
    man = json.loads((run / "dars_manifest.json").read_text())
    assert man["dars"] == "train" and "notes.txt" not in man["files"]
    assert {"config.json", "checkpoint.pt", "log.jsonl"} <= set(man["files"])
    umask = os.umask(0)
    os.umask(umask)
    for name in ("config.json", "checkpoint.pt", "dars_manifest.json"):
        assert stat.S_IMODE((run / name).stat().st_mode) == 0o666 & ~umask, name


def test_rerun_into_own_folder_force_beside_user_files_and_cleanup(world, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "r"
    for _ in range(2):  # a dars folder may be written again without --force
        code, _, err = run_cli(["render", world.run, "--out", out, "--limit", 1, "--orbit", 1], capsys)
        assert code == 0, err
    assert "orbit_000_rgb.png" in json.loads((out / "dars_manifest.json").read_text())["files"]
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "orbit_000_notes.txt").write_text("keep")
    code, _, err = run_cli(["render", world.run, "--out", mine, "--limit", 1, "--orbit", 1, "--force"], capsys)
    assert code == 0, err
    assert (mine / "orbit_000_notes.txt").read_text() == "keep" and (mine / "orbit_000_rgb.png").is_file()

    import toolkit.train.run as run_module

    def fail(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "new" / "x.png"))

    monkeypatch.setattr(run_module, "render_views", fail)  # fails after the folder was created
    code, _, err = run_cli(["render", world.run, "--out", tmp_path / "new" / "deeper", "--limit", 1], capsys)
    assert code == 1 and "no space left on device" in err and "Traceback" not in err
    assert not (tmp_path / "new").exists()  # no empty folder left behind


def test_sh_probe_writes_nothing_beside_its_input(world, tmp_path, capsys):
    probe = tmp_path / "probe.hdr"
    shutil.copy(world.probe, probe)
    code, out, err = run_cli(["priors", "sh-probe", probe, "--json"], capsys)
    assert code == 0, err and json.loads(out)["coeffs"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["probe.hdr"]
    code, out, err = run_cli(["priors", "sh-probe", probe, "--out", tmp_path / "o" / "sh.json"], capsys)
    assert code == 0 and (tmp_path / "o" / "sh.json").is_file()
    code, out, err = run_cli(["priors", "sh-probe", probe, "--out", tmp_path / "o" / "sh.json", "--force"], capsys)
    assert code == 0


def test_resume_cleans_stale_temp_files_and_force_restarts(world, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    run = tmp_path / "r"
    shutil.copytree(world.run, run)
    (run / ".checkpoint.pt.k1ll3d_9.tmp").write_bytes(b"half a checkpoint")
    (run / "snapshots").mkdir()  # a run with snapshots (its manifest lists the folder)
    (run / "snapshots" / ".checkpoint_1min.pt.abcdefgh.tmp").write_bytes(b"x")
    man = json.loads((run / "dars_manifest.json").read_text())
    (run / "dars_manifest.json").write_text(json.dumps({**man, "files": man["files"] + ["snapshots/"]}))
    (run / ".hidden.tmp").write_text("a user's file that only looks like a temp file")
    code, _, err = run_cli(["train", "--resume", "--out", run, "--steps", 3, "--quiet"], capsys)
    assert code == 0, err
    names = {p.name for p in run.rglob("*")}
    assert ".checkpoint.pt.k1ll3d_9.tmp" not in names and ".checkpoint_1min.pt.abcdefgh.tmp" not in names
    assert (run / ".hidden.tmp").is_file() and (run / "notes.txt").read_text() == "my notes\n"
    import torch

    assert torch.load(run / "checkpoint.pt", weights_only=False)["step"] == 3
    # --force starts again: dars's run files are replaced, the user's notes stay
    code, _, err = run_cli(["train", world.scene, "--out", run, "--steps", 1, "--force", "--quiet",
                            "--batch-rays", 256], capsys)
    assert code == 0, err
    assert torch.load(run / "checkpoint.pt", weights_only=False)["step"] == 1
    assert (run / "notes.txt").read_text() == "my notes\n" and (run / ".hidden.tmp").is_file()


def test_first_checkpoint_comes_early(world, tmp_path, monkeypatch):
    """Without waiting for ``checkpoint_every``: after FIRST_CHECKPOINT_STEPS steps (100; 2 here) or a minute."""
    import toolkit.train.folder as folder
    import toolkit.train.loop as loop
    from toolkit.train import train

    saved = []
    real = loop.save_torch
    monkeypatch.setattr(folder, "FIRST_CHECKPOINT_STEPS", 2)
    monkeypatch.setattr(loop, "save_torch", lambda path, ck: (saved.append((ck["step"], path.name)), real(path, ck)))
    train(world.scene, tmp_path / "r", tiny_config(steps=4, checkpoint_every=1000), progress_bar=False,
          log=lambda m: None)
    assert saved == [(2, "checkpoint.pt"), (4, "checkpoint.pt")]
    assert folder.first_checkpoint_due(SimpleNamespace(step=1, elapsed=61.0), tmp_path / "none.pt")
    assert not folder.first_checkpoint_due(SimpleNamespace(step=1, elapsed=5.0), tmp_path / "none.pt")


def test_read_only_output_place(world, tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    os.chmod(ro, 0o555)
    try:
        for argv in (["render", world.run, "--out", ro / "o"], ["priors", "colour", world.scene, "--out", ro / "c"],
                     ["contact-sheet", world.scene, "--out", ro / "s.png"]):
            code, _, err = run_cli(argv, capsys)
            assert code == 2 and "read-only" in err and "Traceback" not in err, err
        assert list(ro.iterdir()) == []
    finally:
        os.chmod(ro, 0o755)


@pytest.mark.parametrize("err_no,words", [
    (errno.ENOSPC, ("no space left", "free some space")), (errno.EACCES, ("permission denied",)),
    (errno.EISDIR, ("is a folder",)), (errno.ENOTDIR, ("not a folder",)), (errno.EROFS, ("read-only",)),
])
def test_os_errors_are_one_line_naming_the_path(world, tmp_path, capsys, monkeypatch, err_no, words):
    """An OS error while writing is one line (exit 1) naming the real file, not its temporary twin."""
    import toolkit.visualise as visualise

    def fail(scene, out, n=6):
        raise OSError(err_no, os.strerror(err_no), str(out.parent / f".{out.name}.abcdefgh.tmp"))

    monkeypatch.setattr(visualise, "contact_sheet", fail)
    code, _, err = run_cli(["contact-sheet", world.scene, "--out", tmp_path / "sheet.png"], capsys)
    assert code == 1 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert str(tmp_path / "sheet.png") in err and ".tmp" not in err, err
    for w in words:
        assert w in err


def test_disk_full_while_training_says_how_to_resume():
    from argparse import Namespace

    from toolkit.cli import describe_os_error

    e = OSError(errno.ENOSPC, "No space left on device", "/runs/a/.checkpoint.pt.x1y2z3w4.tmp")
    msg = describe_os_error(e, Namespace(command="train", out="/runs/a"))
    assert msg.startswith("no space left on device: /runs/a/checkpoint.pt") and "--resume --out /runs/a" in msg


def test_atomic_write_gives_normal_permissions(tmp_path):
    from toolkit.io import atomic_write, write_json

    old = os.umask(0o027)
    try:
        write_json(tmp_path / "a.json", {"a": 1})
        with atomic_write(tmp_path / "b.bin") as f:
            f.write(b"x")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.json").stat().st_mode) == 0o640
    assert stat.S_IMODE((tmp_path / "b.bin").stat().st_mode) == 0o640
    write_json(tmp_path / "c.json", {})
    assert stat.S_IMODE((tmp_path / "c.json").stat().st_mode) == 0o666 & ~old


def test_the_console_script_prints_no_traceback(world, tmp_path):
    """Two cases through the real `dars` executable (exit code and stderr as a shell sees them)."""
    dars = Path(sys.executable).with_name("dars")
    if not dars.is_file():
        pytest.skip("the dars console script is not installed in this environment")
    run = tmp_path / "r"
    shutil.copytree(world.run, run)
    (run / "checkpoint.pt").write_bytes((run / "checkpoint.pt").read_bytes()[:1000])
    for argv, word in (([str(run), "--out", str(tmp_path / "e")], "truncated"),):
        p = subprocess.run([str(dars), "eval", *argv], capture_output=True, text=True, timeout=300)
        assert p.returncode == 2 and word in p.stderr and "Traceback" not in p.stderr, p.stderr
    p = subprocess.run([str(dars), "train", str(world.scene), "--out", str(tmp_path / "o"), "--minutes", "nan"],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 2 and "--minutes" in p.stderr and "Traceback" not in p.stderr, p.stderr
    assert not (tmp_path / "o").exists() and not (tmp_path / "e").exists()
