"""The streaming detector: NIS, windowed NIS and CUSUM one EKF step at a time, alarms
merged into events, each labelled with its likely cause (paper §4 "applications").

Alarms close together are merged into one event; each event gets a likely cause from
the pattern of innovation signs and state corrections
(:func:`~ajtwin.apps.detection.causes.label_cause`). The statistics are in
:mod:`~ajtwin.apps.detection.statistics`, the thresholds in
:mod:`~ajtwin.apps.detection.settings`.
"""

from __future__ import annotations

from collections import deque
from dataclasses import asdict, dataclass, field

import numpy as np

from ajtwin import units
from ajtwin.apps.detection.causes import CAUSES, RUN_IN_EXPLAINS, label_cause
from ajtwin.apps.detection.settings import (
    CUSUM_CHANNELS,
    SHORT_OUTPUT,
    SHORT_STATE,
    DetectorSettings,
    cusum_thresholds,
)
from ajtwin.apps.detection.settling import RunIn
from ajtwin.apps.detection.statistics import (
    Cusum,
    MultiScaleLongRun,
    WindowedNIS,
    carried_differences,
    nis_tail_probability,
    normalised_innovations,
)
from ajtwin.apps.detection.steplog import StepLog
from ajtwin.estimation.vial import VialObserver


@dataclass
class AnomalyEvent:
    """One anomaly: when it was detected, when it began (estimate), what it likely is."""

    detected_s: float
    onset_s: float
    cause: str
    description: str
    detectors: list = field(default_factory=list)  # e.g. ["cusum+ P_c", "nis"]
    evidence: dict = field(default_factory=dict)  # mean normalised innovations etc.

    def to_dict(self) -> dict:
        """The event as a plain dict (JSON-friendly)."""
        return asdict(self)


# --------------------------------------------------------------------------- #
# Pure tests
# --------------------------------------------------------------------------- #


# --------------------------------------------------------------------------- #
# Detection over a run
# --------------------------------------------------------------------------- #


@dataclass
class DetectorStep:
    """What the detectors say after one step (one row of :class:`DetectionResult`)."""

    step: int
    time_s: float
    normalised_innovation: np.ndarray  # (5,)
    nis_p: float
    window_nis_p: float
    cusum_pos: np.ndarray  # (6,)
    cusum_neg: np.ndarray  # (6,)
    alarms: list  # detector labels that fired at this step
    raised: list  # AnomalyEvent opened at this step (label from the evidence so far)
    finalised: list  # AnomalyEvent whose evidence window closed at this step (final label)


#: steps the detectors keep of their per-step values: an event's evidence (evidence_s) and
#: its onset (a CUSUM's change point) lie within this many seconds of the present
HISTORY_S = 3600

#: the detector label of the event a deposit beyond the output model's range raises
CLEANING_DETECTOR = "ΔR_N beyond the model's range"

#: channel families for event grouping (AnomalyDetector._joins)
_FAMILIES = {"L_w": "line", "L_o": "line", "P_c": "pressure", "P_s": "pressure", "Q_m": "material"}


def _family(detector: str) -> str | None:
    """'cusum+ P_c' → 'pressure', 'V_l low' → 'vial', 'windowed NIS' → None (any)."""
    if detector.startswith("cusum"):
        return _FAMILIES[detector.split(" ", 1)[1].split("+")[0]]
    if detector.startswith("deposit"):
        return "pressure"  # a deposit is seen through the pressures
    return "vial" if detector.startswith("V_l") else None


