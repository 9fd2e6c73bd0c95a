import json
import re
from pathlib import Path

import pytest

from _eval_scene import add_ground_truth
from synthetic import make_scene
from toolkit._checks import ConfigError, DarsError
from toolkit.ablation import VARIANT_LABELS, VARIANTS, run_ablation
from toolkit.evaluate import METRIC_KEYS


@pytest.fixture(scope="module")
def ablation(tmp_path_factory):
    """The six variants for 20 steps each through the CLI in JSON mode (the whole ablation, tiny budget)."""
    import contextlib
    import io

    from toolkit.cli import main

    scene = add_ground_truth(make_scene(tmp_path_factory.mktemp("ablscene")), patch=True)
    out = tmp_path_factory.mktemp("abl") / "out"
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        rc = main(["ablate", str(scene), "--out", str(out), "--steps", "20", "--batch-rays", "512", "--limit", "3",
                   "--threads", "1", "--json", "--quiet"])
    assert rc == 0, stderr.getvalue()
    return scene, out, stdout.getvalue(), stderr.getvalue()


def test_ablation_trains_all_six_variants_under_one_budget(ablation):
    scene, out, stdout, stderr = ablation
    doc = json.loads(stdout)  # stdout is exactly the ablation JSON
    assert doc == json.loads((out / "ablation.json").read_text())
    assert [v["name"] for v in doc["variants"]] == list(VARIANTS)
    assert doc["budget"] == {"steps": 20, "minutes": 0.0} and doc["seed"] == 0
    for v in doc["variants"]:
        assert v["training"]["steps"] == 20, v["name"]
        assert v["training"]["field_steps"] == 20, v["name"]  # 20 steps end before eq. 22's first l_env step
        assert v["training"]["variant"] == v["name"]
        assert set(v["metrics"]) == set(METRIC_KEYS)
        assert {k for k, x in v["metrics"].items() if x is None} == set(v["unavailable"])
        assert (out / v["name"] / "eval" / "metrics.json").is_file()
        assert v["view_consistency_curve"]["keys"] == doc["variants"][0]["view_consistency_curve"]["keys"]
    full, nerf = doc["variants"][0], doc["variants"][-1]
    # the priors come from the training photos (not the evaluated test split) and every variant trains with them
    assert json.loads((out / "priors" / "priors.json").read_text())["split"] == "train"
    assert full["training"]["priors"]["labels"].startswith("predicted"), full["training"]["priors"]
    assert full["training"]["priors"]["metal"].startswith("predicted"), full["training"]["priors"]
    assert all(d is None or d == 0 for d in full["delta_vs_full"].values())
    assert nerf["delta_vs_full"]["psnr"] == pytest.approx(nerf["metrics"]["psnr"] - full["metrics"]["psnr"])
    assert "no material decomposition" in nerf["unavailable"]["albedo_mae"]
    assert "no light model" in nerf["unavailable"]["env_light_l2"]
    assert full["metrics"]["env_light_l2"] is not None and full["metrics"]["view_consistency"] is not None
    for k, name in enumerate(VARIANTS, 1):  # progress per variant on stderr
        assert f"[ablate {k}/6] {VARIANT_LABELS[name]}: training" in stderr


def test_ablation_markdown_table_and_figures(ablation):
    _, out, stdout, _ = ablation
    doc = json.loads(stdout)
    md = (out / "ablation.md").read_text()
    table = [ln for ln in md.splitlines() if ln.startswith("| ")]
    assert table[0].startswith("| variant | steps | min | PSNR (dB) ↑ | SSIM ↑ | LPIPS ↓ | FLIP ↓ | Albedo MAE ↓ | "
                               "Roughness RMSE ↓ | Env-light L2 ↓ | View consistency ↓ |")
    for v in doc["variants"]:
        row = next(ln for ln in table if ln.startswith(f"| {v['label']} |"))
        assert f"{v['metrics']['psnr']:.2f}" in row
    nerf_row = next(ln for ln in table if ln.startswith("| Standard NeRF |"))
    d = doc["variants"][-1]["delta_vs_full"]["psnr"]
    assert f"({'+' if d >= 0 else '−'}{abs(d):.2f})" in nerf_row
    assert "**lpips** (all variants)" in md
    for target in re.findall(r"\]\(([^)\s]+)\)", md):
        assert (out / target).is_file(), f"broken link {target}"
    assert (out / "ablation_brightness.png").is_file() and (out / "ablation_weights.png").is_file()


