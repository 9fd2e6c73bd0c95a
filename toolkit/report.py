"""Evaluation and ablation reports: ``metrics.json`` / ``ablation.json``, Markdown and PNG figures.

Everything is written atomically (:func:`toolkit.io.atomic_write`; figures to a temporary file, then renamed), the
figures first and the Markdown last, so a ``report.md`` that exists has every link resolving. Images are linked with
paths relative to the Markdown file. Every number printed in a report is also in its JSON.

Figures (names under the output directory):

* ``curves.png`` — Fig. 6: every loss term logged in ``RUN/log.jsonl`` (one panel each, symlog scale) and the batch
  PSNR, against the step.
* ``weights.png`` — Fig. 7: per training view, the photo, the distortion weight map W over it
  (:func:`toolkit.edges.weight_overlay`) and the samples per ray the training sampler gives each pixel (DARS budgets
  ∝ W; uniform without DARS). ``ablation_weights.png`` puts the full model beside the uniform-sampling variants on
  one colour scale.
* ``brightness.png`` — Fig. 8: mean luminance of the view-consistency patch over the K views, render vs ground truth
  (``ablation_brightness.png``: every variant), above a strip of the K renders with the patch outlined.
* ``test_grid.png`` — per test view: ground truth | render | albedo | roughness | metallic | normals | semantics |
  absolute-error heat map.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Iterable

import numpy as np

from .io import atomic_write, write_json

STAT_KEYS = ("psnr", "ssim", "albedo_mae", "roughness_rmse", "normal_mae", "miou")
"""Metrics that ablations give per-seed statistics and paired differences for (:mod:`toolkit.ablation`)."""

__all__ = ["HEADLINE", "EXTRA_COLUMNS", "ABLATION_COLUMNS", "format_metric", "headline_markdown", "headline_text",
           "ablation_text", "text_table", "plot_training_curves",
           "write_eval_report", "write_ablation_report"]

HEADLINE: tuple[tuple[str, str, str, bool], ...] = (
    ("psnr", "PSNR (dB)", "{:.2f}", True),
    ("ssim", "SSIM", "{:.4f}", True),
    ("flip", "FLIP", "{:.4f}", False),
    ("lpips", "LPIPS", "{:.4f}", False),
    ("albedo_mae", "Albedo MAE", "{:.4f}", False),
    ("roughness_rmse", "Roughness RMSE", "{:.4f}", False),
    ("env_light_l2", "Env-light L2", "{:.4f}", False),
    ("view_consistency", "View consistency", "{:.4f}", False),
)
"""(key, column title, format, higher is better) of the Table 5-style headline."""

EXTRA_COLUMNS: tuple[tuple[str, str, str, bool], ...] = (
    ("normal_mae", "Normal MAE (deg)", "{:.2f}", False),
    ("miou", "mIoU", "{:.4f}", True),
)

_COLUMNS = {c[0]: c for c in HEADLINE + EXTRA_COLUMNS}
_FORMATS = {k: f for k, _, f, _ in HEADLINE + EXTRA_COLUMNS}

ABLATION_COLUMNS: tuple[tuple[str, str, str, bool], ...] = tuple(
    _COLUMNS[k] for k in ("psnr", "ssim", "lpips", "flip", "albedo_mae", "roughness_rmse", "env_light_l2",
                          "view_consistency"))
"""Columns of the Table 6-style ablation table (the headline's columns, in the paper's Table 6 order)."""
_LOSS_TERMS = (("loss", "L_total"), ("rgb", "L_rgb"), ("ssim", "L_ssim"), ("mat", "L_mat"),
               ("psnr_loss", "L_psnr"), ("eikonal", "L_eikonal"), ("orientation", "L_orientation"),
               ("distortion", "L_distortion"), ("semantic", "L_semantic"), ("light_reg", "L_light_reg"),
               ("colour_reg", "L_colour_reg"), ("reproj", "L_reproj (light steps, eq. 22)"))
_NOT_LOSSES = {"kind", "step", "elapsed", "lr", "occupancy", "psnr", "samples_per_ray", "fine_per_ray", "stage"}


def format_metric(key: str, value) -> str:
    """A metric value as printed in the tables (``n/a`` for None)."""
    return _fmt(value, _FORMATS.get(key, "{:.4g}"))


def _fmt(x, f="{:.4g}") -> str:
    return "n/a" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f.format(x)


def _arrow(better_high: bool) -> str:
    return "↑" if better_high else "↓"


def _metric_cells(metrics: dict, columns) -> list[str]:
    return [format_metric(k, metrics.get(k)) for k, _, _, _ in columns]


def headline_markdown(metrics: dict, columns=HEADLINE) -> str:
    """One-row Markdown table of ``metrics`` (Table 5 layout)."""
    return _md_table([f"{t} {_arrow(h)}" for _, t, _, h in columns], [_metric_cells(metrics, columns)],
                     first_left=False)


def text_table(header: list[str], rows: list[list[str]], first_left: bool = False) -> str:
    """A plain-text table for the terminal: columns as wide as their widest cell, two spaces apart, right-aligned
    (the first column left-aligned with ``first_left``)."""
    widths = [max(len(r[j]) for r in [header] + rows) for j in range(len(header))]
    return "\n".join("  ".join(c.ljust(w) if j == 0 and first_left else c.rjust(w)
                               for j, (c, w) in enumerate(zip(r, widths))) for r in [header] + rows)


def headline_text(metrics: dict, unavailable: dict | None = None) -> str:
    """Plain-text headline table for the terminal, then the unavailable metrics with their reasons."""
    cols = HEADLINE + EXTRA_COLUMNS
    lines = [text_table([t for _, t, _, _ in cols], [_metric_cells(metrics, cols)])]
    if unavailable:
        lines.append("unavailable:")
        lines += [f"  {k}: {r}" for k, r in unavailable.items()]
    return "\n".join(lines)


# ============================================================================ figures
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    plt = _plt()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.png")
    try:
        fig.savefig(tmp, dpi=110)
        os.replace(tmp, path)
    finally:
        plt.close(fig)
        if tmp.exists():
            tmp.unlink()
    return path


def _read_log(log_path: Path) -> list[dict]:
    rows = []
    for line in Path(log_path).read_text().splitlines():
        if line.strip():
            try:
                r = json.loads(line)
            except json.JSONDecodeError:
                continue
            if r.get("kind") == "train":
                rows.append(r)
    return rows


def plot_training_curves(log_path: str | Path, out: str | Path) -> Path | None:
    """Fig. 6: one panel per loss term logged in ``log.jsonl`` plus the batch PSNR; None when the log is absent/empty.

    Terms: every numeric key of the ``train`` rows that is not bookkeeping (step, time, lr, occupancy, sample
    counts), i.e. L_total, L_rgb, L_ssim, L_mat, L_eikonal (after its start step), L_distortion (the W-map
    regulariser of eq. 8, constant during training), L_semantic, L_light_reg, L_reproj (eq. 22) and any new term.
    train.py logs L_psnr (eq. 27, −PSNR of the importance-weighted batch) as ``psnr_loss`` and the plain batch PSNR
    as ``psnr``; the last panel shows the latter.
    """
    log_path, out = Path(log_path), Path(out)
    if not log_path.is_file():
        return None
    rows = _read_log(log_path)
    if not rows:
        return None
    known = [k for k, _ in _LOSS_TERMS]
    extra = sorted({k for r in rows for k, v in r.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
                   - _NOT_LOSSES - set(known))
    names = dict(_LOSS_TERMS)
    terms = [k for k in known + extra if any(k in r for r in rows)]
    panels = terms + (["psnr"] if any("psnr" in r for r in rows) else [])
    plt = _plt()
    ncol = min(4, len(panels))
    nrow = math.ceil(len(panels) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.2 * ncol, 2.5 * nrow), squeeze=False)
    for ax in axes.flat[len(panels):]:
        ax.axis("off")
    for ax, k in zip(axes.flat, panels):
        xs = [r["step"] for r in rows if isinstance(r.get(k), (int, float))]
        ys = [r[k] for r in rows if isinstance(r.get(k), (int, float))]
        ax.plot(xs, ys, color="tab:green" if k == "psnr" else "tab:blue", lw=1.2)
        ax.set_title("batch PSNR (dB) = −L_psnr" if k == "psnr" else names.get(k, f"L_{k}"), fontsize=9)
        if k != "psnr" and ys and min(ys) > 0 and max(ys) / max(min(ys), 1e-12) > 20:
            ax.set_yscale("log")
        ax.tick_params(labelsize=7)
        ax.set_xlabel("step", fontsize=8)
        ax.grid(alpha=0.3)
    fig.suptitle("Training losses (Fig. 6)", fontsize=10)
    fig.tight_layout()
    return _save(fig, out)


def _imshow(ax, img, title: str | None = None, **kw):
    ax.imshow(np.clip(img, 0, 1) if np.ndim(img) == 3 else img, interpolation="nearest", **kw)
    ax.set_xticks([])
    ax.set_yticks([])
    if title:
        ax.set_title(title, fontsize=8)


def plot_test_grid(grid: list[dict], out: Path, error_max: float = 0.25) -> Path | None:
    """Rows = test views; columns GT | render | albedo | roughness | metallic | normals | semantics | |error|."""
    if not grid:
        return None
    plt = _plt()
    cols = [("gt", "ground truth"), ("render", "render"), ("albedo", "albedo"), ("roughness", "roughness"),
            ("metallic", "metallic"), ("normal", "normals"), ("semantic", "semantics"), ("error", "|error|")]
    fig, axes = plt.subplots(len(grid), len(cols), figsize=(1.45 * len(cols) + 0.6, 1.5 * len(grid) + 0.35),
                             squeeze=False, layout="constrained")
    im = None
    for r, entry in enumerate(grid):
        for c, (k, title) in enumerate(cols):
            ax = axes[r, c]
            t = title if r == 0 else None
            if k not in entry:
                ax.set_facecolor("0.85")
                ax.text(0.5, 0.5, "n/a", ha="center", va="center", fontsize=8, transform=ax.transAxes)
                ax.set_xticks([])
                ax.set_yticks([])
                if t:
                    ax.set_title(t, fontsize=8)
            elif k == "error":
                im = ax.imshow(entry[k], cmap="magma", vmin=0.0, vmax=error_max, interpolation="nearest")
                ax.set_xticks([])
                ax.set_yticks([])
                if t:
                    ax.set_title(t, fontsize=8)
            else:
                _imshow(ax, entry[k], t)
        axes[r, 0].set_ylabel(entry["key"], fontsize=7)
    if im is not None:
        fig.colorbar(im, ax=axes[:, -1].tolist(), fraction=0.05, pad=0.02, label="|error|").ax.tick_params(labelsize=6)
    return _save(fig, out)


def plot_weights(rows: list[dict], out: Path, comparisons: dict[str, list[dict]] | None = None) -> Path | None:
    """Fig. 7: per training view the photo, W over it, all samples per ray and the fine-sample budget per ray.

    ``comparisons``: {variant label: its ``figures.weights`` list} adds one fine-budget column per variant (same
    views, same colour scale), e.g. the uniform-sampling runs beside the DARS run.
    """
    from .edges import weight_overlay

    if not rows:
        return None
    plt = _plt()
    comparisons = comparisons or {}
    vmax = max([float(np.max(r["samples"])) for r in rows] + [1.0])
    fmax = max([float(np.max(r["fine"])) for r in rows]
               + [float(np.max(r["fine"])) for rs in comparisons.values() for r in rs] + [1.0])
    ncol = 4 + len(comparisons)
    fig, axes = plt.subplots(len(rows), ncol, figsize=(1.9 * ncol + 1.2, 1.9 * len(rows) + 0.5), squeeze=False,
                             layout="constrained")
    im_all = im_fine = None
    for r, row in enumerate(rows):
        first = r == 0
        _imshow(axes[r, 0], row["image"], "photo" if first else None)
        _imshow(axes[r, 1], weight_overlay(row["image"], row["W"]), "W (turbo)" if first else None)
        im_all = axes[r, 2].imshow(row["samples"], cmap="magma", vmin=0, vmax=vmax, interpolation="nearest")
        im_fine = axes[r, 3].imshow(row["fine"], cmap="viridis", vmin=0, vmax=fmax, interpolation="nearest")
        for c, (label, other) in enumerate(comparisons.items()):
            if r < len(other):
                axes[r, 4 + c].imshow(other[r]["fine"], cmap="viridis", vmin=0, vmax=fmax, interpolation="nearest")
            if first:
                axes[r, 4 + c].set_title(f"fine/ray: {label}", fontsize=8)
        for c in range(2, ncol):
            axes[r, c].set_xticks([])
            axes[r, c].set_yticks([])
        if first:
            axes[r, 2].set_title("all samples/ray", fontsize=8)
            axes[r, 3].set_title("fine samples/ray" + (" (this run)" if comparisons else ""), fontsize=8)
        axes[r, 0].set_ylabel(row["key"], fontsize=7)
    fig.colorbar(im_all, ax=axes[:, 2].tolist(), fraction=0.05, pad=0.02, location="bottom",
                 label="all samples per ray").ax.tick_params(labelsize=6)
    fig.colorbar(im_fine, ax=axes[:, 3:].ravel().tolist(), fraction=0.05, pad=0.02, location="bottom",
                 label="fine samples per ray").ax.tick_params(labelsize=6)
    fig.suptitle("Sampling weights (Fig. 7)", fontsize=10)
    return _save(fig, out)


def plot_brightness(curves: dict[str, dict], patch_views: list[dict], out: Path, units: str) -> Path | None:
    """Fig. 8: per-view mean luminance of the patch (one line per curve; ``gt`` dashed black) over the K views, and
    a strip of the K renders with the patch outlined.

    ``curves``: {label: {"keys": [...], "means": [...]}}; the ground truth under the label ``ground truth``.
    """
    if not curves:
        return None
    plt = _plt()
    k = len(patch_views)
    fig = plt.figure(figsize=(max(9.5, 1.1 * k + 2.5), 4.6 if k else 3.4))
    gs = fig.add_gridspec(2 if k else 1, max(k, 1), height_ratios=[3, 1] if k else [1])
    ax = fig.add_subplot(gs[0, :])
    for label, c in curves.items():
        xs = np.arange(len(c["means"]))
        if label == "ground truth":
            ax.plot(xs, c["means"], "k--", marker="o", ms=3, lw=1.5, label=label)
        else:
            ax.plot(xs, c["means"], marker="o", ms=3, lw=1.2, label=f"{label} (std {np.std(c['means'], ddof=1):.4g})"
                    if len(c["means"]) > 1 else label)
    first = next(iter(curves.values()))
    ax.set_xticks(np.arange(len(first["keys"])))
    ax.set_xticklabels(first["keys"], rotation=30, fontsize=6, ha="right")
    ax.set_ylabel(f"mean luminance\n({units.split(';')[0]})", fontsize=8)
    ax.set_title("Cross-view brightness of one surface patch (Fig. 8)", fontsize=10)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    ax.grid(alpha=0.3)
    for j, pv in enumerate(patch_views):
        a = fig.add_subplot(gs[1, j])
        img = np.clip(np.asarray(pv["render"], np.float32), 0, 1).copy()
        m = np.asarray(pv["mask"], bool)
        edge = m & ~(np.roll(m, 1, 0) & np.roll(m, -1, 0) & np.roll(m, 1, 1) & np.roll(m, -1, 1))
        img[edge] = (1.0, 0.1, 0.1)
        _imshow(a, img)
    fig.tight_layout()
    return _save(fig, out)


# ============================================================================ markdown
def _write_text(path: Path, text: str) -> None:
    with atomic_write(path, "w") as f:
        f.write(text)


def _md_table(header: list[str], rows: Iterable[list[str]], first_left: bool = True) -> str:
    """Markdown table, numbers right-aligned (the first column left-aligned with ``first_left``)."""
    sep = "|" + "|".join(("---" if i == 0 and first_left else "---:") for i in range(len(header))) + "|"
    return "\n".join(["| " + " | ".join(header) + " |", sep] + ["| " + " | ".join(r) + " |" for r in rows])


def _training_md(t: dict) -> str:
    sw = t["switches"]
    yes = lambda b: "on" if b else "off"  # noqa: E731
    rows = [[str(t["steps"]), f"{t['minutes']:.2f}", t["preset"], t["variant"], yes(sw["dars"]), yes(sw["semantics"]),
             "fixed" if sw["fixed_light"] else "optimised",
             yes(sw["mat_loss"]) + (" (no class terms)" if sw["mat_loss"] and not sw.get("mat_labels", True) else ""),
             sw["baseline"] or "-",
             yes(t["albedo_supervision"]), str(t["seed"])]]
    tab = _md_table(["steps", "minutes", "preset", "variant", "DARS", "semantics", "light", "L_mat", "baseline",
                     "albedo supervision", "seed"], rows)
    pri = ", ".join(f"{k} = {v}" for k, v in t.get("priors", {}).items()) or "none"
    lines = [tab, "", f"Priors used: {pri}. Initial light: {t.get('l_env_source') or 'n/a'}."]
    if t["albedo_supervision"]:
        lines.append("\n**Albedo supervision was on**: L_mat saw the ground-truth albedo maps of the training views, so "
                     "Albedo MAE is not an independent measurement for this run.")
    return "\n".join(lines)


def write_eval_report(result, out_dir: str | Path) -> dict[str, Path]:
    """Write ``metrics.json``, the figures and ``report.md`` for an :class:`~toolkit.evaluate.EvalResult`.

    Returns:
        {name: path} of everything written (``metrics``, ``report``, and the figures that had data).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    doc = result.to_json()
    fig = result.figures
    written: dict[str, Path] = {}
    for name, fn in (("curves", lambda p: plot_training_curves(fig.log_path, p) if fig.log_path else None),
                     ("weights", lambda p: plot_weights(fig.weights, p)),
                     ("brightness", lambda p: _eval_brightness(doc, fig, p)),
                     ("test_grid", lambda p: plot_test_grid(fig.grid, p))):
        path = fn(out / f"{name}.png")
        if path is not None:
            written[name] = path
    write_json(out / "metrics.json", doc)
    written["metrics"] = out / "metrics.json"
    _write_text(out / "report.md", _eval_markdown(doc, written))
    written["report"] = out / "report.md"
    return written