class AnomalyDetector:
    """NIS, windowed-NIS and CUSUM tests, one EKF step at a time, alarms → labelled events.

    The batch :func:`detect_anomalies` runs this over arrays, so a live twin and a finished
    print give the same events. An event is *raised* at its first alarm with the cause
    read from the evidence so far and *finalised* once ``evidence_s`` seconds after the
    detection have been seen (or at :meth:`finish`), with the batch label.

    Parameters
    ----------
    settings : DetectorSettings, optional
    long_run_history : dict, optional
        :meth:`long_run_history` of the machine's previous print (or of its commissioning
        print): the CUSUMs start with the machine's long-run noise scale instead of 1.
        Ignored when it was taken with another block length or other channels.
    switched_on_s : float, optional
        When the atomizer was switched on (the record's ``atomizer_switched_on_s``): the
        print begins with a run-in (:class:`~ajtwin.apps.detection.settling.RunIn`; a
        switch-on in the atomizer current, given with ``inputs``, begins one too).
    """

    def __init__(
        self,
        settings: DetectorSettings | None = None,
        long_run_history: dict | None = None,
        switched_on_s: float | None = None,
    ):
        s = self.settings = settings or DetectorSettings()
        thresholds = cusum_thresholds(s)
        drifts = np.array(
            [s.cusum_drift] * 4 + [s.cusum_drift_material_flow, s.cusum_drift_pressure_sum]
        )
        self.cusum = Cusum(drifts, thresholds, len(CUSUM_CHANNELS))
        self.window = WindowedNIS(s.nis_window_s)
        self.long_run = MultiScaleLongRun(
            len(CUSUM_CHANNELS), s, carried_differences(long_run_history, s)
        )
        self._q_sum, self._q_n, self._q_ref = 0.0, 0, None  # Q_m's reference level
        self.long_run_reference = np.array([1.0] * 5 + [s.long_run_reference_pressure_sum])
        self.window_steps = int(np.asarray(s.nis_window_s, dtype=int))
        # the last deposit_window_s corrections of ΔR_N [nm] and whether the push is over
        self._deposit_push = deque(maxlen=int(s.deposit_window_s))
        self._deposit_crossing = False
        self.k = -1
        self.start = None  # first step past the warm-up
        self.t0 = None
        # per-step values of the last HISTORY_S steps (an event's evidence and onset)
        self.time = StepLog(HISTORY_S)
        self.e = StepLog(HISTORY_S)
        self.corrections = StepLog(HISTORY_S)
        self.stds = StepLog(HISTORY_S)
        self.vial = StepLog(HISTORY_S)
        self.nozzle = StepLog(HISTORY_S)  # the twin's ΔR_N per step [µm]
        self.opened_deposit: dict[int, float] = {}  # ΔR_N at each event's first alarm [µm]
        self.groups: list[list] = []  # raw alarms (step, change_step, label) per event
        self.events: list[AnomalyEvent] = []  # one per group
        self.final: list[bool] = []
        self._crossing = False
        self._vial_low = False
        self.vial_observer = None  # started at the first step that brings the inputs
        self.vial_running_low = StepLog(HISTORY_S)
        self._observer_vial = StepLog(HISTORY_S)
        self.vial_status = None  # the observer's latest VialStatus (None: no observer)
        self._unmeasured_since: float | None = None  # start of the current run without data
        self.restarts: list[float] = []  # times the warm-up restarted after a data gap
        self._beyond_since: int | None = None  # first step of the deposit beyond the range
        self._cleaning: int | None = None  # the 'nozzle needs cleaning' event (its index)
        # the atomizer's run-ins: events a mist building up explains are labelled 'run_in'
        self.run_in = RunIn(switched_on_s)

    def update_block(self, block, each=None) -> list[DetectorStep]:
        """The steps of a block of the twin's run, one after the other: ``block`` has
        ``time_s`` (m,), ``measurements`` (m, 5) (those the filter used), ``inputs`` (m, 3)
        and ``filtered`` (the filter's results of the m steps), as a committed
        :class:`~ajtwin.estimation.online.StepBlock` or a run's chunk has them.
        ``each(i, step)`` is called after each step (what the detectors say then)."""
        f = block.filtered
        columns = [
            np.asarray(c, dtype=float)
            for c in (
                block.measurements,
                f.predicted_outputs,
                f.innovation_variances,
                f.nis,
                f.n_measured,
                f.means,
                f.predicted_means,
                f.covariances,
            )
        ]
        t = np.asarray(block.time_s, dtype=float)
        u = None if block.inputs is None else np.asarray(block.inputs, dtype=float)
        steps = []
        for k in range(len(t)):
            steps.append(
                self.update(t[k], *(c[k] for c in columns), inputs=None if u is None else u[k])
            )
            if each is not None:
                each(k, steps[-1])
        return steps

    def update(
        self,
        time_s,
        measurement,
        predicted_output,
        innovation_variance,
        nis,
        n_measured,
        mean,
        predicted_mean,
        covariance,
        inputs=None,
    ) -> DetectorStep:
        """Step k: the EKF outputs of one sample (display units; see :func:`detect_anomalies`).

        With ``inputs`` (3,) the vial observer runs too (:mod:`ajtwin.estimation.vial`):
        started from the twin's V_l and σ at the first such step (the fill, or the
        previous print's end), it raises 'V_l low' and decides the 'ink running out'
        label. Without it the twin's V_l below ``vial_low_mL`` does (as before).
        """
        s = self.settings
        self.k += 1
        k = self.k
        t = float(time_s)
        if self.t0 is None:
            self.t0 = t
        self._restart_after_gap(t, n_measured)
        if self.start is None and t >= self.t0 + s.warmup_s:
            self.start = k
        e = normalised_innovations(
            np.asarray(measurement, dtype=float)[None],
            np.asarray(predicted_output, dtype=float)[None],
            np.asarray(innovation_variance, dtype=float)[None],
        )[0]
        mean = np.asarray(mean, dtype=float)
        current = None if inputs is None else float(np.asarray(inputs, dtype=float)[0])
        self.run_in.update(t, current, mean, predicted_output)
        self.time.append(t)
        self.e.append(e)
        self.corrections.append(mean - np.asarray(predicted_mean, dtype=float))
        self.stds.append(np.sqrt(np.maximum(np.diag(np.asarray(covariance, dtype=float)), 1e-300)))
        self.vial.append(float(mean[1]))
        self.nozzle.append(float(mean[3]))
        running_low = self._observe_vial(inputs, measurement, mean, covariance)
        self.vial_running_low.append(running_low)
        self._observer_vial.append(np.nan if running_low is None else self.vial_status.vial_ml)
        p_step = float(nis_tail_probability([nis], [n_measured])[0])
        # Huber-clipped innovations: a heavy-tailed outlier counts as a ±clip σ one
        c = s.innovation_clip_sigma
        e_clip = np.clip(e, -c, c)
        _, _, p_win = self.window.update(self._scaled_nis(nis, e, e_clip), n_measured)
        raw = self._cusum_alarms(k, e_clip)
        crossing = (
            self.start is not None and p_win < s.nis_alpha and k >= self.start + self.window_steps
        )
        if crossing and not self._crossing:  # the first step of a run of crossings
            raw.append((k, max(k - self.window_steps, 0), "windowed NIS"))
        self._crossing = crossing
        raw.extend(self._deposit_alarm(k))
        vial_low = mean[1] < s.vial_low_mL if running_low is None else running_low
        if self.start is not None and not self._vial_low and vial_low:
            self._vial_low = True
            raw.append((k, k, "V_l low"))
        raw.sort()
        raw, cleaning = self._nozzle_cleaning(k, float(mean[3]), raw)

        raised, finalised = self._group_alarms(raw, t)
        raised = cleaning + raised
        return DetectorStep(
            k,
            t,
            e,
            p_step,
            p_win,
            self.cusum.g_pos.copy() if self.cusum.started else np.zeros(len(CUSUM_CHANNELS)),
            self.cusum.g_neg.copy() if self.cusum.started else np.zeros(len(CUSUM_CHANNELS)),
            [name for _, _, name in raw],
            [self.events[i] for i in raised],
            [self.events[i] for i in finalised],
        )

    def _scaled_nis(self, nis, e, e_clip) -> float:
        """The step's NIS for the windowed test: each output's innovation Huber-clipped and
        divided by its long-run σ (the CUSUMs' :class:`MultiScaleLongRun`, ≥ 1), so the
        window tests what the CUSUMs test. Why the scale: the pressures' noise grows with
        the nozzle deposit (the flow controllers' jitter through a narrower nozzle; the
        filter's σ_w is constant): on a clean 24-h print their innovation variance rose
        from 1.08 to 1.55 and the unscaled window raised 7 events after hour 17."""
        nis = float(nis)
        total = np.nansum(e**2)
        if not np.isfinite(nis) or total <= 0:
            return nis
        scale = self.long_run.scale[: len(e)] if self.settings.nis_long_run_scaled else 1.0
        return nis * np.nansum((e_clip / scale) ** 2) / total

    def _nozzle_cleaning(self, k: int, deposit_um: float, raw: list) -> tuple[list, list]:
        """The 'nozzle needs cleaning' event: raised once, after the warm-up, when the twin's
        nozzle deposit is beyond ``cleaning_deposit_um`` (its onset the first step beyond);
        from then on every alarm of the print joins it instead of raising an event (beyond
        the output model's range the innovations grow with the deposit and a label would mean
        nothing). Returns (the alarms left to group, [its index] when raised at this step)."""
        if np.isfinite(deposit_um) and deposit_um > self.settings.cleaning_deposit_um:
            if self._beyond_since is None:
                self._beyond_since = k
        elif self._cleaning is None:
            self._beyond_since = None
        raised = []
        if self._cleaning is None:
            if self.start is None or self._beyond_since is None:
                return raw, []
            self.groups.append([(k, self._beyond_since, CLEANING_DETECTOR)])
            self.events.append(None)
            self.final.append(False)
            self._cleaning = len(self.groups) - 1
            raised = [self._cleaning]
        self.groups[self._cleaning].extend(raw)
        return [], raised

    def _restart_after_gap(self, t: float, n_measured) -> None:
        """After ``gap_restart_s`` seconds or more without any measurement, the first measured
        second restarts the warm-up (``warmup_s``) with fresh CUSUM, windowed-NIS and
        deposit-push sums: over a gap the twin's states follow the model alone, and the
        filter pulling them back once data return is the twin re-acquiring, not a fault
        (the transient the warm-up skips at a print's start; ``data/detectors.toml``
        [gaps]). The long-run noise scale and Q_m's reference level are kept."""
        measured = np.isfinite(n_measured) and float(n_measured) > 0
        if not measured:
            if self._unmeasured_since is None:
                self._unmeasured_since = t
            return
        since, self._unmeasured_since = self._unmeasured_since, None
        if since is None or t - since < self.settings.gap_restart_s:
            return
        s = self.settings
        self.t0, self.start = t, None
        self.cusum = Cusum(self.cusum.drift, self.cusum.threshold, len(CUSUM_CHANNELS))
        self.window = WindowedNIS(s.nis_window_s)
        self._crossing = False
        self._deposit_push.clear()
        self._deposit_crossing = False
        self.restarts.append(t)

    def _observe_vial(self, inputs, measurement, mean, covariance) -> bool | None:
        """The vial observer's step (started from the twin's V_l ± σ at the first step
        with inputs); whether the vial is running low (None: no inputs, no observer)."""
        if inputs is None:
            return None
        if self.vial_observer is None:
            sd = float(np.sqrt(max(float(np.asarray(covariance)[1, 1]), 1e-12)))
            self.vial_observer = VialObserver(fill_ml=float(mean[1]), fill_std_ml=sd)
        self.vial_status = self.vial_observer.update(inputs, float(measurement[4]))
        return self.vial_status.running_low

    def _cusum_alarms(self, k: int, e_clip: np.ndarray) -> list:
        """The CUSUM alarms of step k: (step, change step, label) each.

        Before the warm-up ends only Q_m's level is learned: the print's own level (its
        atomizer efficiency, which the twin learns by EM only after minutes) is Q_m's
        reference, then an EWMA of it (``material_flow_reference_s``); a change during the
        print is a fault. Each channel (five outputs and the common-mode pressure sum) is
        divided by its long-run σ.
        """
        s = self.settings
        q = e_clip[4]
        tau = float(s.material_flow_reference_s)
        if self.start is None:
            if np.isfinite(q):  # warm-up: the print's Q_m level so far
                self._q_sum += q
                self._q_n += 1
            return []
        channels = np.append(e_clip, e_clip[2] + e_clip[3])
        if tau > 0:
            if self._q_ref is None:
                self._q_ref = self._q_sum / self._q_n if self._q_n else 0.0
            channels[4] = q - self._q_ref
            if np.isfinite(q):
                self._q_ref += (q - self._q_ref) / tau
        channels = channels / self.long_run.update(channels / self.long_run_reference)
        raw = []
        for a in self.cusum.update(k, channels):
            sign = "+" if a.direction > 0 else "−"
            raw.append((a.step, a.change_step, f"cusum{sign} {CUSUM_CHANNELS[a.output]}"))
        return raw

    def _group_alarms(self, raw: list, t: float) -> tuple[list, list]:
        """Merge the step's alarms into events (a new event, or the last one when close
        and of a joining family) and relabel the open events; the indices of the events
        raised and of those whose evidence window closed at this step."""
        s = self.settings
        raised = []
        for alarm in raw:
            last = self.groups[-1][-1][0] if self.groups else None
            clog = self._clog_it_follows(alarm)
            if last is not None and t - self._time_of(last) <= s.merge_s and self._joins(alarm):
                self.groups[-1].append(alarm)
            elif clog is not None:
                self.groups[clog].append(alarm)  # the twin catching up with that clog
            else:
                self.opened_deposit[len(self.groups)] = self.nozzle[alarm[0]]
                self.groups.append([alarm])
                self.events.append(None)
                self.final.append(False)
                raised.append(len(self.groups) - 1)
        finalised = []
        for i, group in enumerate(self.groups):
            if self.final[i]:
                continue
            k_end = self._evidence_end(group[0][0])
            if k_end is not None:
                self.final[i] = True
                finalised.append(i)
            self.events[i] = self._event(group, k_end)
        return raised, finalised

    def _clog_it_follows(self, alarm) -> int | None:
        """The clog event a pressure alarm belongs to, or None.

        Once a clog is reported, EM learns its growth into θ_RN, and the model's drift
        θ_RN·ΔR_N grows with the deposit: a deposit growing at a steady rate is then
        over-predicted between EM updates (θ fitted over the last window, where the deposit
        was thinner), so both pressures read below the twin for minutes (nozzle_clog seed 4:
        −0.2…−0.5σ on each gauge from 66 min, a 'cusum− P_c+P_s' at 72.6 min labelled
        carrier leak). A pressure alarm (either sign, the deposit push too) while the
        twin's deposit is still at least what it was when the clog was detected is that
        clog, not a new fault: it joins the clog's event; so does a windowed-NIS alarm that
        would not have fired without the pressures (:meth:`_window_needs`). Alarms on the
        lines, Q_m or the vial still open their own events (a leak after a clog also moves
        Q_m and L_w).
        """
        family = _family(alarm[2])
        if family is None and "pressure" in self._window_needs(alarm[0]):
            family = "pressure"
        if family != "pressure":
            return None
        for i in range(len(self.events) - 1, -1, -1):
            event = self.events[i]
            if event is not None and event.cause == "nozzle_clog":
                opened = self.opened_deposit.get(i, -np.inf)
                return i if self.nozzle[alarm[0]] >= opened else None
        return None

    def _window_needs(self, k: int) -> set:
        """The families of outputs ('pressure', 'line', 'material') without whose excess the
        windowed NIS ending at step k would not have crossed.

        Over the window, with Huber-clipped e: S = Σ e² over the measured samples (n of
        them); a family's excess is Σ_F (e² − 1). The window needs family F when
        P(χ²(n) ≥ S − excess_F) ≥ α.
        """
        c = self.settings.innovation_clip_sigma
        seg = np.clip(np.asarray(self.e[max(k - self.window_steps + 1, 0) : k + 1]), -c, c)
        measured = np.isfinite(seg)
        squares = np.where(measured, seg**2, 0.0)
        n = float(measured.sum())
        if n == 0:
            return set()
        total = float(squares.sum())
        excess = {}
        for i, family in enumerate(_FAMILIES.values()):
            excess[family] = excess.get(family, 0.0) + float(
                squares[:, i].sum() - measured[:, i].sum()
            )
        alpha = self.settings.nis_alpha
        return {
            family
            for family, extra in excess.items()
            if extra > 0 and nis_tail_probability([total - extra], [n])[0] >= alpha
        }

    def _deposit_alarm(self, k: int) -> list:
        """The filter's push on the nozzle deposit over the last ``deposit_window_s``.

        P = Σ_j (x̂_j − x̂_{j|j−1})[ΔR_N] is what the data added to the deposit beyond the
        model's own growth (and θ_RN's, once EM has learnt one). A clog whose pressures the
        filter follows closely (innovations +0.2…+0.6 σ, below every CUSUM) still keeps
        pushing ΔR_N up: held-out alt machine 1168, +76 nm in 10 min. Only after the
        warm-up and with a full window; one alarm per run of crossings.
        """
        s = self.settings
        correction = float(units.um_to_nm(self.corrections[-1][3]))
        self._deposit_push.append(correction if np.isfinite(correction) else 0.0)
        full = len(self._deposit_push) == self._deposit_push.maxlen
        if self.start is None or k < self.start + len(self._deposit_push) or not full:
            return []
        over = sum(self._deposit_push) > s.deposit_push_nm
        alarms = []
        if over and not self._deposit_crossing:
            # change point: the last step where a CUSUM of the window's corrections with
            # allowance κ = push_nm / window (the slowest push that crosses in one window)
            # was 0; the plain cumulative sum's last minimum wanders minutes early on noise
            allowance = s.deposit_push_nm / len(self._deposit_push)
            g, last_zero = 0.0, -1
            for i, c in enumerate(self._deposit_push):
                g = max(0.0, g + c - allowance)
                if g == 0.0:
                    last_zero = i
            # entry i of the window is step k − len + 1 + i
            onset = min(k - len(self._deposit_push) + 2 + last_zero, k)
            alarms.append((k, onset, "deposit push ΔR_N"))
        self._deposit_crossing = over
        return alarms

    def finish(self) -> list[AnomalyEvent]:
        """End of the print: finalise the open events with the data there is; all events."""
        for i, group in enumerate(self.groups):
            if not self.final[i]:
                self.events[i] = self._event(group, self.k + 1)
                self.final[i] = True
        return list(self.events)

    def _joins(self, alarm) -> bool:
        """Whether an alarm belongs to the newest event (within ``merge_s`` of its last
        alarm): yes on a family of channels the event already has (line, pressure, Q_m;
        windowed NIS joins any), or while the event is active (its last alarm, or its
        detection, less than ``merge_other_family_s`` ago). Else a new event: a clog 4 min
        after the last alarm of a Q_m false alarm is a clog, not part of it."""
        group = self.groups[-1]
        family = _family(alarm[2])
        if family is None or family in {_family(name) for _, _, name in group}:
            return True
        last = max(step for step, _, _ in group)
        return self.time[alarm[0]] - self._time_of(last) <= self.settings.merge_other_family_s

    def _time_of(self, k: int) -> float:
        """The time of step k [s]; −inf for a step no longer kept (older than HISTORY_S)."""
        return self.time[k] if k >= self.time.first else -np.inf

    def long_run_history(self) -> dict:
        """The long-run statistics to carry to the machine's next print (JSON-able): the
        block differences d_j behind the current scale (NaN → None), with the block length
        and channels they were taken with."""
        return {
            "channels": list(CUSUM_CHANNELS),
            "blocks": {
                str(b): [[None if not np.isfinite(v) else float(v) for v in row] for row in d]
                for b, d in self.long_run.history().items()
            },
            "scale": self.long_run.scale.tolist(),
        }

    def _run_in_explains(self, group: list, k_end: int, onset_s: float) -> bool:
        """Whether the atomizer's run-in explains an event: it began in a run-in (after a
        switch-on, before the twin said ready to print) and none of its alarms up to
        ``k_end`` is on the pressures (their CUSUMs, the deposit push) or the vial. A mist
        building up moves Q_m, φ_A, d_a and the line; it does not clog the nozzle or leak
        the carrier line, which the pressure detectors find (a leak in seconds), and whose
        alarms keep their label at any time. What the event's label read from the pressures'
        means over its evidence does not decide: the twin correcting d_a and φ_A by tens of
        σ moves them too (second-generator start-ups 39 and 45: P_c −0.3σ against P_s
        +0.3σ beside Q_m −0.7σ, labelled carrier leak with only the Q_m and L_o CUSUMs
        fired; 28: a windowed NIS that counted the pressures' noise)."""
        if not self.run_in.covers(onset_s):
            return False
        for step, _, name in group:
            if step <= k_end and (
                _family(name) in ("pressure", "vial") or name == CLEANING_DETECTOR
            ):
                return False
        return True

    def _evidence_end(self, k_det: int) -> int | None:
        """First step at or after detection + evidence_s, if it has been seen."""
        target = self.time[k_det] + self.settings.evidence_s
        if self.time[-1] < target:
            return None
        return self.time.search(target)

    def _event(self, group: list, k_end: int | None) -> AnomalyEvent:
        """The event of a group of alarms, from the evidence up to ``k_end`` (None: so far)."""
        s = self.settings
        n = self.k + 1
        if k_end is None:
            k_end = n
        k_det = group[0][0]
        # the first alarm's own change point: later alarms may have found older drifts (an
        # onset more than HISTORY_S before its detection is put at the oldest step kept)
        k_on = max(min(k for step, k, _ in group if step == k_det), self.time.first)
        span = slice(max(k_on, 0), min(max(k_end, k_det + 1), n))
        seg = np.asarray(self.e[span])
        counts = np.isfinite(seg).sum(axis=0)
        with np.errstate(invalid="ignore"):
            mean_e = np.where(counts > 0, np.nansum(seg, axis=0) / np.maximum(counts, 1), 0.0)
        shift = np.asarray(self.corrections[span]).sum(axis=0) / self.stds[span.stop - 1]
        vial = self.vial[span.stop - 1]
        running_low = self.vial_running_low[span.stop - 1]
        cause = label_cause(mean_e, counts, shift, vial, s, running_low)
        if group[0][2] == CLEANING_DETECTOR:
            cause = "nozzle_cleaning"
        detectors = []
        for step, _, name in group:
            if step <= k_end and name not in detectors:
                detectors.append(name)
        if cause in RUN_IN_EXPLAINS and self._run_in_explains(group, k_end, self.time[k_on]):
            cause = "run_in"
        return AnomalyEvent(
            detected_s=self.time[k_det],
            onset_s=self.time[k_on],
            cause=cause,
            description=CAUSES[cause],
            detectors=detectors,
            evidence={
                "mean_normalised_innovation": dict(zip(SHORT_OUTPUT, np.round(mean_e, 3).tolist())),
                "state_correction_sigma": dict(zip(SHORT_STATE, np.round(shift, 3).tolist())),
                "vial_mL": float(vial),
                **(
                    {}
                    if running_low is None
                    else {
                        "vial_observer_running_low": bool(running_low),
                        "vial_observer_mL": float(self._observer_vial[span.stop - 1]),
                    }
                ),
            },
        )