def test_ablation_refuses_mixed_budgets_and_bad_variants(ablation, tmp_path):
    scene, out, _, _ = ablation
    with pytest.raises(DarsError, match="another steps"):
        run_ablation(scene, out, steps=21, variants=["full"], log=lambda m: None)
    with pytest.raises(ConfigError, match="exactly one budget"):
        run_ablation(scene, tmp_path / "x", log=lambda m: None)
    with pytest.raises(ConfigError, match="unknown variant"):
        run_ablation(scene, tmp_path / "x", steps=2, variants=["mip"], log=lambda m: None)
    with pytest.raises(ConfigError, match="would change what the variants compare"):
        run_ablation(scene, tmp_path / "x", steps=2, overrides={"dars": False}, log=lambda m: None)


def test_cli_ablate_bad_input(tmp_path, capsys):
    from toolkit.cli import main

    assert main(["ablate", str(tmp_path / "nope"), "--out", str(tmp_path / "o"), "--steps", "2", "--quiet"]) == 2
    assert "error" in capsys.readouterr().err
    assert main(["ablate", str(tmp_path), "--out", str(tmp_path / "o")]) == 2  # a budget is required
    assert "--steps" in capsys.readouterr().err and not (tmp_path / "o").exists()


# ---------------------------------------------------------------------------- several seeds
def test_seed_statistics_and_paired_differences():
    import statistics

    from toolkit.ablation import paired_differences, parse_seeds, seed_statistics

    st = seed_statistics([29.5, 30.25, None, 28.75])
    assert st["n"] == 3 and st["values"] == [29.5, 30.25, None, 28.75]
    assert st["mean"] == pytest.approx(statistics.mean([29.5, 30.25, 28.75]))
    assert st["std"] == pytest.approx(statistics.stdev([29.5, 30.25, 28.75]))  # sample std (n − 1)
    assert seed_statistics([1.5]) == {"values": [1.5], "n": 1, "mean": 1.5, "std": None}
    assert seed_statistics([None, None]) == {"values": [None, None], "n": 0, "mean": None, "std": None}
    d = paired_differences([30.0, 31.0, 29.0, None], [29.5, 30.0, 29.5, 30.0])
    assert d["values"] == [0.5, 1.0, -0.5, None] and d["n"] == 3
    assert d["mean"] == pytest.approx(1 / 3) and d["std"] == pytest.approx(statistics.stdev([0.5, 1.0, -0.5]))
    assert d["within_seed_noise"] is True  # |0.33| < 0.76
    big = paired_differences([31.0, 31.1, 30.9], [30.0, 30.0, 30.0])
    assert big["within_seed_noise"] is False and big["mean"] == pytest.approx(1.0)
    assert paired_differences([1.0], [0.5])["within_seed_noise"] is None  # one pair: no spread
    with pytest.raises(ValueError, match="2 values against 1"):
        paired_differences([1.0, 2.0], [1.0])
    assert parse_seeds("0,1, 2") == [0, 1, 2]
    for bad in ("", "0,0", "-1", "a,b"):
        with pytest.raises(ConfigError, match="seeds"):
            parse_seeds(bad)


