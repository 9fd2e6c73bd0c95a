"""toolkit.priors: where labels come from (labels_for), the trainer's reader (read_priors), the output folder."""

import json

import numpy as np
import pytest
import torch
from _synthetic_gallery import write_scene

from toolkit._checks import DarsError
from toolkit.io import write_png
from toolkit.priors import OutputDir, labels_for, prepare_out_dir, priors_path, read_priors
from toolkit.scene import load_scene


@pytest.fixture
def labelled(tmp_path):
    return load_scene(write_scene(tmp_path / "lab", n_train=3, n_test=1, size=16), "train")


@pytest.fixture
def bare(tmp_path):
    return load_scene(write_scene(tmp_path / "bare", n_train=3, n_test=1, size=16, with_labels=False), "train")


def _predict(scene, folder, frames=None, value=2):
    for i in range(len(scene)) if frames is None else frames:
        write_png(folder / f"{scene.frames[i].key}.png", np.full((16, 16), value, np.uint8))


def test_labels_for_sources(labelled, bare, tmp_path):
    lab, src = labels_for(labelled, "auto", None)
    assert src == "scene" and lab.shape == (3, 16, 16) and lab.dtype == torch.int64
    assert labels_for(labelled, "none", None) == (None, "none")
    seg = tmp_path / "seg"
    assert labels_for(bare, "auto", seg) == (None, "none")  # no predictions yet
    _predict(bare, seg, frames=[0, 1])
    assert labels_for(bare, "auto", seg) == (None, "none")  # all frames or none: frame 2 has no prediction
    lab, src = labels_for(bare, "auto", seg, frames=[1])  # one frame: its prediction
    assert src == "segment" and lab.shape == (1, 16, 16) and int(lab.max()) == 2
    with pytest.raises(DarsError, match=r"frame 2 .* has no segment labels"):
        labels_for(bare, "segment", seg)
    with pytest.raises(DarsError, match=r"frame 0 .* has no scene labels"):
        labels_for(bare, "scene", seg)
    _predict(labelled, seg, value=5)
    assert labels_for(labelled, "segment", seg)[1] == "segment"  # an explicit source wins over the scene's labels
    assert int(labels_for(labelled, "segment", seg)[0].max()) == 5


def test_read_priors_reads_every_stage(bare, tmp_path):
    root = tmp_path / "priors"
    p = read_priors(bare, root)
    assert p.labels is None and p.labels_source == "none" and p.weights is None and p.light is None
    assert read_priors(bare, root, labels=None).labels_source == "off"
    _predict(bare, root / "segment")
    (root / "weights").mkdir(parents=True)
    for i, f in enumerate(bare.frames):
        np.save(root / "weights" / f"{f.key}.npy", np.full((16, 16), 0.25 * i, np.float16))
    (root / "weights" / "weights.json").write_text(json.dumps({"images": [{"key": bare.frames[1].key,
                                                                             "distortion_loss": 0.5}]}))
    (root / "light").mkdir()
    (root / "light" / "light.json").write_text(json.dumps({"coeffs": np.arange(27).reshape(9, 3).tolist()}))
    p = read_priors(bare, root)
    assert p.labels.data.dtype == torch.uint8 and p.labels_source == f"predicted ({root / 'segment'})"
    assert p.labels.data.shape == (3 * 16 * 16,) and int(p.labels[1].max()) == 2
    assert p.weights.data.dtype == torch.uint8 and p.weights.quantised and len(p.weights) == 3
    assert p.weights[2].shape == (16, 16) and abs(float(p.weights[2].max()) - 0.5) <= 0.5 / 255 + 1e-6
    assert p.distortion.tolist() == [0.0, 0.5, 0.0] and p.weights_source == f"loaded ({root / 'weights'})"
    assert p.light.shape == (9, 3) and float(p.light[8, 2]) == 26.0
    assert read_priors(bare, root, weights=False).weights is None
    assert priors_path(bare, "light", root) == root / "light"
    assert priors_path(bare, "light") == bare.priors_dir("light")


