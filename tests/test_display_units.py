"""One time base and one unit per quantity wherever a person looks: units.DISPLAY_UNITS,
numbers without e-notation, figures in print time [min] with φ_A in ppm and Q_m in nL/s."""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np
import pytest

from ajtwin import units
from ajtwin.model.names import INPUT_NAMES, OUTPUT_NAMES, STATE_NAMES


def test_every_state_input_and_output_has_one_display_unit():
    assert set(units.DISPLAY_UNITS) == {*STATE_NAMES, *INPUT_NAMES, *OUTPUT_NAMES}
    assert units.display("aerosol_fraction").label == "φ_A [ppm]"
    assert units.display("material_flow_mL_s").label == "Q_m [nL/s]"
    # hand-computed: 4.5e-7 (a volume fraction) = 0.45 ppm; 1.5e-8 mL/s = 0.015 nL/s
    assert units.display("aerosol_fraction").shown(4.5e-7) == pytest.approx(0.45)
    assert units.display("material_flow_mL_s").shown(1.5e-8) == pytest.approx(0.015)
    assert units.drift_rate_percent_per_hour(1e-6) == pytest.approx(0.36)
    with pytest.raises(KeyError, match="no display unit"):
        units.display("nozzle")


@pytest.mark.parametrize(
    "value, text",
    [(4751.2, "4751"), (9840.4, "9840"), (0.015312, "0.0153"), (73.96, "74"), (-2.0, "-2"),
     (2.2e-5, "0.000022"), (1.0, "1"), (float("nan"), "–"), (0.0, "0"), (123456.7, "123457")],
)  # fmt: skip
def test_numbers_for_people_have_no_e_notation(value, text):
    assert units.readable(value) == text
    assert not re.search(r"[eE][+-]?\d", units.readable(value))
    assert units.minutes_text(1231.8) == "20.5 min"


def test_ajtwin_plot_draws_ppm_and_nl_per_s_against_print_time():
    from ajtwin.simulation import simulate
    from ajtwin.simulation.plotting import plot_record

    record = simulate("exp1", seed=3, duration_min=2.0)
    fig = plot_record(record, nominal=False)
    axes = {ax.get_ylabel(): ax for ax in fig.axes}
    assert {"φ_A [ppm]", "Q_m [nL/s]"} <= set(axes) and "φ_A [–]" not in axes
    phi = axes["φ_A [ppm]"].lines[0].get_ydata()
    np.testing.assert_allclose(phi, record.data["true_aerosol_fraction"] * 1e6)
    q_m = np.asarray(axes["Q_m [nL/s]"].lines[0].get_ydata(), dtype=float)
    assert 0.001 < np.nanmedian(q_m) < 1.0  # ~0.015 nL/s, not 1.5e-8
    assert {ax.get_xlabel() for ax in fig.axes} >= {"print time [min]"}
    assert "time [min]" not in {ax.get_xlabel() for ax in fig.axes}
    import matplotlib.pyplot as plt

    plt.close(fig)


def test_estimate_plot_states_are_scaled_to_their_display_units():
    import matplotlib.pyplot as plt

    from ajtwin.estimation.plotting import OUTPUT_LABELS, STATE_LABELS, plot_states

    assert STATE_LABELS[4] == "φ_A [ppm]" and OUTPUT_LABELS[4] == "Q_m [nL/s]"
    means = np.tile([3.4, 1.0, 1e-4, 0.04, 4.5e-7], (3, 1))
    fig, axes = plt.subplots(1, 5)
    plot_states(axes, np.arange(3.0), {"twin": (means, None, {"color": "k"})})
    assert axes[4].lines[0].get_ydata() == pytest.approx([0.45] * 3)
    assert axes[4].get_title() == "φ_A [ppm]" and axes[0].get_xlabel() == "print time [min]"
    plt.close(fig)


def test_the_demo_outputs_figure_puts_each_alarm_at_its_print_time(monkeypatch):
    """Each print on its own print-time axis, as the Detectors figure: the second print's
    alarm at 8.5 min sits at 8.5 on its axis, not at the first print's length + 8.5."""
    from ajtwin.studies import demo_report

    monkeypatch.setattr(demo_report, "figure_png", lambda fig: fig)
    t1, t2 = np.arange(300.0), np.arange(1200.0)
    alarm = SimpleNamespace(detected_s=510.0)
    prints = [
        {"label": "print 1", "time_s": t1, "measured": np.ones((300, 5)),
         "predicted": np.ones((300, 5)), "events": []},
        {"label": "print 2", "time_s": t2, "measured": np.ones((1200, 5)),
         "predicted": np.ones((1200, 5)), "events": [alarm], "fault_onset_s": 480.0},
    ]  # fmt: skip
    fig = demo_report.outputs_figure(prints)
    second = [ax for ax in fig.axes if ax.get_title() == "print 2"][0]
    marks = sorted(line.get_xdata()[0] for line in second.lines if len(line.get_xdata()) == 2)
    assert marks == pytest.approx([8.0, 8.5])
    assert {ax.get_xlabel() for ax in fig.axes if ax.get_xlabel()} == {"print time [min]"}
    assert fig.axes[4 * 2].get_ylabel() == "Q_m [nL/s]"
