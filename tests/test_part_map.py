"""The part quality map: portions, the line along them, the probability, flags and files."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pandas as pd
import pytest

from ajtwin.apps.quality.part_map import (
    PORTION_COLUMNS,
    REPORT_COLUMNS,
    Tolerance,
    build_part_map,
    cause_groups,
    evaluate_portions,
    explain_flagged,
    out_of_tolerance_probability,
    parse_tolerance,
    place_alarms,
    smoothed_run,
)
from ajtwin.apps.quality.report import flagged_rows, write_report
from ajtwin.estimation.part_line import block_size, line_at
from ajtwin.estimation.print_time import program_for_record
from ajtwin.job import read_program_text
from ajtwin.model import load_parameters
from ajtwin.model.line_speed import load_line_speed_law
from ajtwin.model.system import output_function
from ajtwin.simulation import CameraSettings, run_job_print
from ajtwin.simulation.job_print import line_at_print_times

#: two strokes and a rapid between them, speeds written in the program
PROGRAM = """
ptp/ev (X,Y),0,0,10
OUT0.0=1
ptp/ev (X,Y),3,0,2
OUT0.0=0
ptp/ev (X,Y),3,4,10
OUT0.0=1
ptp/ev (X,Y),3,6,1
OUT0.0=0
"""


def _phi(z):
    return 0.5 * (1.0 + math.erf(z / math.sqrt(2.0)))


def test_tolerance_reads_the_ways_an_operator_writes_it():
    assert parse_tolerance("45±3") == Tolerance(42.0, 48.0)
    assert parse_tolerance("45+-3") == Tolerance(42.0, 48.0)
    assert parse_tolerance(" 45 +/- 2.5 µm") == Tolerance(42.5, 47.5)
    assert parse_tolerance("42:48") == Tolerance(42.0, 48.0)
    assert parse_tolerance("42:48").text == "45±3 µm"
    for bad in ("45", "48:42", "45±-3", "abc", "nan:3", "0:5"):
        with pytest.raises(ValueError, match="tolerance"):
            parse_tolerance(bad)


def test_probability_out_of_tolerance_against_a_hand_computation():
    tol = Tolerance(42.0, 48.0)
    # 44 ± 2: below 42 is z = -1, above 48 is z = +2
    expected = _phi(-1.0) + 1.0 - _phi(2.0)
    assert out_of_tolerance_probability(44.0, 2.0, tol) == pytest.approx(expected, abs=1e-12)
    assert expected == pytest.approx(0.181405, abs=1e-6)
    assert out_of_tolerance_probability(48.0, 1.0, tol) == pytest.approx(0.5 + _phi(-6.0))
    assert out_of_tolerance_probability([41.0, 45.0], [0.0, 0.0], tol).tolist() == [1.0, 0.0]


def test_portions_of_a_hand_made_program_get_their_print_times_and_coordinates():
    job = read_program_text(PROGRAM, process_speed_mm_s=2.0, rapid_speed_mm_s=10.0)

    def line(times, speeds, progress):  # a line that widens 2 µm per second, σ 0.5 µm
        times = np.asarray(times)
        mean = np.stack([40.0 + 2.0 * times, 20.0 + times], axis=1)
        return mean, np.full_like(mean, 0.5)

    tol = Tolerance(38.0, 41.5)
    table, points, notes = evaluate_portions(job, line, tol, printed_until_s=100.0)
    assert notes == [] and list(table.columns) == list(PORTION_COLUMNS)
    # stroke 0: (0,0)→(3,0) at 2 mm/s over 0–1.5 s; the rapid (3,0)→(3,4) at 10 mm/s is no
    # stroke; stroke 1: (3,4)→(3,6) at 1 mm/s from 1.9 s to 3.9 s
    expected = [
        (0, 0, (0, 0), (1, 0), 0.0, 0.5, 2.0),
        (0, 1, (1, 0), (2, 0), 0.5, 1.0, 2.0),
        (0, 2, (2, 0), (3, 0), 1.0, 1.5, 2.0),
        (1, 0, (3, 4), (3, 5), 1.9, 2.9, 1.0),
        (1, 1, (3, 5), (3, 6), 2.9, 3.9, 1.0),
    ]
    assert len(table) == len(expected)
    for row, (stroke, portion, a, b, t0, t1, speed) in zip(table.itertuples(), expected):
        assert (row.stroke, row.portion) == (stroke, portion)
        assert (row.from_x_mm, row.from_y_mm) == pytest.approx(a, abs=1e-12)
        assert (row.to_x_mm, row.to_y_mm) == pytest.approx(b, abs=1e-12)
        assert (row.printed_from_s, row.printed_to_s) == pytest.approx((t0, t1), abs=1e-12)
        assert row.length_mm == pytest.approx(1.0) and row.speed_mm_s == pytest.approx(speed)
        # a linear line: the length-weighted mean is the middle's; the band's envelope ±2σ
        assert row.lw_mean_um == pytest.approx(40.0 + (t0 + t1), abs=1e-9)
        assert (row.lw_lo_um, row.lw_hi_um) == pytest.approx((39 + 2 * t0, 41 + 2 * t1))
        # the worst point is the portion's end (widest): P(L_w > 41.5) there
        worst = 40.0 + 2.0 * t1
        p = _phi((38.0 - worst) / 0.5) + 1.0 - _phi((41.5 - worst) / 0.5)
        assert row.p_out == pytest.approx(p, abs=1e-9)
        assert row.flagged == (p >= 0.5)
    assert table["flagged"].tolist() == [False, True, True, True, True]
    # no sample point on the rapid: every point lies on a stroke
    assert points["speed_mm_s"].min() == pytest.approx(1.0)
    # a record that ended at 3 s: the last portion (printed to 3.9 s) is left out and said
    short, _, notes = evaluate_portions(job, line, tol, printed_until_s=3.0)
    assert len(short) == 4 and "1 of 5 portions" in notes[0]


def test_the_line_is_the_output_model_with_its_linearised_band_and_the_law_uncertainty():
    """The twin's line evaluation, which the part map uses, against an independent
    computation: the state interpolated between two samples, ν applied by the speed law
    written out, ∂g/∂x by central differences. Away from ν_ref the band also holds the speed
    law's own uncertainty, (L ln(ν_ref/ν) σ_b)² with σ_b a quarter of the exponent's
    bracketed range in data/line_speed.toml: the honest band of a line printed at another
    speed than the law was anchored at; at ν_ref that term is 0 and σ is the state's alone."""
    from ajtwin.estimation import Twin

    twin = Twin.default()
    spec = twin.spec
    params = load_parameters()
    x0 = np.array([3.6, 0.99, 1e-3, 0.03, 5e-7])
    x1 = np.array([3.7, 0.98, 2e-3, 0.05, 5.5e-7])
    scale = np.array([0.05, 1e-3, 1e-4, 5e-3, 2e-8])
    rng = np.random.default_rng(3)
    a = rng.normal(size=(5, 5)) * scale
    p0 = a @ a.T + np.diag(scale**2)
    p1 = 1.3 * p0
    u = np.array([[375.0, 23.0, 50.0], [380.0, 24.0, 50.0]])
    tau, nu = np.array([0.25, 0.5]), np.array([3.0, 2.0])
    line = line_at(twin.line_model, [0.0, 1.0], [x0, x1], [p0, p1], u, tau, nu)
    law = load_line_speed_law()
    sigma_b = (0.5 - 0.0) / 4.0  # linewidth_exponent_range = [0, 0.5] taken as ±2σ
    for i in range(2):
        w = tau[i]
        x = x0 + w * (x1 - x0)
        p = (1 - w) * p0 + w * p1
        factor = (law.reference_speed_mm_s / nu[i]) ** 0.3

        def g(state, factor=factor):
            y = np.asarray(output_function(state, u[0], params, spec.coefficients))[:2]
            return y * factor

        jac = np.zeros((2, 5))
        for j in range(5):
            step = np.zeros(5)
            step[j] = 1e-4 * max(abs(x[j]), scale[j])
            jac[:, j] = (g(x + step) - g(x - step)) / (2 * step[j])
        mean = g(x)
        law_share = (mean * math.log(law.reference_speed_mm_s / nu[i]) * sigma_b) ** 2
        expected_sd = np.sqrt(np.diag(jac @ p @ jac.T) + law_share)
        assert (line.linewidth_um[i], line.overspray_um[i]) == pytest.approx(mean, rel=1e-12)
        got_sd = (line.linewidth_std_um[i], line.overspray_std_um[i])
        assert got_sd == pytest.approx(expected_sd, rel=1e-5)
    # at ν_ref the law adds nothing: σ is the state's alone
    assert law_share.max() == 0.0