def test_read_priors_ranks_w_before_storing_it_at_8_bits(bare, tmp_path):
    """``weights_normalise="quantile"`` ranks the map as written (float16), then stores it at 8 bits: a map whose
    values all fall within one 1/255 step still spreads over [0, 1] (ranking the stored bytes would tie them all)."""
    from toolkit.edges import quantile_normalise

    root = tmp_path / "priors"
    (root / "weights").mkdir(parents=True)
    ramp = (0.01 + 0.0025 * np.linspace(0.0, 1.0, 256)).reshape(16, 16).astype(np.float16)  # all round to 3 / 255
    for f in bare.frames:
        np.save(root / "weights" / f"{f.key}.npy", ramp)
    raw = read_priors(bare, root, weights_normalise="none").weights
    assert bool((raw.data == 3).all())  # stored as written: one 8-bit level
    ranked = read_priors(bare, root, weights_normalise="quantile").weights
    assert ranked.data.dtype == torch.uint8
    want = quantile_normalise(torch.from_numpy(ramp.astype(np.float32))[None])[0]
    assert float((ranked[0] - want).abs().max()) <= 0.5 / 255 + 1e-6
    assert float(ranked[0].min()) < 0.05 and float(ranked[0].max()) > 0.95


def test_output_dir_keeps_user_files(bare, tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (out / "mine.txt").write_text("user")
    with pytest.raises(DarsError, match="not empty .*mine.txt.* --force"):  # not a dars folder
        prepare_out_dir(bare, "weights", out, ["ours.txt"])
    with pytest.raises(DarsError, match="holds mine.txt, which dars did not write"):  # never over a user file
        prepare_out_dir(bare, "weights", out, ["mine.txt"], force=True)
    d = prepare_out_dir(bare, "weights", out, ["ours.txt"], force=True)  # beside it
    d.file("ours.txt").write_text("dars")
    d.finish()
    man = json.loads((out / "dars_manifest.json").read_text())
    assert man["files"] == ["ours.txt"] and man["dars"] == "priors weights"
    assert (out / "mine.txt").read_text() == "user"
    assert isinstance(prepare_out_dir(bare, "weights", out, ["ours.txt"]), OutputDir)  # ours: may be rewritten


def test_read_priors_resizes_maps_made_at_another_downscale(tmp_path):
    """Priors computed on the full-size photos serve a run trained with --downscale 2 (resized to the frames'
    size: nearest for labels, area for W); a map that is not a scaled copy of its frame is refused."""
    scene_dir = write_scene(tmp_path / "s", n_train=2, n_test=1, size=16, with_labels=False)
    root = tmp_path / "priors"
    full = load_scene(scene_dir, "train")
    _predict(full, root / "segment", value=3)
    (root / "weights").mkdir(parents=True)
    for f in full.frames:
        w = np.zeros((16, 16), np.float16)
        w[:, 8:] = 1.0
        np.save(root / "weights" / f"{f.key}.npy", w)
    half = load_scene(scene_dir, "train", downscale=2)
    p = read_priors(half, root)
    assert p.labels[0].shape == (8, 8) and int(p.labels[0].min()) == 3
    w0 = p.weights[0]
    assert w0.shape == (8, 8) and float(w0[:, :4].max()) == 0.0 and float(w0[:, 4:].min()) == 1.0
    assert "2 resized" in p.weights_source
    np.save(root / "weights" / f"{full.frames[1].key}.npy", np.zeros((16, 5), np.float16))
    with pytest.raises(DarsError, match="not a scaled copy"):
        read_priors(half, root)


def test_cli_weights_at_a_downscale_serve_a_full_size_run(tmp_path, capsys):
    """`dars priors weights --downscale 2` writes half-size maps; the full-size trainer reads them enlarged."""
    from toolkit.cli import main

    scene_dir = write_scene(tmp_path / "s", n_train=2, n_test=1, size=16, with_labels=False)
    assert main(["priors", "weights", str(scene_dir), "--downscale", "2", "--json"]) == 0
    capsys.readouterr()
    full = load_scene(scene_dir, "train")
    assert np.load(priors_path(full, "weights") / f"{full.frames[0].key}.npy").shape == (8, 8)
    p = read_priors(full)
    assert p.weights[0].shape == (16, 16) and "2 resized" in p.weights_source