@pytest.fixture(scope="module")
def two_seeds(tmp_path_factory):
    """full and no_semantics × seeds 0, 1 for 4 steps each, with the scene's ground-truth labels."""
    from toolkit.evaluate import EvalConfig

    scene = add_ground_truth(make_scene(tmp_path_factory.mktemp("abl2scene"), n_train=16, n_test=3))
    out = tmp_path_factory.mktemp("abl2") / "out"
    lines: list[str] = []
    res = run_ablation(scene, out, steps=4, seeds=[0, 1], variants=["no_semantics", "full"],
                       overrides={"batch_rays": 512, "labels": "ground-truth"}, eval_cfg=EvalConfig(limit=2),
                       log=lines.append)
    return scene, out, res, lines


def test_ablation_several_seeds_json(two_seeds):
    import statistics

    scene, out, res, lines = two_seeds
    doc = json.loads((out / "ablation.json").read_text())
    assert doc == json.loads(json.dumps(res.to_json()))
    assert doc["seeds"] == [0, 1] and doc["seed"] == 0 and doc["layout"] == "OUT/<variant>/seed_<s>/"
    assert [v["name"] for v in doc["variants"]] == ["full", "no_semantics"]  # full first
    assert sum("training (4 steps" in ln for ln in lines) == 4 and "[ablate 4/4] w/o semantic input (seed 1)" in \
        "\n".join(lines)
    by = {v["name"]: v for v in doc["variants"]}
    full = by["full"]
    for v in doc["variants"]:
        assert v["seeds"] == [0, 1] and [r["seed"] for r in v["runs"]] == [0, 1]
        for r in v["runs"]:
            assert r["run"] == str(out / v["name"] / f"seed_{r['seed']}")
            assert (out / v["name"] / f"seed_{r['seed']}" / "eval" / "metrics.json").is_file()
            assert r["training"]["steps"] == 4
            saved = json.loads((Path(r["run"]) / "config.json").read_text())["config"]
            assert saved["seed"] == r["seed"] and saved["labels"] == "ground-truth" == r["inputs"]["labels"]
            assert r["inputs"]["ground_truth"] == ["semantic labels", "metal masks"]
        for k in METRIC_KEYS:
            vals = [r["metrics"][k] for r in v["runs"]]
            assert v["per_seed"][k] == vals
            st = v["summary"][k]
            if None in vals:
                assert st["mean"] is None and v["metrics"][k] is None
                continue
            assert st["n"] == 2 and st["mean"] == pytest.approx(statistics.mean(vals))
            assert st["std"] == pytest.approx(statistics.stdev(vals)) and v["metrics"][k] == st["mean"]
            diffs = [a - b for a, b in zip(vals, full["per_seed"][k])]  # paired: the same seed
            p = v["paired_vs_full"][k]
            assert p["values"] == pytest.approx(diffs) and p["n"] == 2
            assert p["mean"] == pytest.approx(statistics.mean(diffs)) and v["delta_vs_full"][k] == p["mean"]
            assert p["std"] == pytest.approx(statistics.stdev(diffs))
            assert p["within_seed_noise"] == (abs(p["mean"]) < p["std"])
            assert [r["delta_vs_full"][k] for r in v["runs"]] == pytest.approx(diffs)
    assert all(x == 0 for k in ("psnr", "ssim") for x in full["paired_vs_full"][k]["values"])
    nosem = by["no_semantics"]
    assert nosem["within_seed_noise"] == [k for k in ("psnr", "ssim", "albedo_mae", "roughness_rmse", "normal_mae",
                                                      "miou") if nosem["paired_vs_full"][k]["within_seed_noise"]]
    assert full["summary"]["albedo_mae"]["n"] == 2 and nosem["paired_vs_full"]["normal_mae"]["n"] == 2
    assert full["summary"]["miou"]["n"] == 2 and nosem["metrics"]["miou"] is None  # no semantic input: head untrained
    assert nosem["noise_note"] and doc["inputs"] == {"labels": ["ground-truth"],
                                                     "ground_truth": ["metal masks", "semantic labels"]}
    # no semantic input: labels still feed L_mat, but neither L_semantic nor W
    for r in nosem["runs"]:
        assert r["inputs"]["labels_used_by"] == "L_mat" and r["training"]["priors"]["weights"] == "computed (G+M)"
        assert r["training"]["switches"]["semantics"] is False and r["training"]["switches"]["mat_labels"] is True
        logged = [json.loads(x) for x in (Path(r["run"]) / "log.jsonl").read_text().splitlines() if x.strip()]
        train_rows = [x for x in logged if x.get("kind") == "train"]
        assert train_rows and all("semantic" not in x for x in train_rows) and any(x.get("mat", 0) > 0 for x in train_rows)
    for r in full["runs"]:
        assert r["inputs"]["labels_used_by"] == "L_semantic, W (E), L_mat"
        assert r["training"]["priors"]["weights"] == "computed (G+E+M)"


