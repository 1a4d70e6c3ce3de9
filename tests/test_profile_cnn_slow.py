"""Slow: 10-fold cross-validation of the two-stage CNN on rendered synthetic data.

A reduced instance of the reported run (docs/profile_cnn.md): 125 pairs, 600
CV-labelled columns, half-width ResNet-18, 40 + 10 epochs. It checks the paper's
two claims qualitatively: fine-tuning on CV labels lowers the linewidth and
overspray errors, and Q_m (an integral) stays accurate.
"""

from __future__ import annotations

import pytest

from ajtwin.profile_cnn.evaluate import cross_validate
from ajtwin.profile_cnn.synth import synthetic_labelled, synthetic_pairs
from ajtwin.profile_cnn.train import TrainConfig


@pytest.mark.slow
def test_ten_fold_cross_validation(tmp_path):
    pairs = synthetic_pairs(125, seed=11, progress=False)
    labelled = synthetic_labelled(600, seed=11, progress=False)
    cfg = TrainConfig(seed=11, stage1_epochs=40, stage2_epochs=10, base_channels=32, n_threads=1)
    result = cross_validate(
        pairs, labelled, cfg, k=10, out_json=tmp_path / "cv.json", progress=False
    )
    s = result["summary"]
    assert s["n_folds"] == 10
    for feature in ("linewidth", "overspray"):
        before = s[f"before_columns.mae_{feature}_vs_cv_um.mean"]
        after = s[f"after_columns.mae_{feature}_vs_cv_um.mean"]
        assert after < 0.7 * before, (feature, before, after)
    assert s["before_pairs.qm_rel_error.mean"] < 0.10
    assert s["after_pairs.qm_rel_error.mean"] < 0.20