def _eval_brightness(doc: dict, fig, path: Path) -> Path | None:
    vc = doc["details"].get("view_consistency")
    if not vc:
        return None
    curves = {"render": {"keys": vc["keys"], "means": vc["render_means"]},
              "ground truth": {"keys": vc["keys"], "means": vc["gt_means"]}}
    return plot_brightness(curves, fig.patch_views, path, vc["units"])


def _eval_markdown(doc: dict, written: dict[str, Path]) -> str:
    ev, tr, det = doc["eval"], doc["training"], doc["details"]
    L = [f"# Evaluation of `{ev['run']}`", "",
         f"Split `{ev['split']}`: {ev['views']} of {ev['views_in_split']} views at {ev['image_size'][0]}x"
         f"{ev['image_size'][1]} px, checkpoint step {ev['checkpoint_step']}. Written by `dars eval`; every number "
         "below is also in [metrics.json](metrics.json).", "",
         "## Headline (Table 5 layout)", "", headline_markdown(doc), "", headline_markdown(doc, EXTRA_COLUMNS), ""]
    if det.get("object_psnr") is not None:
        L += [f"The object alone (the pixels whose alpha is at least 0.5; PSNR above also counts the plain "
              f"background): **PSNR {det['object_psnr']:.2f} dB**.", ""]
    nvd = det.get("normal_vs_depth")
    if nvd:
        L += [f"Normals against the rendered depth (no ground truth needed; 0° = the normals follow the surface, "
              f"90° = no relation): **{nvd['angle_mean_deg']:.1f}°** on average over {nvd['pixels']} opaque pixels, "
              f"{100 * nvd['back_facing_share']:.1f} % of them facing away from the camera.", ""]
    if doc["unavailable"]:
        L += ["Unavailable metrics (null in the JSON):", ""]
        L += [f"- **{k}**: {r}" for k, r in doc["unavailable"].items()]
        L.append("")
    L += ["## Training", "", _training_md(tr), ""]
    vc = det.get("view_consistency")
    L += ["## Cross-view brightness (Fig. 8)", ""]
    if vc:
        p = vc["patch"]
        L += [f"View consistency = sample std over K = {vc['k']} views of the mean luminance of one surface patch: "
              f"**render {_fmt(vc['value'])}**, ground truth {_fmt(vc['gt_value'])} ({vc['units']}). Patch: "
              f"{p['size']:.3f} m square at ({', '.join(f'{c:.3f}' for c in p['centre'])}), normal "
              f"({', '.join(f'{c:.3f}' for c in p['normal'])}); {p['source']}. Occlusion from {vc['occlusion']}.", ""]
        if "brightness" in written:
            L += ["![cross-view brightness](brightness.png)", "",
                  "Top: mean luminance of the patch in each of the K views (render solid, ground truth dashed). "
                  "Bottom: the K renders with the patch outlined in red.", ""]
        L += [_md_table(["view", "render mean", "GT mean", "pixels"],
                        [[k, _fmt(a), _fmt(b), str(n)] for k, a, b, n in
                         zip(vc["keys"], vc["render_means"], vc["gt_means"], vc["pixels"])]), ""]
    else:
        L += [f"Not available: {doc['unavailable'].get('view_consistency', 'n/a')}", ""]
    L += ["## Training curves (Fig. 6)", ""]
    if "curves" in written:
        L += ["![training curves](curves.png)", "",
              "Every loss term of `log.jsonl` against the step (log scale where a term spans > 20x). L_distortion is "
              "the regulariser value of the precomputed W maps (eq. 8), constant during training. L_psnr is the "
              "importance-weighted −PSNR (eq. 27); the last panel is the plain batch PSNR.", ""]
    else:
        L += ["No training log (`log.jsonl`) in the run.", ""]
    s = det.get("sampling", {})
    L += ["## Sampling weights (Fig. 7)", ""]
    if "weights" in written:
        L += ["![W heat maps and samples per ray](weights.png)", "",
              f"Training views: photo | W over the photo ({s.get('w_source')}) | all samples per ray the training "
              "sampler gives each pixel (coarse samples in occupied space + fine samples) | fine samples per ray "
              f"({s.get('train_budget')}).", ""]
        L += [_md_table(["training view", "mean samples/ray", "min", "max", "mean fine/ray", "min fine", "max fine"],
                        [[k, _fmt(m, "{:.2f}"), _fmt(a, "{:.0f}"), _fmt(b, "{:.0f}"), _fmt(fm, "{:.2f}"),
                          _fmt(fa, "{:.0f}"), _fmt(fb, "{:.0f}")] for k, m, a, b, fm, fa, fb in
                         zip(s["train_views"], s["train_mean_samples_per_ray"], s["train_min_samples_per_ray"],
                             s["train_max_samples_per_ray"], s["train_mean_fine_per_ray"], s["train_min_fine_per_ray"],
                             s["train_max_fine_per_ray"])]), ""]
    L += [f"Test renders: {_fmt(s.get('test_mean_samples_per_ray'), '{:.2f}')} samples per ray on average "
          f"({s.get('test_budget')}).", ""]
    if "test_grid" in written:
        L += ["## Test views", "", "![test views](test_grid.png)", "",
              "Columns: ground truth | render | albedo (sRGB-encoded for display) | roughness | metallic | normals "
              "((n+1)/2, opacity ≥ 0.5) | semantics (argmax, opacity ≥ 0.5) | absolute error of the displayed images "
              "(mean over channels, colour scale 0–0.25). n/a: the run has no such output.", ""]
    L += ["## Per-view metrics", ""]
    cols = ["psnr", "ssim", "flip", "lpips", "albedo_mae", "roughness_rmse", "normal_mae", "miou", "samples_per_ray"]
    L += [_md_table(["view"] + cols, [[r["key"]] + [_fmt(r.get(c)) for c in cols] for r in doc["per_view"]]), ""]
    mat = det.get("materials") or {}
    if mat.get("albedo_mae_aligned") is not None or mat.get("metallic_mae") is not None:
        L += [f"Materials beside the table: albedo MAE after a per-channel scale to the ground truth "
              f"{_fmt(mat.get('albedo_mae_aligned'), '{:.4f}')} (scale {mat.get('albedo_scale')}: albedo and light are "
              "known only up to a common scale from photos; above 1 the albedo is too dark), metallic MAE "
              f"{_fmt(mat.get('metallic_mae'), '{:.4f}')}.", ""]
    if mat.get("roughness_rmse_by_class"):
        from .losses import PAINTING_ROUGHNESS  # torch: kept out of the CLI's --help imports

        L += [f"Roughness RMSE per ground-truth class (L_mat pulls painting roughness to {PAINTING_ROUGHNESS:g}; the "
              "painting figure is the one that shows whether the field learned the scene's own): " + ", ".join(
                  f"{k} {_fmt(v, '{:.3f}')}" for k, v in mat["roughness_rmse_by_class"].items()), ""]
    if mat.get("albedo_mae_by_class"):
        n_by, lv = mat.get("albedo_pixels_by_class") or {}, mat.get("albedo_level_by_class") or {}
        total = sum(v * n_by.get(k, 0) for k, v in mat["albedo_mae_by_class"].items() if v is not None) or 1.0
        L += ["Albedo MAE per ground-truth class (its share of the pooled error; predicted / true level, above 1 too "
              "bright): " + ", ".join(f"{k} {_fmt(v, '{:.3f}')} ({100 * (v or 0) * n_by.get(k, 0) / total:.0f} %; "
                                      f"{_fmt(lv.get(k), '{:.2f}')}x)" for k, v in mat["albedo_mae_by_class"].items()), ""]
    if det.get("miou_per_class"):
        L += ["Per-class IoU: " + ", ".join(f"{k} {_fmt(v, '{:.3f}')}" for k, v in det["miou_per_class"].items()), ""]
    geo = det.get("geometry")
    if geo:
        a = geo["all"]
        L += [f"Rendered depth against the ground truth: median error **{a['depth_error_median_m']:.3f} m**, mean "
              f"opacity {a['opacity_mean']:.3f} ({a['pixels']} pixels). Opacity well below 1 on a class means the "
              "learned background shows through it (a wall explained as environment instead of surface).", ""]
        if geo.get("by_class"):
            L += [_md_table(["class", "share of pixels", "median depth error (m)", "mean opacity"],
                            [[k, f"{v['share']:.2f}", f"{v['depth_error_median_m']:.3f}", f"{v['opacity_mean']:.3f}"]
                             for k, v in geo["by_class"].items()]), ""]
    ch = det.get("chamfer")
    if ch:
        L += ["## Geometry", ""]
        if ch.get("value") is not None:
            L += [f"Chamfer distance to `{ch['reference']}`: **{ch['value']:.5f} m** (recon→ref {ch['mean_ab']:.5f}, "
                  f"ref→recon {ch['mean_ba']:.5f}, max {ch['max']:.5f}; {ch['mean_fraction']:.4%} of the reference "
                  f"diagonal), marching cubes at {ch['resolution']} cells, {ch['faces']} faces.", ""]
        else:
            L += [f"Chamfer distance to `{ch.get('reference')}`: n/a — {ch.get('reason')}", ""]
    L += ["## Definitions", ""]
    L += [f"- {k}: {v}" for k, v in det.get("definitions", {}).items() if v]
    if det.get("pixels"):
        L += ["- pooled pixels: " + ", ".join(f"{k} {v}" for k, v in det["pixels"].items())]
    return "\n".join(L) + "\n"