def test_ablation_several_seeds_markdown_and_layout(two_seeds, tmp_path):
    scene, out, res, _ = two_seeds
    md = (out / "ablation.md").read_text()
    for heading in ("## Per seed", "## Paired differences against the full model", "## What each variant removes",
                    "## Inputs"):
        assert heading in md
    doc = res.to_json()
    nosem = doc["variants"][1]
    paired_md = md.split("## Paired differences against the full model")[1]
    row = next(ln for ln in paired_md.splitlines() if ln.startswith("| w/o semantic input — mean ± std | n = 2 |"))
    p = nosem["paired_vs_full"]["psnr"]
    assert f"{'+' if p['mean'] >= 0 else '−'}{abs(p['mean']):.2f} ± {p['std']:.2f}" in row
    assert f"- **w/o semantic input**: {nosem['noise_note']}" in md
    assert "Ground truth fed to training: metal masks, semantic labels" in md
    for target in re.findall(r"\]\(([^)\s]+)\)", md):
        assert (out / target).is_file(), f"broken link {target}"
    from toolkit.ablation import WALL_CLOCK_WARNING
    from toolkit.report import _ablation_markdown, ablation_text

    minutes_doc = dict(doc, budget={"steps": 0, "minutes": 0.1, "warning": WALL_CLOCK_WARNING})
    warned = _ablation_markdown(minutes_doc, {}, out)
    assert "**Warning — wall-clock budget" in warned and "Full DARS-NeRF (seed 1) 4" in warned
    assert "warning: wall-clock budget" in ablation_text(minutes_doc)
    assert "mean ± sample std" in ablation_text(doc) and "w/o semantic input vs full (paired)" in ablation_text(doc)
    # re-running reuses every run; another layout or seed setting is refused
    lines: list[str] = []
    again = run_ablation(scene, out, steps=4, seeds=[0, 1], variants=["full", "no_semantics"],
                         overrides={"batch_rays": 512, "labels": "ground-truth"}, log=lines.append)
    assert all(v.reused for v in again.variants) and sum("resuming/reusing" in ln for ln in lines) == 4
    with pytest.raises(DarsError, match="per-seed runs"):
        run_ablation(scene, out, steps=4, variants=["full"], log=lambda m: None)
    with pytest.raises(DarsError, match="another labels"):
        run_ablation(scene, out, steps=4, seeds=[0, 1], variants=["full"], overrides={"batch_rays": 512},
                     log=lambda m: None)
    with pytest.raises(ConfigError, match="not both"):
        run_ablation(scene, tmp_path / "x", steps=4, seed=1, seeds=[0, 1], log=lambda m: None)
    with pytest.raises(ConfigError, match="distinct"):
        run_ablation(scene, tmp_path / "x", steps=4, seeds=[1, 1], log=lambda m: None)


def test_ablation_single_seed_folder_refuses_several_seeds(ablation):
    scene, out, _, _ = ablation
    with pytest.raises(DarsError, match="holds a single-seed run"):
        run_ablation(scene, out, steps=20, seeds=[0, 1], variants=["full"], log=lambda m: None)


