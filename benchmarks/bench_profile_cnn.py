"""Speed of the height-profile CNN (ResNet-18-1D, 200-pixel columns) on this machine.

Figures:

* inference columns/s of the full-width network (64–512 channels), 1 and 2 torch
  threads, batches of 512 columns;
* training columns/s of stage 1 (profile MSE) and stage 2 (feature loss,
  including the per-column model reference §9 walk), 1 and 2 threads, batches of 32;
* the implied training time of the default model
  (``ajtwin cnn train --synthetic``: 125 pairs × 100 epochs + 4000 columns × 50
  epochs) — extrapolated from the measured rates, not run here;
* the same for the half-width network (32–256 channels) used in the reported
  10-fold cross-validation.

Random inputs are fine for speed (the cost does not depend on the values).
The machine is shared: figures vary with the load of other processes.
"""

from __future__ import annotations

import numpy as np

PX = 0.75
WIDTHS = {"resnet18": 64, "resnet18_half": 32}


def _columns(n, seed=0):
    from ajtwin.profile_cnn.data import ColumnDataset
    from ajtwin.vision.profile import brightness_from_slope, line_profile

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


class Inference:
    """Columns/s of the full-width network's inference, batches of 512 columns."""

    params = (list(WIDTHS), [1, 2])
    param_names = ["network", "threads"]
    timeout = 600
    COLUMNS = 2048

    def setup(self, network, threads):
        import torch

        from ajtwin.profile_cnn.model import ProfileModel
        from ajtwin.profile_cnn.network import NetworkConfig, ResNet18Profile

        torch.set_num_threads(threads)
        config = NetworkConfig(base_channels=WIDTHS[network])
        self.model = ProfileModel(ResNet18Profile(config), PX, 0.5)
        self.columns = np.random.default_rng(1).uniform(50, 200, (self.COLUMNS, 200))
        self.model.predict_um(self.columns[:512])

    def teardown(self, network, threads):
        import torch

        torch.set_num_threads(1)

    def track_columns_per_s(self, network, threads):
        import time

        t0 = time.perf_counter()
        self.model.predict_um(self.columns)
        return self.COLUMNS / (time.perf_counter() - t0)

    track_columns_per_s.unit = "columns/s"


class Training:
    """Training columns/s of stage 1 (profile MSE) and stage 2 (feature loss, with the
    per-column model reference §9 walk), 2 epochs of 128 columns, batches of 32; and the
    default model's training time implied by them (``ajtwin cnn train --synthetic``: 125
    pairs × 100 epochs + 4000 columns × 50 epochs), extrapolated, not run."""

    params = (list(WIDTHS), [1, 2])
    param_names = ["network", "threads"]
    timeout = 900
    EPOCHS = 2

    def setup(self, network, threads):
        from ajtwin.profile_cnn.train import TrainConfig, Trainer

        data = _columns(128)
        config = TrainConfig(
            stage1_epochs=self.EPOCHS,
            stage2_epochs=self.EPOCHS,
            base_channels=WIDTHS[network],
            n_threads=threads,
        )
        trainer = Trainer(config, data, data, progress=False)
        trainer.run()
        n = len(data) * self.EPOCHS
        self.rates = n / trainer.stage_seconds["1"], n / trainer.stage_seconds["2"]

    def track_stage1_columns_per_s(self, network, threads):
        return self.rates[0]

    def track_stage2_columns_per_s(self, network, threads):
        return self.rates[1]

    def track_default_model_training_min(self, network, threads):
        return (125 * 100 / self.rates[0] + 4000 * 50 / self.rates[1]) / 60

    track_stage1_columns_per_s.unit = track_stage2_columns_per_s.unit = "columns/s"
    track_default_model_training_min.unit = "min"