# ============================================================================ ablation
def write_ablation_report(result, out_dir: str | Path) -> dict[str, Path]:
    """Write ``ablation.json``, ``ablation.md`` and the comparison figures for an
    :class:`~toolkit.ablation.AblationResult`."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    doc = result.to_json()
    written: dict[str, Path] = {}
    runs = result.first_seed_runs()  # the figures show the first seed's run of every variant
    by_name = {v.name: v for v in runs}
    # Fig. 8: every variant on the same patch and views
    curves: dict[str, dict] = {}
    gt = None
    units = "relative luminance"
    patch_views: list[dict] = []
    for v in runs:
        vc = v.evaluation.details.get("view_consistency")
        if vc:
            curves[v.label] = {"keys": vc["keys"], "means": vc["render_means"]}
            units = vc["units"]
            if gt is None:
                gt = {"keys": vc["keys"], "means": vc["gt_means"]}
                patch_views = v.evaluation.figures.patch_views
    if curves and gt is not None:
        same = all(c["keys"] == gt["keys"] for c in curves.values())
        if same:
            curves["ground truth"] = gt
            p = plot_brightness(curves, patch_views, out / "ablation_brightness.png", units)
            if p:
                written["brightness"] = p
    # Fig. 7: the full model's W and samples next to the uniform-sampling variants
    base = by_name.get("full") or (runs[0] if runs else None)
    if base is not None and base.evaluation.figures.weights:
        comps = {v.label: v.evaluation.figures.weights for v in runs
                 if v is not base and not v.evaluation.training["switches"]["dars"] and v.evaluation.figures.weights}
        p = plot_weights(base.evaluation.figures.weights, out / "ablation_weights.png", comps)
        if p:
            written["weights"] = p
    write_json(out / "ablation.json", doc)
    written["json"] = out / "ablation.json"
    _write_text(out / "ablation.md", _ablation_markdown(doc, written, out))
    written["report"] = out / "ablation.md"
    return written


def _delta(d, fmt: str) -> str:
    return "" if d is None else f" ({'+' if d >= 0 else '−'}{fmt.format(abs(d))})"


def _pm(st: dict, fmt: str, signed: bool = False) -> str:
    """``mean ± std`` of a :func:`~toolkit.ablation.seed_statistics` entry (``n/a`` without values)."""
    if st is None or st.get("mean") is None:
        return "n/a"
    m = st["mean"]
    txt = (("+" if m >= 0 else "−") + fmt.format(abs(m))) if signed else fmt.format(m)
    return txt + ("" if st.get("std") is None else f" ± {fmt.format(st['std'])}")


def _signed(x, fmt: str) -> str:
    return "n/a" if x is None else ("+" if x >= 0 else "−") + fmt.format(abs(x))


def _field_steps_note(doc: dict) -> list[str]:
    """A paragraph when the variants optimised the field for different numbers of steps at the same step budget: the
    eq. 22 lighting stage takes its l_env steps from the field's, so "fixed lighting" and "standard NeRF" train the
    field longer. Empty when every run's field steps equal its steps' (or the runs predate ``field_steps``)."""
    per = {}
    for v in doc["variants"]:
        runs = v.get("runs") or [v]
        fs = [r["training"].get("field_steps") for r in runs]
        if any(f is None for f in fs):
            return []
        per[v["label"]] = (sorted(set(fs)), sorted({r["training"]["steps"] for r in runs}))
    if all(f == st for f, st in per.values()):
        return []

    def span(x):
        return str(x[0]) if len(x) == 1 else f"{x[0]}–{x[-1]}"

    return ["**Field steps differ.** The lighting stage (eq. 22) spends some of a run's steps on l_env alone, so at "
            "one step budget the variants with it optimise the field fewer times: "
            + ", ".join(f"{lab} {span(f)} of {span(st)}" for lab, (f, st) in per.items())
            + ". A PSNR difference between them includes these steps (`toolkit.train.field_steps`).", ""]


def _ablation_markdown(doc: dict, written: dict, out: Path) -> str:

    b = doc["budget"]
    seeds = doc.get("seeds") or [doc["seed"]]
    multi = len(seeds) > 1
    budget = f"{b['steps']} steps" if b.get("steps") else f"{b['minutes']:g} minutes of training"
    nv = len(doc["variants"])
    seed_txt = (f"seeds {', '.join(map(str, seeds))} (every variant once per seed)" if multi else f"seed {seeds[0]}")
    L = [f"# Ablation (Table 6 layout): `{doc['scene']}`", "",
         f"{nv} variant{'s' if nv != 1 else ''} of one trainer (`toolkit.train.make_config` switches), each trained for "
         f"**{budget}** per run with preset `{doc['preset']}` and {seed_txt}, one after another, then evaluated on the "
         f"`{doc['split']}` split by `toolkit.evaluate.evaluate_run`. Every number is also in "
         "[ablation.json](ablation.json).", ""]
    if b.get("minutes") and not b.get("steps"):
        steps = {f"{v['label']}" + (f" (seed {r['seed']})" if multi else ""): r["training"]["steps"]
                 for v in doc["variants"] for r in v.get("runs", [v])}
        L += ["**Warning — " + b.get("warning", "wall-clock budget: the variants trained different numbers of steps.")
              + "** Steps trained: " + ", ".join(f"{k} {n}" for k, n in steps.items()) + ".", ""]
    head = ["variant", "steps", "min"] + [f"{t} {_arrow(h)}" for _, t, _, h in ABLATION_COLUMNS]
    rows = []
    for v in doc["variants"]:
        m, d = v["metrics"], v["delta_vs_full"]
        runs = v.get("runs") or [v]
        st = sorted({r["training"]["steps"] for r in runs})
        mins = [r["training"]["minutes"] for r in runs]
        cells = [v["label"], str(st[0]) if len(st) == 1 else f"{st[0]}–{st[-1]}", f"{sum(mins) / len(mins):.2f}"]
        for k, _, f, _ in ABLATION_COLUMNS:
            val = m.get(k)
            if val is None:
                cells.append("n/a")
                continue
            sd = (v.get("summary") or {}).get(k, {}).get("std") if multi else None
            cells.append(f.format(val) + ("" if sd is None else f" ± {f.format(sd)}")
                         + (_delta(d.get(k), f) if v["name"] != "full" else ""))
        rows.append(cells)
    L += [_md_table(head, rows), ""]
    if multi:
        L += ["Mean ± sample standard deviation over the seeds (min: mean minutes per run). In parentheses: the mean "
              "paired difference to the full model (variant − full, same seed; its spread is in the tables below). "
              "n/a: the metric is unavailable for that variant (reasons below).", ""]
    else:
        L += ["In parentheses: difference to the full model (variant − full). n/a: the metric is unavailable for that "
              "variant (reasons below).", ""]
    L += _field_steps_note(doc)
    reasons: dict[tuple[str, str], list[str]] = {}
    shown = {c for c, _, _, _ in ABLATION_COLUMNS} | set(STAT_KEYS)
    for v in doc["variants"]:
        for k, r in v["unavailable"].items():
            if k in shown:
                reasons.setdefault((k, r), []).append(v["label"])
    if reasons:
        n = len(doc["variants"])
        L += ["Unavailable:", ""]
        L += [f"- **{k}** ({'all variants' if len(labs) == n and n > 1 else ', '.join(labs)}): {r}"
              for (k, r), labs in reasons.items()]
        L.append("")
    if all("summary" in v for v in doc["variants"]):
        L += _seed_sections(doc, multi)
    L += ["## What each variant removes", ""]
    L += [f"- **{v['label']}** (`{v['name']}`): {v.get('removes') or 'n/a'}" for v in doc["variants"]]
    L.append("")
    L += _inputs_section(doc, multi)
    if "brightness" in written:
        L += ["## Cross-view brightness (Fig. 8)", "", "![cross-view brightness](ablation_brightness.png)", "",
              "Mean luminance of the same surface patch over the same K views for every variant (legend: its sample "
              "std = view consistency) and the ground truth (dashed)" + (f"; seed {seeds[0]}'s runs" if multi else "")
              + ".", ""]
    if "weights" in written:
        L += ["## Sampling (Fig. 7)", "", "![W and samples per ray](ablation_weights.png)", "",
              "Training views of the full model: photo | W | all samples per ray | fine samples per ray under DARS "
              "(budget ∝ W), beside the fine samples per ray of the uniform-sampling variants (same views, same "
              "colour scale" + (f", seed {seeds[0]}'s runs" if multi else "") + "). Per-view means are in each "
              "variant's `sampling` entry of ablation.json.", ""]
    L += ["## Per-variant reports", ""]
    for v in doc["variants"]:
        for r in v.get("runs") or [v]:
            rep = Path(r["run"]) / "eval" / "report.md"
            rel = os.path.relpath(rep, out) if rep.is_file() else None
            L.append(f"- {v['label']}" + (f", seed {r['seed']}" if multi else "") + f": run `{r['run']}`"
                     + (f", [report]({rel})" if rel else "") + (" (reused an existing run)" if r.get("reused") else ""))
    return "\n".join(L) + "\n"


def _seed_sections(doc: dict, multi: bool) -> list[str]:
    """Per-seed figures, paired differences against ``full`` and the seed-noise sentences."""

    cols = [_COLUMNS[k] for k in STAT_KEYS]
    L = ["## Per seed", ""]
    head = ["variant", "seed", "steps"] + [f"{t} {_arrow(h)}" for _, t, _, h in cols]
    rows = []
    for v in doc["variants"]:
        for i, r in enumerate(v["runs"]):
            rows.append([v["label"], str(r["seed"]), str(r["training"]["steps"])]
                        + [_fmt(v["per_seed"][k][i], f) for k, _, f, _ in cols])
        if multi:
            rows.append([f"{v['label']} — mean ± std", f"n = {len(v['runs'])}", ""]
                        + [_pm(v["summary"][k], f) for k, _, f, _ in cols])
    L += [_md_table(head, rows), "", "Standard deviations are sample standard deviations (n − 1) over the seeds.", ""]
    if not any(v.get("paired_vs_full") for v in doc["variants"] if v["name"] != "full"):
        return L
    L += ["## Paired differences against the full model", "",
          "Variant − full, trained with the same seed; per seed, then mean ± std of the difference (n pairs).", ""]
    head = ["variant", "seed"] + [f"Δ {t}" for _, t, _, _ in cols]
    rows = []
    for v in doc["variants"]:
        pv = v.get("paired_vs_full")
        if v["name"] == "full" or not pv:
            continue
        for i, r in enumerate(v["runs"]):
            rows.append([v["label"], str(r["seed"])] + [_signed(pv[k]["values"][i], f) for k, _, f, _ in cols])
        if multi:
            rows.append([f"{v['label']} — mean ± std", f"n = {pv['psnr']['n']}"]
                        + [_pm(pv[k], f, signed=True) for k, _, f, _ in cols])
    L += [_md_table(head, rows), ""]
    notes = [f"- **{v['label']}**: {v['noise_note']}" for v in doc["variants"]
             if v["name"] != "full" and v.get("noise_note")]
    if notes:
        L += ["Seed noise: a paired difference whose mean is smaller than its standard deviation over seeds is "
              "**within seed noise** — the variant is not shown to differ from the full model on that metric.", ""]
        L += notes
        L.append("")
    return L


def _inputs_section(doc: dict, multi: bool) -> list[str]:
    """Which inputs were ground truth: each run's ``labels`` setting (its config.json) and the recorded sources."""
    rows = []
    for v in doc["variants"]:
        for r in v.get("runs") or []:
            i = r.get("inputs") or {}
            rows.append([v["label"]] + ([str(r["seed"])] if multi else [])
                        + [str(i.get("labels")), str(i.get("labels_source")), str(i.get("labels_used_by") or "-"),
                           str(i.get("metal_source")), "on" if i.get("albedo_supervision") else "off",
                           ", ".join(i.get("ground_truth") or []) or "none"])
    if not rows:
        return []
    head = ["variant"] + (["seed"] if multi else []) + ["labels (config.json)", "label source", "labels used by",
                                                        "metal mask", "albedo supervision", "ground-truth inputs"]
    gt = (doc.get("inputs") or {}).get("ground_truth") or []
    L = ["## Inputs", "", _md_table(head, rows), ""]
    unlabelled = sorted({v["label"] for v in doc["variants"] for r in v.get("runs") or []
                         if v["name"] in ("full", "no_semantics", "no_mat_loss")
                         and str((r.get("inputs") or {}).get("labels_source")) in ("none", "off", "None")})
    if unlabelled:
        L += ["**No labels** reached " + ", ".join(unlabelled) + " (label source none: no segmentation prior, or "
              "`--labels none`): the semantic input and L_mat's class terms were inactive there, so those variants do "
              "not measure them. Run `dars priors segment` first, or pass `--labels ground-truth` (then the labels "
              "are ground truth).", ""]
    L.append("Ground truth fed to training: " + (", ".join(gt) + " — scores that compare against the same ground "
                                                 "truth are not independent." if gt else "none.") + "")
    L.append("")
    return L


