"""dars train-many (toolkit.museum): manifest checks, a tiny museum end to end, resume without redoing work."""

import json

import pytest

from synthetic import make_scene
from toolkit._checks import DarsError
from toolkit.cli import main
from toolkit.museum import read_manifest, scene_stages


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("tiny"), n_train=24, n_test=4)


def _write(path, doc):
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("entry, message", [
    ({"scene": "S", "steps": 10, "stepz": 3}, r"entry 1 \('hall'\): unknown field\(s\) 'stepz'"),
    ({"scene": "S", "steps": "ten"}, r"entry 1 \('hall'\): field 'steps' must be a whole number > 0, got 'ten'"),
    ({"scene": "S"}, r"entry 1 \('hall'\): give a training length"),
    ({"steps": 5}, r"give exactly one of 'scene' .* or 'photos'"),
    ({"scene": "missing", "steps": 5}, r"field 'scene': .*missing not found"),
    ({"scene": "S", "steps": 5, "priors": ["weights", "sky"]}, r"field 'priors': unknown stage\(s\) 'sky'"),
    ({"scene": "S", "steps": 5, "train_args": "--seed 3"}, r"field 'train_args' must be a list of strings"),
])
def test_bad_manifest_names_entry_and_field(tiny, tmp_path, entry, message):
    entry = {"name": "hall", **{k: (str(tiny) if v == "S" else v) for k, v in entry.items()}}
    with pytest.raises(DarsError, match=message):
        read_manifest(_write(tmp_path / "m.json", [entry]))


def test_manifest_forms(tiny, tmp_path):
    (tmp_path / "a.json").write_text("[{")
    with pytest.raises(DarsError, match="a.json is not valid JSON"):
        read_manifest(tmp_path / "a.json")
    with pytest.raises(DarsError, match=r"entry 1: expected a mapping"):
        read_manifest(_write(tmp_path / "c.json", [3]))
    with pytest.raises(DarsError, match=r"entry 2 \('a'\): field 'name': 'a' is also entry 1"):
        read_manifest(_write(tmp_path / "b.json", [{"name": "a", "scene": str(tiny), "steps": 3}] * 2))
    (tmp_path / "m.yaml").write_text(f"defaults:\n  steps: 7\n  priors: []\nscenes:\n  - scene: {tiny}\n"
                                     f"  - name: two\n    scene: {tiny}\n    minutes: 0.5\n    nproc: 2\n")
    a, b = read_manifest(tmp_path / "m.yaml")
    assert (a.name, a.steps, a.priors) == (tiny.name, 7, ()) and (b.steps, b.minutes) == (0, 0.5)
    train = [s for s in scene_stages(b, tmp_path / "out" / "two") if s.name == "train"][0]
    assert "torch.distributed.run" in train.argv and "--nproc_per_node" in train.argv  # data-parallel training

    (tmp_path / "photos").mkdir()
    (c,) = read_manifest(_write(tmp_path / "p.json", [{"name": "hall", "photos": "photos", "steps": 5}]))
    stages = scene_stages(c, tmp_path / "out" / "hall")
    assert [s.name for s in stages] == ["poses", "priors-weights", "train", "eval", "export-asset"]
    scene = str(tmp_path / "out" / "hall" / "scene")
    assert stages[0].argv[3:6] == ["poses", str(tmp_path / "photos"), "--out"] and scene in stages[0].argv
    assert scene in stages[1].argv and scene in stages[2].argv  # the later stages read the posed scene


def test_layout_prior_stage_is_fitted_in_the_frame_training_loads(tiny, tmp_path):
    (job,) = read_manifest(_write(tmp_path / "m.json", [{"name": "r", "scene": str(tiny), "steps": 5,
                                                          "priors": ["layout", "weights"],
                                                          "train_args": ["--layout-depth", "0.1", "--no-upright"]}]))
    stages = scene_stages(job, tmp_path / "out" / "r")
    assert [s.name for s in stages][:2] == ["priors-weights", "priors-layout"]  # PRIOR_STAGES order
    lay = stages[1].argv
    assert lay[3:5] == ["priors", "layout"] and "--no-upright" in lay
    train = stages[2].argv
    assert "--priors" in train and train[train.index("--priors") + 1] == str(tmp_path / "out" / "r" / "priors")


def test_train_many_runs_and_resumes(tiny, tmp_path, capsys):
    man = _write(tmp_path / "museum.json", [{
        "name": "room1", "scene": str(tiny), "steps": 60, "priors": ["weights"],
        "train_args": ["--batch-rays", "512"], "eval_args": ["--limit", "2"],
        "asset_args": ["--resolution", "32", "--faces", "2000", "--texture", "64", "--ao-samples", "0"]}])
    out = tmp_path / "out"
    assert main(["train-many", str(man), "--out", str(out), "--threads", "1"]) == 0
    summary = json.loads((out / "summary.json").read_text())["scenes"]
    (row,) = summary
    assert row["status"] == "done", row
    assert row["ran"] == ["priors-weights", "train", "eval", "export-asset"]
    assert row["steps"] == 60 and row["psnr"] > 5 and row["asset_bytes"] > 0 and row["seconds"] > 0
    assert (out / "room1" / "asset" / "scene.glb").is_file()
    md = (out / "summary.md").read_text()
    assert "| room1 | done | 60 |" in md
    capsys.readouterr()

    # run again: nothing is redone; a longer training would resume the run, then eval and asset follow it
    assert main(["train-many", str(man), "--out", str(out), "--dry-run", "--json"]) == 0
    plan = json.loads(capsys.readouterr().out)
    assert not any(s["run"] for s in plan["room1"])
    _write(man, [{**json.loads(man.read_text())[0], "steps": 70}])
    assert main(["train-many", str(man), "--out", str(out), "--dry-run", "--json"]) == 0
    plan = {s["stage"]: s for s in json.loads(capsys.readouterr().out)["room1"]}
    assert [k for k, s in plan.items() if s["run"]] == ["train", "eval", "export-asset"]
    assert "--resume" in plan["train"]["command"] and "70" in plan["train"]["command"]


def test_failing_scenes_are_reported_and_the_rest_go_on(tiny, tmp_path, capsys):
    man = _write(tmp_path / "m.json", {"defaults": {"steps": 5, "priors": [], "train_args": ["--batch-rays", "8"]},
                                       "scenes": [{"name": "a", "scene": str(tiny)}, {"name": "b", "scene": str(tiny)}]})
    out = tmp_path / "out"
    assert main(["train-many", str(man), "--out", str(out), "--jobs", "2"]) == 2
    assert "2 of 2 scenes failed (a, b)" in capsys.readouterr().err
    rows = json.loads((out / "summary.json").read_text())["scenes"]
    assert [r["name"] for r in rows] == ["a", "b"]
    for r in rows:
        assert r["status"] == "failed" and r["failed_stage"] == "train" and r["exit_code"] == 2
        assert "batch-rays 8" in r["error"] and (out / r["name"] / "logs" / "train.log").is_file()
    assert "failed at train" in (out / "summary.md").read_text()
