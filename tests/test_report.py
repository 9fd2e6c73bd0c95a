import json
import re

import numpy as np
import pytest

from _eval_scene import add_ground_truth, small_config
from synthetic import make_scene
from toolkit.evaluate import EvalConfig, evaluate_run
from toolkit.report import (HEADLINE, format_metric, headline_markdown, headline_text, plot_training_curves,
                            write_eval_report)
from toolkit.train import load_run, train


def local_links(md: str) -> list[str]:
    """Targets of Markdown links/images that are not URLs."""
    return [t for t in re.findall(r"\]\(([^)\s]+)\)", md) if not re.match(r"[a-z]+://", t)]


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    scene = add_ground_truth(make_scene(tmp_path_factory.mktemp("repscene")), patch=True)
    run_dir = tmp_path_factory.mktemp("reprun") / "run"
    train(scene, run_dir, small_config(steps=8), progress_bar=False, log=lambda m: None)
    res = evaluate_run(load_run(run_dir), "test", EvalConfig(limit=4, figure_views=2, weight_views=2),
                       log=lambda m: None)
    return run_dir, res


def test_report_files_written_and_links_resolve(evaluated, tmp_path):
    _, res = evaluated
    written = write_eval_report(res, tmp_path / "eval")
    assert {"metrics", "report", "curves", "weights", "brightness", "test_grid"} <= set(written)
    for p in written.values():
        assert p.is_file() and p.stat().st_size > 0, p
    md = written["report"].read_text()
    links = local_links(md)
    for name in ("metrics.json", "curves.png", "weights.png", "brightness.png", "test_grid.png"):
        assert name in links, f"{name} not linked from report.md"
    for target in links:
        assert (written["report"].parent / target).is_file(), f"broken link {target}"
    assert not list((tmp_path / "eval").glob("*.tmp*")), "temporary files left behind"


def test_report_numbers_are_in_the_json(evaluated, tmp_path):
    _, res = evaluated
    written = write_eval_report(res, tmp_path / "eval")
    doc = json.loads(written["metrics"].read_text())
    md = written["report"].read_text()
    assert headline_markdown(doc) in md
    for key, _, _, _ in HEADLINE:
        assert format_metric(key, doc[key]) in md
    vc = doc["details"]["view_consistency"]  # the scene block's patch (top of the sphere) is used and reported
    assert vc is not None and vc["patch"]["source"].startswith("scene JSON") and vc["patch"]["size"] == 0.5
    for key, r_mean in zip(vc["keys"], vc["render_means"]):
        assert key in md and f"{r_mean:.4g}" in md
    for row in doc["per_view"]:
        assert row["key"] in md and f"{row['psnr']:.4g}" in md
    s = doc["details"]["sampling"]
    assert len(s["train_views"]) == 2 and all(f"{m:.2f}" in md for m in s["train_mean_samples_per_ray"])
    assert f"{doc['training']['minutes']:.2f}" in md and str(doc["training"]["steps"]) in md


def test_headline_text_lists_unavailable():
    txt = headline_text({"psnr": 25.123, "ssim": None}, {"ssim": "images too small"})
    assert "25.12" in txt and "n/a" in txt and "ssim: images too small" in txt
    assert format_metric("psnr", float("nan")) == "n/a"


def test_training_curves_plot_every_loss_term(tmp_path):
    log = tmp_path / "log.jsonl"
    rows = [{"kind": "train", "step": s, "loss": 1.0 / s, "rgb": 0.5 / s, "ssim": 0.2, "mat": 0.1, "psnr": 10 + s,
             "distortion": 0.001, "new_term": 0.3, "lr": 1e-3, "stage": "a"} for s in range(1, 6)]
    log.write_text("\n".join(json.dumps(r) for r in rows) + "\n{not json}\n")
    out = plot_training_curves(log, tmp_path / "curves.png")
    assert out is not None and out.is_file()
    from PIL import Image

    assert np.asarray(Image.open(out)).std() > 0
    assert plot_training_curves(tmp_path / "missing.jsonl", tmp_path / "x.png") is None
    (tmp_path / "empty.jsonl").write_text("")
    assert plot_training_curves(tmp_path / "empty.jsonl", tmp_path / "y.png") is None