def ablation_text(doc: dict) -> str:
    """The Table 6 metrics of an ``ablation.json`` document as a plain-text table for the terminal (mean ± std over
    seeds and the seed-noise notes when there are several seeds)."""
    header = ["variant"] + [t for _, t, _, _ in ABLATION_COLUMNS]
    seeds = doc.get("seeds") or [doc.get("seed")]
    if len(seeds) <= 1 or not all("summary" in v for v in doc["variants"]):
        return text_table(header, [[v["label"]] + _metric_cells(v["metrics"], ABLATION_COLUMNS)
                                   for v in doc["variants"]], first_left=True)
    rows = [[v["label"]] + [_pm(v["summary"][k], f) for k, _, f, _ in ABLATION_COLUMNS] for v in doc["variants"]]
    lines = [f"seeds {', '.join(map(str, seeds))}: mean ± sample std", text_table(header, rows, first_left=True)]
    lines += [f"{v['label']} vs full (paired): " + ", ".join(
        f"{k} {_pm(v['paired_vs_full'][k], _FORMATS.get(k, '{:.4g}'), signed=True)}"
        for k in ("psnr", "ssim", "albedo_mae") if v["paired_vs_full"][k]["mean"] is not None)
        + (f" — {v['noise_note']}" if v.get("noise_note") else "")
        for v in doc["variants"] if v["name"] != "full" and v.get("paired_vs_full")]
    if doc["budget"].get("warning"):
        lines.append("warning: " + doc["budget"]["warning"])
    return "\n".join(lines)
