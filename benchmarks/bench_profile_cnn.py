"""Speed of the height-profile CNN (ResNet-18-1D, 200-pixel columns) on this machine.

Figures:

* inference columns/s of the full-width network (64–512 channels), 1 and 2 torch
  threads, batches of 512 columns;
* training columns/s of stage 1 (profile MSE) and stage 2 (feature loss,
  including the per-column model reference §9 walk), 1 thread, batches of 32;
* the implied training time of the default model
  (``ajtwin cnn train --synthetic``: 125 pairs × 100 epochs + 4000 columns × 50
  epochs) — extrapolated from the measured rates, not run here;
* the same for the half-width network (32–256 channels) used in the reported
  10-fold cross-validation.

Random inputs are fine for speed (the cost does not depend on the values).
The machine is shared: figures vary with the load of other processes.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from ajtwin.profile_cnn.data import ColumnDataset
from ajtwin.profile_cnn.model import ProfileModel
from ajtwin.profile_cnn.network import NetworkConfig, ResNet18Profile
from ajtwin.profile_cnn.train import TrainConfig, Trainer
from ajtwin.vision.profile import brightness_from_slope, line_profile

PX = 0.75


def _columns(n, seed=0):
    rng = np.random.default_rng(seed)
    r = (np.arange(200) - 99.5) * PX
    cols, profs, lws, ovs = [], [], [], []
    for _ in range(n):
        lw, ov = rng.uniform(35, 50), rng.uniform(18, 30)
        h = line_profile(r, lw, ov, rng.uniform(12, 20))
        cols.append(170 * np.r_[1.0, brightness_from_slope(np.diff(h) / PX)])
        profs.append(h)
        lws.append(lw)
        ovs.append(ov)
    return ColumnDataset(
        np.array(cols),
        PX,
        profiles_um=np.array(profs),
        linewidth_um=np.array(lws),
        overspray_um=np.array(ovs),
    )


def _inference_rate(width, threads, n=2048):
    torch.set_num_threads(threads)
    model = ProfileModel(ResNet18Profile(NetworkConfig(base_channels=width)), PX, 0.5)
    cols = np.random.default_rng(1).uniform(50, 200, (n, 200))
    model.predict_um(cols[:512])  # warm-up
    t0 = time.perf_counter()
    model.predict_um(cols)
    return n / (time.perf_counter() - t0)


def _training_rates(width, data, epochs=2, threads=1):
    cfg = TrainConfig(
        stage1_epochs=epochs, stage2_epochs=epochs, base_channels=width, n_threads=threads
    )
    trainer = Trainer(cfg, data, data, progress=False)
    trainer.run()
    n = len(data) * epochs
    return n / trainer.stage_seconds["1"], n / trainer.stage_seconds["2"]


def main() -> dict:
    data = _columns(128)
    figures = {}
    for width, tag in ((64, "resnet18"), (32, "resnet18_half")):
        figures[f"{tag}_parameters"] = sum(
            p.numel() for p in ResNet18Profile(NetworkConfig(base_channels=width)).parameters()
        )
        figures[f"{tag}_infer_columns_per_s_1thread"] = round(_inference_rate(width, 1), 1)
        figures[f"{tag}_infer_columns_per_s_2threads"] = round(_inference_rate(width, 2), 1)
        s1, s2 = _training_rates(width, data)
        figures[f"{tag}_train_stage1_columns_per_s_1thread"] = round(s1, 1)
        figures[f"{tag}_train_stage2_columns_per_s_1thread"] = round(s2, 1)
        figures[f"{tag}_default_model_train_time_estimate_min"] = round(
            (125 * 100 / s1 + 4000 * 50 / s2) / 60, 1
        )
        s1_2, s2_2 = _training_rates(width, data, threads=2)
        figures[f"{tag}_train_stage1_columns_per_s_2threads"] = round(s1_2, 1)
        figures[f"{tag}_train_stage2_columns_per_s_2threads"] = round(s2_2, 1)
    torch.set_num_threads(1)
    return figures


if __name__ == "__main__":
    for key, value in main().items():
        print(f"{key}: {value}")
