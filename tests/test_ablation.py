import json
import re

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
        assert v["training"]["variant"] == v["name"]
        assert set(v["metrics"]) == set(METRIC_KEYS)
        assert {k for k, x in v["metrics"].items() if x is None} == set(v["unavailable"])
        assert (out / v["name"] / "eval" / "metrics.json").is_file()
        assert v["view_consistency_curve"]["keys"] == doc["variants"][0]["view_consistency_curve"]["keys"]
    full, nerf = doc["variants"][0], doc["variants"][-1]
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