def test_the_line_in_padded_blocks_equals_the_line_point_by_point():
    """Blocks padded to a power of two (so a live map's changing number of points does not
    recompile) give each point's value as evaluated alone, and report their progress."""
    from ajtwin.estimation import Twin

    twin = Twin.default()
    rng = np.random.default_rng(5)
    t = np.arange(6.0)
    x = np.array([3.5, 1.0, 0.0, 0.03, 4.6e-7]) * (1 + 0.01 * rng.normal(size=(6, 5)))
    p = np.array([np.diag([1e-3, 1e-6, 1e-9, 1e-6, 1e-16])] * 6)
    u = np.tile([375.0, 23.0, 50.0], (6, 1))
    tau = rng.uniform(-0.5, 5.5, size=300)  # outside the steps: the nearest
    nu = rng.uniform(1.0, 4.0, size=300)
    done = []
    all_at_once = line_at(twin.line_model, t, x, p, u, tau, nu, progress=done.append)
    assert done == [300] and block_size(300) == 512
    for i in (0, 17, 299):
        alone = line_at(twin.line_model, t, x, p, u, tau[i], nu[i])
        assert alone.linewidth_um[0] == pytest.approx(all_at_once.linewidth_um[i], rel=1e-13)
        assert alone.linewidth_std_um[0] == pytest.approx(
            all_at_once.linewidth_std_um[i], rel=1e-12
        )
    before = line_at(twin.line_model, t, x, p, u, [-3.0, 0.0], [2.0, 2.0])
    assert before.linewidth_um[0] == before.linewidth_um[1]  # before the first step: its state


