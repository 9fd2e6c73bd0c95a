"""Tests of samples/render_object.py: object captures (a reference mesh under an HDR probe) with ground truth.

They skip with a reason where mitsuba, the probes or the meshes (``../shared/data``) are missing."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "samples"))
import render_object as ro  # noqa: E402

HAS_MITSUBA = importlib.util.find_spec("mitsuba") is not None
needs_data = pytest.mark.skipif(
    not (HAS_MITSUBA and (ro.MESH_ROOT / ro.MESHES["bunny"][0]).is_file() and (ro.ENVMAPS / "probulator_pisa_256x128.hdr").is_file()),
    reason=f"needs mitsuba, the meshes in {ro.MESH_ROOT} and the probes in {ro.ENVMAPS}")


def test_draws_are_deterministic_and_cover_the_probes():
    assert ro.draw("spot", 3) == ro.draw("spot", 3)
    assert ro.draw("spot", 3) != ro.draw("spot", 4)
    draws = [ro.draw(m, s) for m in ro.MESHES for s in range(40)]
    assert {d.env for d in draws} == set(ro.PROBES)
    assert 0.1 < np.mean([d.metallic for d in draws]) < 0.4
    assert all(d.color is None for d in draws if d.mesh in ("spot", "bob"))  # textured meshes keep their texture
    assert ro.draw("bunny", 0, env="pisa").env == "pisa"
    with pytest.raises(ro.ConfigError, match="unknown mesh"):
        ro.draw("teapot", 0)
    with pytest.raises(ro.ConfigError, match="unknown probe"):
        ro.draw("bunny", 0, env="moon")


def test_orbit_cameras_look_at_the_centre_and_frame_the_sphere():
    fov = math.radians(40)
    cams = ro.orbit_cameras(50, 0, 1.0, fov, 0.85)
    for c in cams:
        np.testing.assert_allclose(c[:3, :3] @ c[:3, :3].T, np.eye(3), atol=1e-9)
        assert np.linalg.det(c[:3, :3]) > 0
        eye, fwd = c[:3, 3], -c[:3, 2]
        np.testing.assert_allclose(np.cross(fwd, -eye / np.linalg.norm(eye)), 0, atol=1e-9)  # looks at the origin
        assert abs(c[2, 0]) < 1e-9  # no roll: the x axis is level
        # the unit sphere's angular radius is 85 % of the half field of view
        assert math.asin(1.0 / np.linalg.norm(eye)) == pytest.approx(0.85 * fov / 2, rel=1e-9)
    elev = np.degrees(np.arcsin(cams[:, 2, 3] / np.linalg.norm(cams[:, :3, 3], axis=1)))
    assert elev.min() > -20 and elev.max() < 75 and elev.max() - elev.min() > 60


@needs_data
def test_tiny_object_render_loads_as_an_object_with_ground_truth(tmp_path):
    from toolkit.scene import load_scene

    out = tmp_path / "bunny"
    opts = ro.ObjectOptions(size=24, n_train=3, n_test=1, spp=16, gt_subsamples=2, progress=False)
    summary = ro.render_object("bunny", 0, out, opts, variant="scalar_rgb")
    assert summary["views"] == {"train": 3, "test": 1} and summary["exposure"] > 0
    meta = json.loads((out / "transforms_train.json").read_text())
    assert "aabb" not in meta and len(meta["sh"]) == 9 and meta["render"]["draw"]["mesh"] == "bunny"
    sc = load_scene(out, "train")
    rgba = sc.load_image(0, with_alpha=True).numpy()
    alpha = rgba[3]
    assert (alpha < 0.01).mean() > 0.3 and (alpha > 0.99).mean() > 0.05  # a transparent background around the object
    nrm = sc.load_extra(0, "normal").permute(1, 2, 0).numpy()
    hit = alpha > 0.99
    norms = np.linalg.norm(nrm[hit], axis=-1)
    assert np.all(np.abs(norms - 1) < 0.05)  # unit world normals on the object
    assert np.all(np.abs(nrm[alpha < 0.01]).max(-1) < 0.01)  # zero (encoded 0) where nothing was hit
    sem = sc.load_extra(0, "semantic").numpy()
    assert set(np.unique(sem[hit])) == {ro.CLASSES["other"]} and set(np.unique(sem[alpha < 0.01])) == {ro.BACKGROUND}


@needs_data
def test_object_cache_renders_once_and_again_when_the_options_change(tmp_path):
    opts = ro.ObjectOptions(size=16, n_train=2, n_test=1, spp=4, gt_subsamples=1, progress=False)
    a = ro.ensure_object("spot", 1, opts, root=tmp_path, variant="scalar_rgb")
    assert a == tmp_path / "objects" / "spot_s1" and (a / "transforms_test.json").is_file()
    stamp = json.loads((a / "stamp.json").read_text())
    assert stamp["hash"] == ro.cache_stamp("spot", 1, opts)["hash"] and stamp["draw"]["mesh"] == "spot"
    before = (a / "train" / "r_000.png").stat().st_mtime_ns
    assert ro.ensure_object("spot", 1, opts, root=tmp_path, variant="scalar_rgb") == a
    assert (a / "train" / "r_000.png").stat().st_mtime_ns == before  # cached: not rendered again
    other = ro.ObjectOptions(size=20, n_train=2, n_test=1, spp=4, gt_subsamples=1, progress=False)
    assert ro.ensure_object("spot", 1, other, root=tmp_path, variant="scalar_rgb") == a
    assert json.loads((a / "transforms_train.json").read_text())["w"] == 20
    assert [p.name for p in (tmp_path / "objects").iterdir() if p.is_dir()] == ["spot_s1"]  # no temporary folder left
    assert (tmp_path / "objects" / ".lock-spot_s1").is_file()  # renders of one capture wait for each other
