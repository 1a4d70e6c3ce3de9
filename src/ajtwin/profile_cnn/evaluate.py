"""Scores of a height-profile model on held-out data, and K-fold cross-validation.

Scores (all on columns the model never trained on):

* ``mae_linewidth_vs_cv_um`` / ``mae_overspray_vs_cv_um`` — features of the
  predicted profile (:func:`~ajtwin.profile_cnn.features.smooth_features`)
  against the CV labels (what the paper reports: 5.3 → 1.3 µm, 9.4 → 6.1 µm);
* ``mae_linewidth_vs_true_um`` / ``mae_overspray_vs_true_um`` — against the
  true features (synthetic data: ``profile_features`` of the hidden profile;
  real pairs: of the registered profilometer profile);
* ``qm_rel_error`` — mean |A_pred − A_true| / A_true of the cross-section area,
  which is the relative error of Q_m = ν·A at any platen speed;
  ``qm_rel_bias`` the signed mean;
* ``feature_nan_fraction`` — share of predicted profiles on which the model reference §9
  definitions cannot be applied (no shoulder peak, tail leaving the column)
  even after the read-out's smoothing fallback
  (:func:`~ajtwin.profile_cnn.features.read_features`); the MAEs are over the
  others. ``feature_fallback_fraction`` — share that needed the fallback
  (undefined on the raw predicted profile).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from ajtwin.profile_cnn.data import ColumnDataset
from ajtwin.profile_cnn.features import features_numpy, read_features
from ajtwin.profile_cnn.flow import cross_section_area_um2
from ajtwin.profile_cnn.model import ProfileModel
from ajtwin.profile_cnn.train import TrainConfig, train_restarts


def _mae(pred, ref):
    ok = np.isfinite(pred) & np.isfinite(ref)
    return float(np.mean(np.abs(pred[ok] - ref[ok]))) if ok.any() else float("nan")


def score(model: ProfileModel, data: ColumnDataset) -> dict:
    """Scores of ``model`` on ``data`` (see module docstring)."""
    t0 = time.perf_counter()
    pred = model.predict_um(data.columns)
    infer_s = time.perf_counter() - t0
    lw, ov, fallback = read_features(pred, data.um_per_px)
    out: dict = {
        "n_columns": len(data),
        "feature_nan_fraction": float(np.mean(~(np.isfinite(lw) & np.isfinite(ov)))),
        "feature_fallback_fraction": float(np.mean(fallback)),
        "inference_columns_per_s": len(data) / infer_s if infer_s > 0 else float("nan"),
    }
    if data.linewidth_um is not None:
        out["mae_linewidth_vs_cv_um"] = _mae(lw, data.linewidth_um)
        out["mae_overspray_vs_cv_um"] = _mae(ov, data.overspray_um)
    true_lw = data.extra.get("true_linewidth_um")
    true_ov = data.extra.get("true_overspray_um")
    if true_lw is None and data.profiles_um is not None:
        true_lw, true_ov = features_numpy(data.profiles_um, data.um_per_px)
    if true_lw is not None:
        out["mae_linewidth_vs_true_um"] = _mae(lw, np.asarray(true_lw))
        out["mae_overspray_vs_true_um"] = _mae(ov, np.asarray(true_ov))
    if data.profiles_um is not None:
        area_pred = cross_section_area_um2(pred, data.um_per_px)
        area_true = cross_section_area_um2(data.profiles_um, data.um_per_px)
        rel = (area_pred - area_true) / area_true
        out["qm_rel_error"] = float(np.mean(np.abs(rel)))
        out["qm_rel_bias"] = float(np.mean(rel))
        out["profile_rmse_um"] = float(np.sqrt(np.mean((pred - data.profiles_um) ** 2)))
    return out


def fold_indices(groups, k: int, seed: int) -> list[np.ndarray]:
    """Split sample indices into ``k`` folds that never split a group.

    Groups are shuffled with ``seed`` and dealt into ``k`` folds of nearly
    equal group count.
    """
    groups = np.asarray(groups)
    unique = np.unique(groups)
    if unique.size < k:
        raise ValueError(f"{unique.size} groups cannot make {k} folds")
    order = np.random.default_rng(seed).permutation(unique)
    return [np.flatnonzero(np.isin(groups, part)) for part in np.array_split(order, k)]


def cross_validate(
    pairs: ColumnDataset,
    labelled: ColumnDataset,
    config: TrainConfig,
    *,
    k: int = 10,
    folds: list[int] | None = None,
    out_json=None,
    progress: bool = True,
) -> dict:
    """K-fold cross-validation of two-stage training (paper §5: k = 10).

    Fold i holds out the i-th part of the stage-1 pairs *and* of the stage-2
    columns (groups kept together); the model is trained on the rest, scored
    after stage 1 ("before" fine-tuning) and after stage 2 ("after"), on both
    held-out sets. Results are written to ``out_json`` after every fold, so
    an interrupted run keeps the folds it finished (and resumes after them).

    Returns
    -------
    dict
        ``folds``: per-fold scores; ``summary``: mean and variance across
        folds of every score.
    """
    pair_folds = fold_indices(pairs.group, k, config.seed)
    label_folds = fold_indices(labelled.group, k, config.seed + 1)
    result = {"k": k, "config": config.to_dict(), "folds": []}
    if out_json and Path(out_json).exists():
        previous = json.loads(Path(out_json).read_text())
        if previous.get("config") == config.to_dict() and previous.get("k") == k:
            result["folds"] = previous["folds"]
    done = {f["fold"] for f in result["folds"]}
    for i in folds if folds is not None else range(k):
        if i in done:
            continue
        train_p = np.setdiff1d(np.arange(len(pairs)), pair_folds[i])
        train_l = np.setdiff1d(np.arange(len(labelled)), label_folds[i])
        test_p, test_l = pairs.subset(pair_folds[i]), labelled.subset(label_folds[i])
        entry: dict = {"fold": i, "n_train_pairs": len(train_p), "n_train_columns": len(train_l)}

        per_restart: dict = {}

        def on_stage_end(
            restart, stage, model, per_restart=per_restart, test_p=test_p, test_l=test_l
        ):
            tag = "before" if stage == 1 else "after"
            scores = per_restart.setdefault(restart, {})
            scores[f"{tag}_pairs"] = score(model, test_p)
            scores[f"{tag}_columns"] = score(model, test_l)

        t0 = time.perf_counter()
        _, trainers, best = train_restarts(
            config,
            pairs.subset(train_p),
            labelled.subset(train_l),
            progress=progress,
            on_stage_end=on_stage_end,
        )
        entry.update(per_restart[best])  # "before" is the kept restart's stage-1 model
        if len(trainers) > 1:
            entry["restart_kept"] = best
        entry["wall_seconds"] = time.perf_counter() - t0
        entry["train_seconds"] = sum(t.train_seconds for t in trainers)
        entry["train_seconds_stage1"] = sum(t.stage_seconds["1"] for t in trainers)
        entry["train_seconds_stage2"] = sum(t.stage_seconds["2"] for t in trainers)
        result["folds"].append(entry)
        result["summary"] = summarize(result["folds"])
        if out_json:
            Path(out_json).parent.mkdir(parents=True, exist_ok=True)
            Path(out_json).write_text(json.dumps(result, indent=2))
    result["summary"] = summarize(result["folds"])
    if out_json:
        Path(out_json).write_text(json.dumps(result, indent=2))
    return result


def summarize(folds: list[dict]) -> dict:
    """Mean and (population) variance across folds of every numeric score."""
    summary: dict = {"n_folds": len(folds)}
    keys = {}
    for f in folds:
        for part, scores in f.items():
            if isinstance(scores, dict):
                for name, value in scores.items():
                    keys.setdefault((part, name), []).append(value)
    for (part, name), values in sorted(keys.items()):
        v = np.asarray(values, dtype=float)
        summary[f"{part}.{name}.mean"] = float(np.nanmean(v))
        summary[f"{part}.{name}.var"] = float(np.nanvar(v))
    for key in ("train_seconds", "train_seconds_stage1", "train_seconds_stage2"):
        times = [f[key] for f in folds if key in f]
        if times:
            summary[f"{key}_per_fold.mean"] = float(np.mean(times))
    return summary


REPORT_ROWS = (
    ("linewidth MAE vs CV labels (µm)", "columns", "mae_linewidth_vs_cv_um"),
    ("overspray MAE vs CV labels (µm)", "columns", "mae_overspray_vs_cv_um"),
    ("linewidth MAE vs truth (µm)", "columns", "mae_linewidth_vs_true_um"),
    ("overspray MAE vs truth (µm)", "columns", "mae_overspray_vs_true_um"),
    ("Q_m relative error, held-out pairs", "pairs", "qm_rel_error"),
    ("Q_m relative bias, held-out pairs", "pairs", "qm_rel_bias"),
    ("Q_m relative error, held-out columns", "columns", "qm_rel_error"),
    ("features undefined (share of columns)", "columns", "feature_nan_fraction"),
    ("read through the smoothing fallback (share)", "columns", "feature_fallback_fraction"),
)


def report_table(summary: dict) -> str:
    """Markdown table: before/after fine-tuning, mean and variance across folds."""
    lines = [
        "| score | before (mean) | before (fold var) | after (mean) | after (fold var) |",
        "|---|---|---|---|---|",
    ]
    for label, part, name in REPORT_ROWS:
        cells = []
        for tag in ("before", "after"):
            key = f"{tag}_{part}.{name}"
            mean, var = summary.get(f"{key}.mean"), summary.get(f"{key}.var")
            cells += ["–", "–"] if mean is None else [f"{mean:.4g}", f"{var:.3g}"]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