def test_alarms_are_placed_where_the_nozzle_was():
    job = read_program_text(PROGRAM, process_speed_mm_s=2.0, rapid_speed_mm_s=10.0)
    events = [{"detected_s": 0.75, "onset_s": 1.7, "cause": "nozzle_clog",
               "description": "nozzle clog", "detectors": ["cusum+ P_c"]}]  # fmt: skip
    table = place_alarms(job, events)
    row = table.iloc[0]
    assert (row.detected_x_mm, row.detected_y_mm, row.detected_stroke) == pytest.approx((1.5, 0, 0))
    # at 1.7 s the stage is on the rapid, 0.2 s after (3, 0): 2 mm up, shutter closed
    assert (row.onset_x_mm, row.onset_y_mm, row.onset_stroke) == pytest.approx((3.0, 2.0, -1))
    assert row.detectors == "cusum+ P_c"


CLOG_PROGRAM = "tests/data/prg/prg2svg/2 and 6-Au.prg"


@pytest.fixture(scope="module")
def clog_print():
    """A 12-min job print whose nozzle clogs fast from 4 min (first generator, seed 1)."""
    return run_job_print(
        CLOG_PROGRAM,
        "nozzle_clog",
        seed=1,
        duration_min=12,
        camera=CameraSettings(mode="trailing"),
        overrides={"fault": {"onset_min": 4.0, "nozzle_deposition_multiplier": 1500.0}},
    )


@pytest.fixture(scope="module")
def clog_map(clog_print):
    record = clog_print.record
    width = record.data["true_linewidth_um"].to_numpy()[:240]
    target = round(float(np.nanmedian(width)))
    tol = Tolerance(target - 1.5, target + 1.5)
    job = program_for_record(record, CLOG_PROGRAM)  # the program as the print ran it
    run = smoothed_run(record, job=job)  # its frames filed at their print times
    assert run.camera_counts["filed"] > 0 and run.line_factors is not None
    part = build_part_map(job, run, tol, source="clog")
    part.run = run
    return part


def test_flagged_portions_are_those_whose_true_width_leaves_the_tolerance(clog_print, clog_map):
    points, table = clog_map.points, clog_map.portions
    virtual = clog_print.virtual
    truth = line_at_print_times(
        np.minimum(points["time_s"].to_numpy(), len(clog_print.record) - 1),
        points["speed_mm_s"].to_numpy(),
        virtual.states,
        virtual.processes.head_inputs,
        virtual.outputs_true,
        load_parameters(),
        virtual.line_coefficients,
        virtual.machine,
        clog_print.line_speed_law,
    )[:, 0]
    tol = clog_map.tolerance
    out = (truth < tol.low_um) | (truth > tol.high_um)
    truly = pd.Series(out).groupby(points["portion"].to_numpy()).max().to_numpy()
    flagged = table["flagged"].to_numpy()
    onset = clog_print.record.meta["fault_onset_s"]
    after = table["printed_from_s"].to_numpy() >= onset
    assert truly[after].sum() > 200 and not truly[~after].any()  # the clog made them
    both = (truly & flagged).sum()
    assert both / flagged.sum() >= 0.85  # precision
    assert both / truly.sum() >= 0.95  # recall
    assert not flagged[~after].any()  # nothing flagged before the clog began
    # the band holds the true width over most of the length (a fast clog: ~84 %)
    assert clog_map.coverage_of(truth) >= 0.75


