"""Two-stage training of the height-profile CNN (paper §5, model reference §9).

Stage 1: supervised MSE between predicted and profilometer profiles
(the paper's 125 scans). Stage 2: fine-tuning on many columns labelled only
with computer-vision linewidth and overspray; the loss is the MSE between the
linewidth/overspray computed *differentiably* from the predicted profile
(:mod:`ajtwin.profile_cnn.features`) and the CV labels (paper: 50 epochs).

Reproducibility: every epoch's batch order and augmentation come from a
generator seeded by ``(seed, stage, epoch)``, and kernels are deterministic,
so a run resumed from a checkpoint produces the same weights as one that was
never interrupted.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from ajtwin.profile_cnn import features as feat
from ajtwin.profile_cnn.data import ColumnDataset, normalize_columns
from ajtwin.profile_cnn.model import ProfileModel, set_threads
from ajtwin.profile_cnn.network import DEFAULT_WIDTH, NetworkConfig, build_network


@dataclass
class TrainConfig:
    """Training hyper-parameters (all stored in the checkpoint).

    Parameters
    ----------
    seed : int
        Seeds weights, batch order and augmentation.
    stage1_epochs, stage2_epochs : int
        Epochs of supervised pre-training and of CV-label fine-tuning
        (paper: 50 for stage 2).
    batch_size : int
    stage1_lr, stage2_lr : float
        Adam learning rates (cosine-annealed to 5 % over each stage).
    weight_decay : float
    augment : bool
        Stage 1 and 2: mirror the column across the line centre (with its
        profile) and shift it by up to ``max_shift_px`` pixels — symmetries
        of the physics, which stretch 125 pairs further.
    max_shift_px : int
    stage2_replay_weight : float
        Weight of the stage-1 profile loss (on a quarter batch of pairs, in
        units of ``height_scale_um²``) mixed into each stage-2 step; the
        feature loss is in µm², so useful weights are 1e2–1e4. 0 = the
        paper's pure feature loss.
    stage2_area_weight : float
        Weight of an area anchor in stage 2: ``((A − A₁)/A₁)²`` per column,
        where A is the cross-section area (∝ Q_m) of the predicted profile and
        A₁ that of the stage-1 model on the same column (computed once when
        stage 2 starts; no labels needed). The feature loss alone lets the
        network raise heights to make edges visible, which inflates Q_m; the
        anchor keeps the profilometer-grounded integral. Useful weights
        1e3–1e5 (the feature loss is in µm²); 0 = the paper's pure feature loss,
        which inflated Q_m by +29 % (half width, 10-fold CV) and diverged at
        full width (Q_m +220 %), hence the default 1000.
    base_channels : int, optional
        Channels of the first stage/level; default per ``arch`` (ResNet-18: 64,
        i.e. 64–512 channels; U-Net: 16). Smaller only for tests.
    arch : {"resnet18", "unet1d"}
        The paper's ResNet-18 (default) or the small 1-D U-Net compared in
        docs/explanation/profile-cnn.md.
    n_threads : int, optional
        torch intra-op threads (default 1, see :func:`~ajtwin.profile_cnn.model.set_threads`).
    grad_clip : float
        Gradient-norm clip (feature positions can react strongly to nm-level slopes).
    stage1_area_weight : float
        Weight of a stage-1 area term, ``((A − A_true)/A_true)²`` per pair
        (A = cross-section area ∝ Q_m, of the prediction and of the registered
        scan). Height MSE weighs the area only indirectly; a small network
        that fits the pairs less closely then misses Q_m by 4–5 %, and the
        stage-2 anchor keeps whatever area stage 1 ended with. 0 = off.
    stage2_val_fraction : float
        Share of the stage-2 CV-labelled column groups held back from the
        feature loss as a validation split of the *training* data. When > 0,
        the network is scored on it (linewidth + overspray MAE vs the CV labels,
        plus 100 µm per undefined share) when stage 2 starts and after every
        stage-2 epoch, and the best state is kept — stage 2's loss spikes
        decide which minimum a run ends in, and the last epoch is not always
        the best one. 0 = keep the last epoch (the paper).
    restarts : int
        Independent trainings (seeds ``seed``, ``seed + 1``, …; one validation
        split, drawn from ``seed``) of which the one with the best stage-2
        validation score is kept (:func:`train_restarts`). Stage 2 ends in a
        minimum that depends on the initialisation (docs/explanation/profile-cnn.md, *Edges*);
        the validation score tracks held-out truth, so picking among a few runs by
        it is a selection on training data only. Needs ``stage2_val_fraction`` > 0.
    restart_screen_epochs : int
        With restarts: train every restart only to this stage-2 epoch, then
        finish the ``restart_finalists`` best by validation score so far and keep
        the best of those (0 = finish every restart). A run that reaches a good
        stage-2 minimum shows it early (docs/explanation/profile-cnn.md), so screening lets
        more initialisations be tried in the same time.
    restart_finalists : int
        Restarts finished after the screen.
    split_seed : int, optional
        Seed of the validation split (default ``seed``); the restarts share it so
        that their scores compare.
    stage1_brightness_weight : float
        Weight of a second stage-1 term: MSE between the camera brightness
        (optics model, slope → B/B_bg) of the predicted and the true profile.
        Linewidth and overspray are defined on that brightness, so this teaches
        the slopes they depend on; 0 = plain profile MSE.
    """

    seed: int = 0
    stage1_epochs: int = 100
    stage2_epochs: int = 50
    batch_size: int = 32
    stage1_lr: float = 1e-3
    stage2_lr: float = 2e-4
    weight_decay: float = 1e-4
    augment: bool = True
    max_shift_px: int = 6
    stage2_replay_weight: float = 0.0
    stage2_area_weight: float = 1000.0
    base_channels: int | None = None
    arch: str = "resnet18"
    n_threads: int | None = None
    grad_clip: float = 5.0
    stage1_brightness_weight: float = 0.0
    stage2_val_fraction: float = 0.0
    stage1_area_weight: float = 0.0
    restarts: int = 1
    restart_screen_epochs: int = 0
    restart_finalists: int = 2
    split_seed: int | None = None

    def to_dict(self) -> dict:
        """The configuration as plain values (saved with the model and the checkpoint)."""
        return asdict(self)


def _epoch_generator(seed: int, stage: int, epoch: int) -> torch.Generator:
    digest = hashlib.sha256(f"{seed}/{stage}/{epoch}".encode()).digest()
    return torch.Generator().manual_seed(int.from_bytes(digest[:8], "little") & (2**63 - 1))


def _augment(x: torch.Tensor, ys: list[torch.Tensor], gen: torch.Generator, max_shift: int):
    """Random mirror and shift applied identically to columns and profiles."""
    n = x.shape[0]
    flip = torch.rand(n, generator=gen) < 0.5
    shifts = torch.randint(-max_shift, max_shift + 1, (n,), generator=gen)
    n_px = x.shape[-1]
    base = torch.arange(n_px)
    # index map: mirror then shift, clamped at the ends (edge values repeat: substrate)
    src = torch.where(flip[:, None], n_px - 1 - base[None, :], base[None, :])
    src = (src - shifts[:, None]).clamp(0, n_px - 1)
    return torch.gather(x, 1, src), [None if y is None else torch.gather(y, 1, src) for y in ys]


def data_fingerprint(*datasets: ColumnDataset | None) -> str:
    """SHA-256 of the training data (columns and labels), so a checkpoint resumes only on the same
    data."""
    h = hashlib.sha256()
    for ds in datasets:
        if ds is None:
            h.update(b"none")
            continue
        h.update(ds.columns.tobytes())
        for a in (ds.profiles_um, ds.linewidth_um, ds.overspray_um):
            h.update(b"-" if a is None else a.tobytes())
    return h.hexdigest()[:16]


class Trainer:
    """Runs stage 1 and stage 2, with checkpoints and resume.

    Parameters
    ----------
    config : TrainConfig
    pairs : ColumnDataset, optional
        Stage-1 (column, profile) pairs.
    labelled : ColumnDataset, optional
        Stage-2 columns with ``linewidth_um``/``overspray_um`` CV labels.
    init_model : ProfileModel, optional
        Start from this model instead of fresh weights (e.g. fine-tune only).
    checkpoint : path, optional
        Written after every epoch (atomically); with ``resume=True`` an
        existing checkpoint of the same config and data is continued.
    """

    def __init__(
        self,
        config: TrainConfig,
        pairs: ColumnDataset | None = None,
        labelled: ColumnDataset | None = None,
        *,
        init_model: ProfileModel | None = None,
        checkpoint=None,
        resume: bool = False,
        progress: bool = True,
        on_stage_end=None,
    ):
        if pairs is None and labelled is None:
            raise ValueError("nothing to train on: give stage-1 pairs and/or stage-2 columns")
        if pairs is not None and pairs.profiles_um is None:
            raise ValueError("stage-1 data set has no profiles_um")
        if labelled is not None and (
            labelled.linewidth_um is None or labelled.overspray_um is None
        ):
            raise ValueError("stage-2 data set needs linewidth_um and overspray_um labels")
        self.config = config
        self.pairs = pairs
        self.labelled, self.validation = _validation_split(labelled, config)
        self.checkpoint = Path(checkpoint) if checkpoint else None
        self.progress = progress
        self.on_stage_end = on_stage_end  # callback(stage, model) after each finished stage
        set_threads(config.n_threads)
        torch.use_deterministic_algorithms(True)
        ref = pairs if pairs is not None else labelled
        if init_model is not None:
            self.model = init_model
        else:
            if pairs is None:
                raise ValueError("training from scratch needs stage-1 pairs (or an init model)")
            torch.manual_seed(config.seed)
            if config.arch not in DEFAULT_WIDTH:
                raise ValueError(f"unknown network {config.arch!r}")
            net = build_network(
                NetworkConfig(
                    n_pixels=ref.n_pixels,
                    base_channels=config.base_channels or DEFAULT_WIDTH[config.arch],
                    arch=config.arch,
                )
            )
            scale = float(np.mean(np.max(pairs.profiles_um, axis=1)))
            if not scale > 0:
                raise ValueError("stage-1 profiles have no positive height")
            self.model = ProfileModel(net, ref.um_per_px, scale)
        for ds, name in ((pairs, "stage-1"), (labelled, "stage-2")):
            if ds is not None and abs(ds.um_per_px - self.model.um_per_px) > 1e-9:
                raise ValueError(
                    f"{name} data at {ds.um_per_px} µm/px, model at {self.model.um_per_px} µm/px"
                )
        self.history: list[dict] = []
        self.stage = 1
        self.epoch = 0  # epochs completed in the current stage
        self.optimizer = None
        self.scheduler = None
        self.fingerprint = data_fingerprint(pairs, labelled)
        self.train_seconds = 0.0
        self.stage_seconds = {"1": 0.0, "2": 0.0}
        self.area_ref: torch.Tensor | None = None  # stage-1 areas of the stage-2 columns
        # best stage-2 state on the validation split: score, epoch, network weights
        self.best: dict | None = None
        if resume and self.checkpoint and self.checkpoint.exists():
            self._load_checkpoint()

    # ------------------------------------------------------------ plumbing

    def _stage_epochs(self, stage: int) -> int:
        if stage == 1:
            return self.config.stage1_epochs if self.pairs is not None else 0
        return self.config.stage2_epochs if self.labelled is not None else 0

    def _make_optimizer(self, stage: int):
        lr = self.config.stage1_lr if stage == 1 else self.config.stage2_lr
        opt = torch.optim.AdamW(
            self.model.network.parameters(), lr=lr, weight_decay=self.config.weight_decay
        )
        data = self.pairs if stage == 1 else self.labelled
        steps = max(1, self._stage_epochs(stage) * int(np.ceil(len(data) / self.config.batch_size)))
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=steps, eta_min=0.05 * lr)
        return opt, sched

    def _save_checkpoint(self):
        if not self.checkpoint:
            return
        state = {
            "model": self.model.state(),
            "optimizer": self.optimizer.state_dict() if self.optimizer else None,
            "scheduler": self.scheduler.state_dict() if self.scheduler else None,
            "stage": self.stage,
            "epoch": self.epoch,
            "history": json.dumps(self.history),
            "config": json.dumps(self.config.to_dict()),
            "fingerprint": self.fingerprint,
            "train_seconds": self.train_seconds,
            "stage_seconds": json.dumps(self.stage_seconds),
            "area_ref": self.area_ref,
            "best": None
            if self.best is None
            else {
                "score": self.best["score"],
                "epoch": self.best["epoch"],
                "state_dict": self.best["state_dict"],
            },
        }
        self.checkpoint.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.checkpoint.with_suffix(self.checkpoint.suffix + ".tmp")
        torch.save(state, tmp)
        tmp.replace(self.checkpoint)

    def _load_checkpoint(self):
        state = torch.load(self.checkpoint, map_location="cpu", weights_only=True)
        saved_config = json.loads(state["config"])
        mine = self.config.to_dict()
        defaults = TrainConfig().to_dict()  # settings added since the checkpoint was written
        differs = {
            k for k in mine if k != "n_threads" and saved_config.get(k, defaults[k]) != mine[k]
        }
        if differs:
            raise ValueError(
                f"checkpoint {self.checkpoint} was made with different settings "
                f"({', '.join(sorted(differs))}); use a new checkpoint path or the same settings"
            )
        if state["fingerprint"] != self.fingerprint:
            raise ValueError(f"checkpoint {self.checkpoint} was made on different data")
        self.model = ProfileModel.from_state(state["model"])
        self.stage, self.epoch = int(state["stage"]), int(state["epoch"])
        self.history = json.loads(state["history"])
        self.train_seconds = float(state["train_seconds"])
        self.stage_seconds = json.loads(state["stage_seconds"])
        self.area_ref = state.get("area_ref")
        self.best = state.get("best")
        if state["optimizer"] is not None:
            self.optimizer, self.scheduler = self._make_optimizer(self.stage)
            self.optimizer.load_state_dict(state["optimizer"])
            self.scheduler.load_state_dict(state["scheduler"])

    # ------------------------------------------------------------ losses

    def _stage1_batch_loss(self, x, y_um):
        pred = self.model.network(x)
        loss = torch.mean((pred - y_um / self.model.height_scale_um) ** 2)
        w = self.config.stage1_brightness_weight
        if w > 0:
            # also match the profile's look to the camera (slope → brightness), which
            # is what linewidth and overspray are defined on
            px = self.model.um_per_px
            b_pred = feat.brightness_ratio(pred * self.model.height_scale_um, px)
            b_true = feat.brightness_ratio(y_um, px)
            loss = loss + w * torch.mean((b_pred - b_true) ** 2)
        w = self.config.stage1_area_weight
        if w > 0:
            # area of the clamped profile, as Q_m is read; the pixel size cancels
            a_pred = torch.clamp(pred * self.model.height_scale_um, min=0.0).sum(dim=1)
            a_true = y_um.sum(dim=1).to(a_pred.dtype).clamp(min=1e-6)
            loss = loss + w * torch.mean(((a_pred - a_true) / a_true) ** 2)
        return loss

    def _stage2_batch_loss(self, x, lw, ov, idx=None):
        h = self.model.forward_um(x)
        lw_p, ov_p = feat.smooth_features(h, self.model.um_per_px)
        # profiles whose features are undefined (no shoulder found, overspray
        # leaving the column) carry no feature loss: skip those terms
        err = torch.cat([lw_p - lw, ov_p - ov])
        ok = torch.isfinite(err)
        if not ok.any():
            return err.sum()  # nan: the caller skips the batch
        loss = torch.sum(err[ok] ** 2) / len(lw)
        if self.area_ref is not None and idx is not None:
            area = h.sum(dim=1) * self.model.um_per_px
            ref = self.area_ref[idx].to(area.dtype).clamp(min=1e-6)
            loss = loss + self.config.stage2_area_weight * torch.mean(((area - ref) / ref) ** 2)
        return loss

    # ------------------------------------------------------------ loop

    def run(self, stop_after_stage2_epoch: int | None = None) -> ProfileModel | None:
        """Train the remaining epochs of both stages; returns the model.

        With ``stop_after_stage2_epoch`` E, stop (checkpoint written, ``None``
        returned) once stage 2 has E epochs done; a later ``run()`` continues the
        same run (same schedule, same batches) to its end.
        """
        while self.stage <= 2:
            n_epochs = self._stage_epochs(self.stage)
            if (
                self.stage == 2
                and stop_after_stage2_epoch is not None
                and self.epoch >= stop_after_stage2_epoch
                and self.epoch < n_epochs
            ):
                return None
            if self.epoch >= n_epochs:
                if self.stage == 2 and self.best is not None:
                    self.model.network.load_state_dict(self.best["state_dict"])
                if self.on_stage_end is not None:
                    self.model.network.eval()
                    self.on_stage_end(self.stage, self.model)
                self.stage, self.epoch = self.stage + 1, 0
                self.optimizer = self.scheduler = None
                continue
            if self.optimizer is None:
                self.optimizer, self.scheduler = self._make_optimizer(self.stage)
            if self.stage == 2 and self.config.stage2_area_weight > 0 and self.area_ref is None:
                areas = self.model.predict_um(self.labelled.columns).sum(axis=1)
                self.area_ref = torch.from_numpy(areas * self.model.um_per_px)
            if self.stage == 2 and self.validation is not None and self.best is None:
                self._keep_if_best(0)  # the stage-1 model is a candidate too
            bar = tqdm(
                total=n_epochs,
                initial=self.epoch,
                desc=f"stage {self.stage}",
                unit="epoch",
                disable=not self.progress,
                leave=True,
            )
            while self.epoch < n_epochs:
                if (
                    self.stage == 2
                    and stop_after_stage2_epoch is not None
                    and self.epoch >= stop_after_stage2_epoch
                ):
                    break
                t0 = time.perf_counter()
                loss = self._run_epoch(self.stage, self.epoch)
                dt = time.perf_counter() - t0
                self.train_seconds += dt
                self.stage_seconds[str(self.stage)] += dt
                self.epoch += 1
                entry = {"stage": self.stage, "epoch": self.epoch, "loss": loss}
                if self.stage == 2 and self.validation is not None:
                    entry["val_score_um"] = self._keep_if_best(self.epoch)
                self.history.append(entry)
                bar.set_postfix(loss=f"{loss:.4g}")
                bar.update(1)
                self._save_checkpoint()
            bar.close()
        self.model.network.eval()
        self.model.meta.update(
            {
                "train_config": self.config.to_dict(),
                "history": self.history,
                "train_seconds": round(self.train_seconds, 2),
                "stage_seconds": {k: round(v, 2) for k, v in self.stage_seconds.items()},
                "data_fingerprint": self.fingerprint,
                "n_pairs": 0 if self.pairs is None else len(self.pairs),
                "n_labelled": 0 if self.labelled is None else len(self.labelled),
                "n_validation": 0 if self.validation is None else len(self.validation),
                "stage2_selected_epoch": None if self.best is None else self.best["epoch"],
                "stage2_selected_val_score_um": None
                if self.best is None
                else round(self.best["score"], 4),
                "torch_threads": torch.get_num_threads(),
            }
        )
        return self.model

    def validation_score(self) -> float:
        """Linewidth + overspray MAE (µm) vs the CV labels of the validation split.

        Features are read as :func:`~ajtwin.profile_cnn.features.read_features`
        reads them for scoring; each 1 % of undefined columns adds 1 µm.
        """
        val = self.validation
        pred = self.model.predict_um(val.columns)
        lw, ov, _ = feat.read_features(pred, val.um_per_px)
        ok = np.isfinite(lw) & np.isfinite(ov)
        if not ok.any():
            return float("inf")
        mae = np.mean(np.abs(lw[ok] - val.linewidth_um[ok])) + np.mean(
            np.abs(ov[ok] - val.overspray_um[ok])
        )
        return float(mae + 100.0 * np.mean(~ok))

    def _keep_if_best(self, epoch: int) -> float:
        value = self.validation_score()
        if self.best is None or value < self.best["score"]:
            self.best = {
                "score": value,
                "epoch": epoch,
                "state_dict": {
                    k: v.detach().clone() for k, v in self.model.network.state_dict().items()
                },
            }
        return value

    def _run_epoch(self, stage: int, epoch: int) -> float:
        gen = _epoch_generator(self.config.seed, stage, epoch)
        data = self.pairs if stage == 1 else self.labelled
        x_all = torch.from_numpy(normalize_columns(data.columns))
        order = torch.randperm(len(data), generator=gen)
        net = self.model.network
        net.train()
        # (batch norm keeps adapting in stage 2: freezing its stage-1 statistics
        # was tried and fine-tuning then made the linewidth error worse, 21 → 27 µm)
        total, count = 0.0, 0
        bs = self.config.batch_size
        replay = self.config.stage2_replay_weight if self.pairs is not None else 0.0
        for start in range(0, len(order), bs):
            idx = order[start : start + bs]
            if len(idx) < 2:  # batch norm needs ≥ 2 samples
                continue
            x = x_all[idx]
            if stage == 1:
                y = torch.from_numpy(data.profiles_um)[idx]
                if self.config.augment:
                    x, (y,) = _augment(x, [y], gen, self.config.max_shift_px)
                loss = self._stage1_batch_loss(x, y)
            else:
                lw = torch.from_numpy(data.linewidth_um)[idx]
                ov = torch.from_numpy(data.overspray_um)[idx]
                if self.config.augment:  # widths are invariant to mirror and shift
                    x, _ = _augment(x, [], gen, self.config.max_shift_px)
                loss = self._stage2_batch_loss(x, lw, ov, idx)
                if replay > 0:
                    n_replay = max(4, len(idx) // 4)  # a quarter batch keeps stage 2 cheap
                    pidx = torch.randint(0, len(self.pairs), (n_replay,), generator=gen)
                    xp = torch.from_numpy(normalize_columns(self.pairs.columns[pidx.numpy()]))
                    yp = torch.from_numpy(self.pairs.profiles_um[pidx.numpy()])
                    loss = loss + replay * self._stage1_batch_loss(xp, yp)
            self.optimizer.zero_grad(set_to_none=True)
            if not torch.isfinite(loss):
                continue  # every sample of the batch lacked a feature (nan): skip
            loss.backward()
            # the feature positions can be very sensitive to nm-level slopes: clip
            torch.nn.utils.clip_grad_norm_(net.parameters(), self.config.grad_clip)
            self.optimizer.step()
            self.scheduler.step()
            total += float(loss.detach()) * len(idx)
            count += len(idx)
        return total / max(count, 1)


def _validation_split(labelled: ColumnDataset | None, config: TrainConfig):
    """(training part, validation part) of the stage-2 columns, whole groups each.

    The draw depends only on ``config.split_seed`` (default ``config.seed``) and the
    groups, so a resumed run, and every restart, splits the same way. No split (``None``)
    when the fraction is 0.
    """
    frac = config.stage2_val_fraction
    if labelled is None or frac <= 0:
        return labelled, None
    if not frac < 1:
        raise ValueError(f"stage2_val_fraction must be in [0, 1), got {frac}")
    groups = np.unique(labelled.group)
    if len(groups) < 2:
        raise ValueError("a validation split needs at least 2 column groups")
    split_seed = config.seed if config.split_seed is None else config.split_seed
    rng = np.random.default_rng([split_seed, 19])
    n_val = min(len(groups) - 1, max(1, int(round(frac * len(groups)))))
    val_groups = rng.choice(groups, size=n_val, replace=False)
    is_val = np.isin(labelled.group, val_groups)
    return labelled.subset(np.flatnonzero(~is_val)), labelled.subset(np.flatnonzero(is_val))


def train_restarts(
    config: TrainConfig,
    pairs: ColumnDataset | None,
    labelled: ColumnDataset | None,
    *,
    checkpoint=None,
    resume: bool = False,
    progress: bool = True,
    on_stage_end=None,
    init_model: ProfileModel | None = None,
) -> tuple[ProfileModel, list[Trainer], int]:
    """Train ``config.restarts`` models and keep the best by stage-2 validation score.

    Restart r trains with seed ``config.seed + r`` (weights, batch order,
    augmentation) on the same validation split (``split_seed``, default
    ``config.seed``); each has its own checkpoint ``CHECKPOINT.rR`` (one restart:
    ``CHECKPOINT`` itself, as :class:`Trainer`), so an interrupted run resumes
    at the restart and epoch it reached. Ties keep the earlier restart.

    Parameters
    ----------
    on_stage_end : callable, optional
        ``on_stage_end(restart, stage, model)`` after each finished stage.

    Returns
    -------
    (model, trainers, best)
        The kept model (its meta lists every restart's seed and score), all
        trainers, and the index of the kept one.
    """

    n = int(config.restarts)
    if n < 1:
        raise ValueError(f"restarts must be >= 1, got {config.restarts}")
    if n > 1 and not config.stage2_val_fraction > 0:
        raise ValueError(
            "restarts pick the best run by its stage-2 validation score: "
            "give a validation split (--val-fraction > 0)"
        )
    split_seed = config.seed if config.split_seed is None else config.split_seed
    screen = int(config.restart_screen_epochs)
    screening = n > 1 and 0 < screen < config.stage2_epochs
    trainers = []
    for r in range(n):
        run_config = replace(
            config, seed=config.seed + r, split_seed=split_seed if n > 1 else config.split_seed
        )
        run_checkpoint = checkpoint
        if checkpoint and n > 1:
            run_checkpoint = Path(str(checkpoint) + f".r{r}")
        callback = None
        if on_stage_end is not None:
            callback = lambda stage, model, r=r: on_stage_end(r, stage, model)  # noqa: E731
        if progress and n > 1:
            tqdm.write(f"restart {r + 1}/{n} (seed {run_config.seed})")
        trainer = Trainer(
            run_config,
            pairs,
            labelled,
            init_model=init_model,
            checkpoint=run_checkpoint,
            resume=resume,
            progress=progress,
            on_stage_end=callback,
        )
        trainer.run(stop_after_stage2_epoch=screen if screening else None)
        trainers.append(trainer)

    def score_of(trainer):
        return trainer.best["score"] if trainer.best is not None else float("inf")

    screen_scores = [score_of(t) for t in trainers]
    finalists = list(range(n))
    if screening:
        ranked = np.argsort(screen_scores, kind="stable")
        finalists = sorted(int(r) for r in ranked[: max(1, config.restart_finalists)])
        for r in finalists:
            if progress:
                tqdm.write(f"finishing restart {r + 1} (seed {trainers[r].config.seed})")
            trainers[r].run()
    scores = [score_of(t) if r in finalists else float("inf") for r, t in enumerate(trainers)]
    best = int(np.argmin(scores)) if n > 1 else 0
    model = trainers[best].model
    model.meta["restarts"] = [
        {
            "seed": trainer.config.seed,
            "finished": r in finalists,
            "screen_val_score_um": None
            if not screening or np.isinf(screen_scores[r])
            else round(float(screen_scores[r]), 4),
            "val_score_um": None if np.isinf(scores[r]) else round(float(scores[r]), 4),
            "selected_epoch": None
            if trainer.best is None or r not in finalists
            else trainer.best["epoch"],
            "train_seconds": round(trainer.train_seconds, 2),
        }
        for r, trainer in enumerate(trainers)
    ]
    model.meta["restart_kept"] = best
    model.meta["train_seconds_all_restarts"] = round(sum(t.train_seconds for t in trainers), 2)
    return model, trainers, best


def train(
    pairs: ColumnDataset | None,
    labelled: ColumnDataset | None,
    config: TrainConfig | None = None,
    **kwargs,
) -> ProfileModel:
    """Train a :class:`ProfileModel` in two stages (with ``config.restarts``, the best
    of several runs). See :class:`Trainer` and :func:`train_restarts`."""
    return train_restarts(config or TrainConfig(), pairs, labelled, **kwargs)[0]
