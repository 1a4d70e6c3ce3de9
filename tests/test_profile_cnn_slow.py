"""Slow: 10-fold cross-validation of the two-stage CNN on rendered synthetic data.

A reduced instance of the reported runs (docs/explanation/profile-cnn.md): 125 pairs, 600
CV-labelled columns, for the half-width ResNet-18 (40 + 10 epochs, 3 min) and
the 1-D U-Net (100 + 50 epochs, 5.5 min). The limits are what these runs
reached (with the scan smoothing), with a margin:

* ResNet-18: fine-tuning lowers the overspray error (18.0 → 3.9 µm vs CV
  labels) but not the linewidth error (17.0 → 18.7 µm): its dense head does not
  place edges (docs/explanation/profile-cnn.md, *Edges*); Q_m stays within ~5 %.
* U-Net (its default 100 + 50 epochs): fine-tuning lowers both errors
  (linewidth 22.3 → 7.8 µm, overspray 8.6 → 2.0 µm); Q_m within ~6 %.
"""

from __future__ import annotations

import pytest

from ajtwin.profile_cnn.evaluate import cross_validate
from ajtwin.profile_cnn.synth import synthetic_labelled, synthetic_pairs
from ajtwin.profile_cnn.train import TrainConfig


@pytest.fixture(scope="module")
def cv_data():
    pairs = synthetic_pairs(125, seed=11, progress=False)
    return pairs, synthetic_labelled(600, seed=11, progress=False)


def _summary(cv_data, tmp_path, **config):
    pairs, labelled = cv_data
    config = {"stage1_epochs": 40, "stage2_epochs": 10, **config}
    cfg = TrainConfig(seed=11, n_threads=1, **config)
    result = cross_validate(
        pairs, labelled, cfg, k=10, out_json=tmp_path / "cv.json", progress=False
    )
    s = result["summary"]
    assert s["n_folds"] == 10
    assert s["after_columns.feature_nan_fraction.mean"] == 0.0
    return s


def _mae(s, tag, feature):
    return s[f"{tag}_columns.mae_{feature}_vs_cv_um.mean"]


@pytest.mark.slow
def test_ten_fold_cross_validation(cv_data, tmp_path):
    s = _summary(cv_data, tmp_path, base_channels=32)
    assert _mae(s, "after", "overspray") < 0.5 * _mae(s, "before", "overspray")
    # the linewidth is not improved by this network (measured 18.7 µm): only bounded
    assert _mae(s, "after", "linewidth") < 25.0
    assert s["before_pairs.qm_rel_error.mean"] < 0.10
    assert s["after_pairs.qm_rel_error.mean"] < 0.10


@pytest.mark.slow
def test_ten_fold_cross_validation_unet(cv_data, tmp_path):
    # the U-Net's default epochs (100 + 50): with 10 stage-2 epochs its linewidth
    # error did not move yet (23.3 → 22.8 µm), the overspray did (8.0 → 1.7 µm)
    s = _summary(cv_data, tmp_path, arch="unet1d", stage1_epochs=100, stage2_epochs=50)
    # measured: linewidth 22.3 → 7.8 µm, overspray 8.6 → 2.0 µm, Q_m (pairs) 6.2 %
    assert _mae(s, "after", "linewidth") < 0.5 * _mae(s, "before", "linewidth")
    assert _mae(s, "after", "overspray") < 0.4 * _mae(s, "before", "overspray")
    assert s["after_columns.mae_overspray_vs_true_um.mean"] < 3.0
    assert s["after_pairs.qm_rel_error.mean"] < 0.08