def test_report_files_are_written_readable_and_self_contained(clog_map, tmp_path):
    import matplotlib.image

    paths = write_report(clog_map, tmp_path / "out")
    table = pd.read_csv(paths["strokes.csv"])
    assert list(table.columns) == list(REPORT_COLUMNS)
    assert len(table) == len(clog_map.portions) and table["flagged"].sum() > 0
    assert (table["lw_lo_um"] <= table["lw_mean_um"]).all()
    assert (table["lw_mean_um"] <= table["lw_hi_um"]).all()
    image = matplotlib.image.imread(paths["part.png"])
    assert image.ndim == 3 and image.shape[0] > 300 and image.shape[1] > 300
    page = paths["report.html"].read_text(encoding="utf-8")
    assert not re.search(r"https?://|//[a-z0-9.-]+\.[a-z]{2,}/|<link|<script\s+src", page, re.I)
    assert 'src="data:image/png;base64,' in page
    facts = json.loads(re.search(r'id="facts">(.*?)</script>', page, re.S).group(1))
    assert facts["flagged_portions"] == int(clog_map.portions["flagged"].sum())
    # the flagged table lists the most probable first
    rows = re.findall(r"<h2>Flagged portions.*?</table>", page, re.S)[0]
    assert rows.count("<tr>") == min(500, facts["flagged_portions"]) + 1


def test_the_report_says_why_each_flagged_group_is_out_in_minutes_and_mm(clog_map, tmp_path):
    """Each flagged portion carries its cause: the alarm it was printed under (cause in
    words, since when, what to do) or that none was raised, and what the twin reads as
    having moved the line (the nozzle deposit, here); times in minutes, no e-notation, no
    feature −1, runs counted from 1."""
    import dataclasses

    from click.testing import CliRunner

    from ajtwin.cli.job import _echo_part_report

    # no alarm at all: every flagged portion is said to be out without one, driven by ΔR_N
    (group,) = cause_groups(clog_map)
    assert group["alarm"] == 0 and "no alarm" in group["sentence"]
    assert "nozzle ΔR_N" in group["driver"] and "+" in group["driver"]
    # the clog's alarm from 4.5 min: the portions printed after its onset are its own
    event = {"detected_s": 300.0, "onset_s": 270.0, "cause": "nozzle_clog",
             "description": "", "detectors": ["cusum+ P_c+P_s", "deposit push ΔR_N"]}  # fmt: skip
    alarms = place_alarms(clog_map.job, [event])
    table = explain_flagged(clog_map.portions, alarms, clog_map.run)
    part = dataclasses.replace(clog_map, portions=table, alarms=alarms, machine="lab1")
    groups = {g["alarm"]: g for g in cause_groups(part)}
    clog = groups[1]
    assert clog["sentence"] == (
        "A1 nozzle clogging since 4.5 min: clean the nozzle, then "
        "`ajtwin machine maintain lab1 --nozzle-cleaned`"
    )
    assert clog["from_min"] >= 4.5 and clog["portions"] > 0.9 * table["flagged"].sum()
    assert "ΔR_N" in clog["driver"]
    flagged = table[table["flagged"]]
    assert (flagged["cause"] != "").all() and (table.loc[~table["flagged"], "cause"] == "").all()
    paths = write_report(part, tmp_path / "out")
    page = paths["report.html"].read_text(encoding="utf-8")
    words = re.sub(r"<script.*?</script>|<img[^>]*>|<style>.*?</style>", "", page, flags=re.S)
    assert "<h2>Why they are out</h2>" in words and "--nozzle-cleaned" in words
    assert not re.search(r"\d[eE][+-]\d", words)  # no 4.75e+03
    assert "feature -1" not in words and "(no feature)" not in words
    assert "printed [min]" in words and "<th>run</th>" in words
    runs = flagged_rows(part, flagged)["run"].astype(int).to_numpy()
    assert (runs == flagged["repetition"].to_numpy() + 1).all()  # the map's "run N"
    with CliRunner().isolation() as (out, *_):
        _echo_part_report(part, paths)
        text = out.getvalue().decode()
    assert "why         A1 nozzle clogging since 4.5 min" in text
    assert "worst: run 5," in text and " s," not in text and "feature" not in text
    assert not re.search(r"\d[eE][+-]\d", text)