def test_cli_ablate_seed_options(tmp_path, capsys):
    from toolkit.cli import main

    scene = make_scene(tmp_path / "s", n_train=4, n_test=1)
    assert main(["ablate", str(scene), "--out", str(tmp_path / "o"), "--steps", "2", "--seed", "1", "--seeds", "0,1"]) == 2
    assert "not allowed with argument" in capsys.readouterr().err
    assert main(["ablate", str(scene), "--out", str(tmp_path / "o"), "--steps", "2", "--seeds", "0,0"]) == 2
    assert "distinct" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_old_no_semantics_configs_keep_both_switches_off():
    from toolkit.evaluate import variant_of
    from toolkit.train import TrainConfig, make_config

    new = make_config("fast", dars=True, semantics=False)
    assert new.semantics is False and new.mat_labels is True and variant_of(new) == "no_semantics"
    old = new.to_dict()
    del old["mat_labels"]  # saved before the switches were separated: semantics=False also dropped L_mat's classes
    loaded = TrainConfig.from_dict(old)
    assert loaded.mat_labels is False and variant_of(loaded) == "no_semantics_legacy"
    full = make_config("fast").to_dict()
    del full["mat_labels"]
    assert TrainConfig.from_dict(full).mat_labels is True
    assert variant_of(make_config("fast", dars=True, mat_loss=False)) == "no_mat_loss"


def test_variants_option_takes_commas_hyphens_and_spaces():
    """``--variants full,no-dars`` (the issue's form) and ``--variants full no_dars`` name the same variants."""
    from toolkit.cli import build_parser
    from toolkit.cli.evaluate import flat_variants

    p = build_parser()
    for argv in (["full,no-dars"], ["full", "no_dars"], ["full,no_dars", "no-dars"]):
        a = p.parse_args(["ablate", "scene", "--out", "o", "--steps", "1", "--variants", *argv])
        assert flat_variants(a.variants) == ["full", "no_dars"], argv
    with pytest.raises(SystemExit):
        p.parse_args(["ablate", "scene", "--out", "o", "--steps", "1", "--variants", "full,no-light"])


def test_field_steps_note_names_the_steps_the_lighting_stage_takes():
    from toolkit.report import _field_steps_note

    def variant(label, field):
        return {"label": label, "runs": [{"training": {"steps": 600, "field_steps": f}} for f in field]}

    doc = {"variants": [variant("Full DARS-NeRF", [560, 560]), variant("fixed lighting", [600, 600])]}
    note = " ".join(_field_steps_note(doc))
    assert "Full DARS-NeRF 560 of 600" in note and "fixed lighting 600 of 600" in note
    doc["variants"][0]["runs"][0]["training"]["field_steps"] = 600  # equal everywhere but one seed: still shown
    assert "Full DARS-NeRF 560–600 of 600" in " ".join(_field_steps_note(doc))
    same = {"variants": [variant("fixed lighting", [600]), variant("Standard NeRF", [600])]}
    assert _field_steps_note(same) == []
    old = {"variants": [{"label": "Full DARS-NeRF", "training": {"steps": 600}}]}  # ablation.json before field_steps
    assert _field_steps_note(old) == []


def test_cli_ablate_device_trains_and_evaluates_there(tmp_path, capsys):
    """--device reaches every variant's config (and the evaluation's load); CUDA on a machine without it is refused."""
    import torch

    from toolkit.cli import main

    scene = make_scene(tmp_path / "s", n_train=4, n_test=1)
    out = tmp_path / "o"
    assert main(["ablate", str(scene), "--out", str(out), "--steps", "2", "--variants", "nerf", "--batch-rays", "64",
                 "--threads", "1", "--device", "cpu", "--json", "--quiet"]) == 0
    assert json.loads((out / "nerf" / "config.json").read_text())["config"]["device"] == "cpu"
    capsys.readouterr()
    if not torch.cuda.is_available():
        assert main(["ablate", str(scene), "--out", str(tmp_path / "c"), "--steps", "2", "--variants", "nerf",
                     "--threads", "1", "--device", "cuda", "--quiet"]) == 2
        assert "CUDA is not available" in capsys.readouterr().err
