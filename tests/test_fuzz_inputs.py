"""Fuzzing the input surfaces with hypothesis: record reader, scenario loader, CLI.

Every generated input must give either a valid result or a clear error of a defined type
whose message names the file — never a traceback of another type, a hang or a silently
wrong record. What "valid" means is checked, not assumed:

* a record: time on a strictly increasing 1 s grid, every record column present, every
  value NaN or inside the reader's plausible range, metadata passing ``validate_meta``;
  and for a file that was only cut short (a logger killed mid-write), every row read is
  exactly a row of the original, with a warning when the last one may be incomplete;
* a scenario: set-points finite and inside the model's input limits;
* a command line: options that parse satisfy their documented ranges.

Profiles (hypothesis settings): ``fuzz`` (default suite, a few hundred inputs over all
tests, seconds) and ``fuzz-long`` (``pytest -m slow``: 10,000 inputs in total). Inputs that
once failed are kept in ``tests/fuzz_corpus/`` and replayed by :func:`test_corpus`.
"""

from __future__ import annotations

import io
import json
import math
import os
import warnings
from collections import Counter
from pathlib import Path

import click
import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ajtwin.io.records import (
    PLAUSIBLE_RANGES,
    RECORD_COLUMNS,
    RecordError,
    read_record,
    validate_meta,
)

CORPUS = Path(__file__).parent / "fuzz_corpus"
#: Outcome counts of the record fuzzers; written as JSON lines to $AJTWIN_FUZZ_REPORT (if set)
#: after each test, for docs/validation.md.
OUTCOMES: Counter = Counter()


@pytest.fixture(autouse=True)
def _report_outcomes(request):
    OUTCOMES.clear()
    yield
    target = os.environ.get("AJTWIN_FUZZ_REPORT")
    if target and OUTCOMES:
        with open(target, "a") as fh:
            fh.write(json.dumps({"test": request.node.name, **dict(OUTCOMES)}) + "\n")


_COMMON = dict(
    deadline=None,
    derandomize=False,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    database=None,
)
# per test: the default suite runs ~60-100 inputs per surface (a few hundred in all);
# the slow run 10,000 in all (2,500 per surface)
settings.register_profile("fuzz", max_examples=60, **_COMMON)
settings.register_profile("fuzz-long", max_examples=2500, **_COMMON)
PROFILES = [
    pytest.param("fuzz", id="fuzz"),
    pytest.param("fuzz-long", id="fuzz-long", marks=pytest.mark.slow),
]


# --------------------------------------------------------------------------- #
# Shared: what a valid record is
# --------------------------------------------------------------------------- #
def assert_valid_record(record) -> None:
    t = record.time_s
    assert len(t) >= 1 and np.all(np.isfinite(t))
    if len(t) > 1:
        np.testing.assert_allclose(np.diff(t), 1.0, atol=1e-6)
    for column in RECORD_COLUMNS:
        assert column in record.data.columns, column
    for column, (low, high, *_) in PLAUSIBLE_RANGES.items():
        if column not in record.data.columns:
            continue
        values = record.data[column].to_numpy(dtype=float)
        finite = values[np.isfinite(values)]
        assert not np.isinf(values).any(), column
        assert np.all((finite >= low) & (finite <= high)), column
    validate_meta(record.meta, "check")


def read_outcome(path: Path):
    """read_record → ('ok', record, warnings) or ('error', message); anything else fails."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            record = read_record(path)
        except RecordError as exc:
            assert str(path) in str(exc), f"error does not name the file: {exc}"
            OUTCOMES["error: " + _kind_of(str(exc), path)] += 1
            return "error", str(exc), None
    assert_valid_record(record)
    OUTCOMES["valid record" + (" (with warnings)" if caught else "")] += 1
    return "ok", record, [str(w.message) for w in caught]


def _kind_of(message: str, path: Path) -> str:
    """The gist of an error for the outcome counts: quotes, brackets and numbers blanked."""
    import re

    text = message.replace(str(path), "").lstrip(": ")
    text = re.sub(r"'[^']*'|\"[^\"]*\"|\([^)]*\)", "…", text)
    text = re.sub(r"(?<![A-Za-z\d.-])[-+]?\d[\d.e+-]*", "N", text)
    return " ".join(text.split()[:7])


def base_table(n: int, seed: int) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    return pd.DataFrame(
        {
            "time_s": np.arange(n, dtype=float),
            "atomizer_current_mA": 375 + rng.normal(0, 5, n),
            "carrier_flow_sccm": 23 + rng.normal(0, 0.2, n),
            "sheath_flow_sccm": 50 + rng.normal(0, 0.2, n),
            "carrier_pressure_Pa": 5661 + rng.normal(0, 3, n),
            "sheath_pressure_Pa": 5641 + rng.normal(0, 3, n),
            "linewidth_um": 43 * np.exp(rng.normal(0, 0.04, n)),
            "overspray_um": 29 * np.exp(rng.normal(0, 0.08, n)),
            "material_flow_mL_s": 1.54e-8 * np.exp(rng.normal(0, 0.15, n)),
        }
    )


json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(10**20), 10**20)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=10),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=12), inner, max_size=4)
    ),  # fmt: skip
    max_leaves=10,
)
meta_values = st.one_of(
    json_values,
    st.fixed_dictionaries(
        {},
        optional={
            "platen_speed_mm_s": json_values,
            "seed": json_values,
            "fault_onset_s": json_values,
            "fault_kind": json_values,
            "machine_id": json_values,
            "units": json_values,
            "format_version": json_values,
        },
    ),
)
cell_text = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(10**30), 10**30).map(str),
    st.text(max_size=8),
    st.sampled_from(["", "nan", "NA", "null", "1e999", "-0", "0x10", "1,5", '"', "2026-11-23"]),
)

# a corruption: (kind, parameters)
corruptions = st.one_of(
    st.tuples(st.just("cell"), st.integers(0, 60), st.integers(0, 8), cell_text),
    st.tuples(st.just("time"), st.integers(0, 60), st.floats(allow_nan=True)),
    st.tuples(st.just("cut"), st.floats(0.0, 1.0)),
    st.tuples(st.just("insert"), st.floats(0.0, 1.0), st.binary(min_size=1, max_size=6)),
    st.tuples(st.just("dropline"), st.integers(0, 60)),
    st.tuples(st.just("dupline"), st.integers(0, 60)),
    st.tuples(
        st.just("header"),
        st.integers(0, 8),
        st.sampled_from(["time_s", "carrier_flow_sccm", "Q_c", "", " x ", "linewidth"]),
    ),  # fmt: skip
    st.tuples(st.just("meta"), meta_values),
    st.tuples(st.just("encoding"), st.sampled_from(["utf-16", "utf-16-le", "latin-1", "cp1252"])),
    st.tuples(st.just("separator"), st.sampled_from([";", "\t", "|"])),
    st.tuples(st.just("crlf")),
    st.tuples(
        st.just("wallclock"),
        st.sampled_from(["", "Z", "+01:00", "-0530"]),
        st.integers(0, 60),
        st.sampled_from(["", "Z", "+02:00"]),
    ),  # fmt: skip
)


def corrupt_csv(table: pd.DataFrame, ops) -> bytes:
    table = table.copy().astype(object)
    meta_lines = []
    encoding = "utf-8"
    separator = ","
    byte_ops = []
    for op in ops:
        kind = op[0]
        if kind == "cell" and len(table):
            table.iat[op[1] % len(table), op[2] % table.shape[1]] = op[3]
        elif kind == "time" and len(table):
            table.iat[op[1] % len(table), 0] = op[2]
        elif kind == "dropline" and len(table) > 1:
            table = table.drop(table.index[op[1] % len(table)])
        elif kind == "dupline" and len(table):
            row = op[1] % len(table)
            table = pd.concat([table.iloc[: row + 1], table.iloc[row:]])
        elif kind == "header":
            names = list(table.columns)
            names[op[1] % len(names)] = op[2]
            table.columns = names
        elif kind == "meta":
            meta_lines.append("# meta: " + json.dumps(op[1]))
        elif kind == "encoding":
            encoding = op[1]
        elif kind == "separator":
            separator = op[1]
        elif kind == "wallclock" and len(table):
            # ISO wall-clock stamps, one row with another zone suffix (or none)
            stamps = pd.Timestamp("2026-11-23T08:00:00") + pd.to_timedelta(
                np.arange(len(table)), "s"
            )
            text = [s.isoformat() + op[1] for s in stamps]
            text[op[2] % len(text)] = stamps[op[2] % len(text)].isoformat() + op[3]
            table.iloc[:, 0] = text
        else:
            byte_ops.append(op)
    text = "\n".join(meta_lines + [table.to_csv(index=False, sep=separator).rstrip("\n")]) + "\n"
    if ("crlf",) in byte_ops:
        text = text.replace("\n", "\r\n")
    data = text.encode(encoding, errors="replace")
    for op in byte_ops:
        if op[0] == "cut":
            data = data[: int(op[1] * len(data))]
        elif op[0] == "insert":
            at = int(op[1] * len(data))
            data = data[:at] + op[2] + data[at:]
    return data


# --------------------------------------------------------------------------- #
# The record reader: CSV
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("profile", PROFILES)
def test_fuzz_csv_reader(profile, tmp_path):
    path = tmp_path / "fuzz.csv"

    @settings(settings.get_profile(profile))
    @given(
        n=st.integers(1, 30),
        seed=st.integers(0, 2**16),
        ops=st.lists(corruptions, max_size=4),
    )
    def run(n, seed, ops):
        table = base_table(n, seed)
        path.write_bytes(corrupt_csv(table, ops))
        read_outcome(path)

    run()


@pytest.mark.parametrize("profile", PROFILES)
def test_fuzz_csv_cut_short_never_gives_a_wrong_row(profile, tmp_path):
    """A file cut at any byte: every row read is the original's, or a warning says it may not be."""
    path = tmp_path / "cut.csv"

    @settings(settings.get_profile(profile))
    @given(n=st.integers(2, 30), seed=st.integers(0, 2**16), cut=st.integers(0, 10**6))
    def run(n, seed, cut):
        table = base_table(n, seed)
        whole = table.to_csv(index=False).encode()
        path.write_bytes(whole[: cut % (len(whole) + 1)])
        outcome = read_outcome(path)
        if outcome[0] == "error":
            return
        _, record, caught = outcome
        got = record.data[list(table.columns)].to_numpy(dtype=float)
        want = table.to_numpy(dtype=float)[: len(got)]
        assert len(got) <= len(table)
        exact = [np.array_equal(got[i], want[i], equal_nan=True) for i in range(len(got))]
        assert all(exact[:-1]), "a complete line was read wrongly"
        if not exact[-1]:
            assert any("line end" in w or "cut" in w for w in caught), "cut row read silently"

    run()


# --------------------------------------------------------------------------- #
# The record reader: Parquet
# --------------------------------------------------------------------------- #
parquet_columns = st.sampled_from(
    ["float", "int", "string", "bool", "datetime", "null", "nan", "huge", "negative", "list",
     "struct", "binary", "decimal", "duration", "datetime_tz", "dictionary", "uint64"]
)  # fmt: skip


def _parquet_column(kind: str, n: int, base: np.ndarray):
    import pyarrow as pa

    if kind == "float":
        return pa.array(base)
    if kind == "int":
        return pa.array(np.round(base).astype(np.int64))
    if kind == "string":
        return pa.array([f"{v:.6g}" for v in base])
    if kind == "bool":
        return pa.array(base > np.median(base))
    if kind == "datetime":
        return pa.array(pd.date_range("2026-11-23", periods=n, freq="s"))
    if kind == "null":
        return pa.nulls(n, pa.float64())
    if kind == "nan":
        return pa.array(np.full(n, np.nan))
    if kind == "huge":
        return pa.array(base * 1e300)
    if kind == "list":
        return pa.array([[v, v] for v in base])
    if kind == "struct":
        return pa.array([{"value": v} for v in base])
    if kind == "binary":
        return pa.array([bytes([int(v) % 256, 0xFF]) for v in base])
    if kind == "decimal":
        import decimal

        return pa.array([decimal.Decimal(f"{v:.6f}") for v in base])
    if kind == "duration":
        return pa.array(pd.to_timedelta(np.arange(n), "s"))
    if kind == "datetime_tz":
        return pa.array(pd.date_range("2026-11-23", periods=n, freq="s", tz="Europe/Berlin"))
    if kind == "dictionary":
        return pa.array([f"{v:.6g}" for v in base]).dictionary_encode()
    if kind == "uint64":
        return pa.array(np.full(n, 2**64 - 1, dtype=np.uint64))
    return pa.array(-base)


@pytest.mark.parametrize("profile", PROFILES)
def test_fuzz_parquet_reader(profile, tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = tmp_path / "fuzz.parquet"

    @settings(settings.get_profile(profile))
    @given(
        n=st.integers(1, 30),
        seed=st.integers(0, 2**16),
        kinds=st.dictionaries(st.integers(0, 8), parquet_columns, max_size=3),
        rename=st.dictionaries(
            st.integers(0, 8), st.sampled_from(["time_s", "Q_c", "x", ""]), max_size=2
        ),  # fmt: skip
        meta=st.one_of(
            st.none(), st.binary(max_size=20), meta_values.map(lambda v: json.dumps(v).encode())
        ),
        damage=st.one_of(
            st.none(),
            st.tuples(st.floats(0, 1), st.binary(min_size=1, max_size=8)),
            st.floats(0, 1),
        ),  # fmt: skip
    )
    def run(n, seed, kinds, rename, meta, damage):
        table = base_table(n, seed)
        names = list(table.columns)
        for index, name in rename.items():
            names[index] = name
        arrays = [
            _parquet_column(kinds.get(i, "float"), n, table.iloc[:, i].to_numpy(dtype=float))
            for i in range(table.shape[1])
        ]
        arrow = pa.Table.from_arrays(arrays, names=names)
        if meta is not None:
            arrow = arrow.replace_schema_metadata({b"ajtwin": meta})
        buffer = io.BytesIO()
        pq.write_table(arrow, buffer)
        data = buffer.getvalue()
        if isinstance(damage, tuple):
            at = int(damage[0] * len(data))
            data = data[:at] + damage[1] + data[at + len(damage[1]) :]
        elif damage is not None:
            data = data[: int(damage * len(data))]
        path.write_bytes(data)
        read_outcome(path)

    run()


# --------------------------------------------------------------------------- #
# Scenario / configuration TOML loaders
# --------------------------------------------------------------------------- #
toml_scalars = st.one_of(
    st.integers(-(10**6), 10**6),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=6),
    st.booleans(),
)
toml_values = st.one_of(
    toml_scalars,
    st.lists(st.lists(toml_scalars, max_size=3), max_size=3),
    st.lists(toml_scalars, max_size=3),
)
scenario_keys = st.sampled_from(
    [
        ("scenario", "duration_min"),
        ("inputs", "atomizer_current_mA"),
        ("inputs", "carrier_flow_sccm"),
        ("inputs", "sheath_flow_sccm"),
        ("initial", "vial_volume_mL"),
        ("truth", "nozzle_deposition_factor"),
        ("measurement", "linewidth_sd_um"),
        ("fault", "kind"),
        ("fault", "onset_min"),
        ("fault", "leak_fraction"),
        ("fault", "generation_fraction"),
        ("fault", "ramp_min"),
        ("scenario", "typo"),
        ("nosuchtable", "x"),
    ]
)


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return json.dumps(value)
    return "[" + ", ".join(_toml_value(v) for v in value) + "]"


@pytest.mark.parametrize("profile", PROFILES)
def test_fuzz_scenario_loader(profile, tmp_path):
    from ajtwin.model.names import INPUT_NAMES
    from ajtwin.model.system import INPUT_LIMITS
    from ajtwin.simulation.scenarios import load_scenario

    path = tmp_path / "fuzz.toml"

    @settings(settings.get_profile(profile))
    @given(
        entries=st.lists(st.tuples(scenario_keys, toml_values), max_size=5),
        raw=st.one_of(st.none(), st.binary(max_size=40)),
        fault=st.sampled_from(["", "none", "nozzle_clog", "carrier_leak", "atomizer_dropout"]),
    )
    def run(entries, raw, fault):
        if raw is not None:
            path.write_bytes(raw)
        else:
            tables: dict = {}
            if fault:
                tables.setdefault("fault", {})["kind"] = fault
            for (table, key), value in entries:
                tables.setdefault(table, {})[key] = value
            text = "\n".join(
                f"[{table}]\n" + "\n".join(f"{k} = {_toml_value(v)}" for k, v in keys.items())
                for table, keys in tables.items()
            )
            path.write_text(text + "\n")
        try:
            scenario = load_scenario(path)
        except FileNotFoundError:
            raise
        except ValueError as exc:  # InputFileError is one
            assert str(path) in str(exc), f"error does not name the file: {exc}"
            OUTCOMES["error: " + _kind_of(str(exc), path)] += 1
            return
        OUTCOMES["valid scenario"] += 1
        u = scenario.setpoints(30)
        assert np.all(np.isfinite(u))
        for i, name in enumerate(INPUT_NAMES):
            low, high = INPUT_LIMITS[name]
            assert np.all((u[:, i] > low) & (u[:, i] <= high))
        assert scenario.duration_s >= 1

    run()


@pytest.mark.parametrize("profile", PROFILES)
def test_fuzz_alias_file(profile, tmp_path):
    from ajtwin.io.records import load_aliases

    path = tmp_path / "aliases.toml"

    @settings(settings.get_profile(profile))
    @given(
        body=st.one_of(
            st.binary(max_size=40),
            st.dictionaries(
                st.sampled_from(["linewidth_um", "Q", "time_s", "overspray_um"]),
                toml_values,
                max_size=3,
            ).map(
                lambda d: "[aliases]\n" + "\n".join(f"{k} = {_toml_value(v)}" for k, v in d.items())
            ),  # fmt: skip
        )
    )
    def run(body):
        path.write_bytes(body if isinstance(body, bytes) else body.encode())
        try:
            mapping = load_aliases(path)
        except ValueError as exc:
            assert "alias" in str(exc) or str(path) in str(exc), str(exc)
            return
        assert all(isinstance(k, str) and isinstance(v, str) for k, v in mapping.items())

    run()


# --------------------------------------------------------------------------- #
# The CLI's option parsing (click's CliRunner / make_context: parsing and callbacks only)
# --------------------------------------------------------------------------- #
number_text = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(10**12), 10**12).map(str),
    st.sampled_from(["nan", "inf", "-inf", "1e300", "-0", "0", "", "abc", "1e-300", "３"]),
    st.text(max_size=5),
)


@pytest.mark.parametrize("profile", PROFILES)
def test_fuzz_estimate_options(profile, tmp_path):
    from ajtwin import units
    from ajtwin.cli.estimate import estimate
    from ajtwin.model import load_parameters

    record = tmp_path / "p.csv"
    base_table(5, 0).to_csv(record, index=False)
    capacity = units.m3_to_ml(load_parameters().vial_volume)

    @settings(settings.get_profile(profile))
    @given(
        options=st.dictionaries(
            st.sampled_from(["--gate", "--vial-ml", "--window", "--every", "--noise"]),
            number_text,
            max_size=4,
        )
    )
    def run(options):
        argv = [str(record), "--out", str(tmp_path / "s.csv")]
        for key, value in options.items():
            argv += [key, value]
        try:
            ctx = estimate.make_context("estimate", argv)
        except click.exceptions.UsageError as exc:  # BadParameter is one
            assert exc.exit_code == 2
            OUTCOMES["usage error"] += 1
            return
        OUTCOMES["parsed"] += 1
        p = ctx.params
        assert p["gate"] > 0 and not math.isnan(p["gate"])
        assert 0 < p["vial_ml"] < capacity and math.isfinite(p["vial_ml"])
        assert p["window"] >= 2 and p["every"] >= 1
        assert p["noise_tuning"] in ("calibrated", "paper")

    run()


@pytest.mark.parametrize("profile", PROFILES)
def test_fuzz_every_command_parses_or_says_usage(profile):
    """Any argv to any subcommand: parsed, or a click usage error — never another exception."""
    from ajtwin.cli import main

    names = ["simulate", "estimate", "render", "extract", "ingest", "forecast", "advise", "plot"]

    @settings(settings.get_profile(profile))
    @given(
        name=st.sampled_from(names),
        argv=st.lists(
            st.one_of(
                number_text,
                st.sampled_from(
                    [
                        "--out",
                        "--seed",
                        "--duration-min",
                        "--gate",
                        "--vial-ml",
                        "--um-per-px",
                        "--fps",
                        "--size",
                        "--help",
                        "--",
                        "-x",
                        "--noise",
                        "--blur",
                        "--tilt",
                        "--start-offset",
                        "--camera-offset",
                        "--platen-speed",
                        "--duration",
                    ]
                ),  # fmt: skip
            ),
            max_size=6,
        ),
    )
    def run(name, argv):
        # a shell cannot pass a NUL byte (argv strings end at one); click's own path check
        # raises ValueError on it, which no user can reach
        argv = [a.replace("\x00", "") for a in argv]
        command = main.get_command(None, name)
        if "--help" in argv:
            return  # prints and exits: not parsing
        try:
            ctx = command.make_context(name, list(argv))
        except (click.exceptions.UsageError, click.exceptions.Exit):
            OUTCOMES["usage error"] += 1
            return
        OUTCOMES["parsed"] += 1
        for key, value in ctx.params.items():  # no NaN or inf reaches a command (but --gate inf)
            if isinstance(value, float) and not (key == "gate" and value == math.inf):
                assert math.isfinite(value), (name, key, value)

    run()


# --------------------------------------------------------------------------- #
# Metadata validation directly (cheap: many inputs)
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("profile", PROFILES)
def test_fuzz_validate_meta(profile):
    @settings(settings.get_profile(profile))
    @given(meta=meta_values)
    def run(meta):
        try:
            checked = validate_meta(meta, "m.json")
        except RecordError as exc:
            assert str(exc).startswith("m.json: ")
            return
        speed = checked.get("platen_speed_mm_s", 1.0)
        assert isinstance(speed, int | float) and 0 < speed <= 1000
        assert checked.get("seed") is None or type(checked["seed"]) is int
        json.dumps(checked)  # storable

    run()


# --------------------------------------------------------------------------- #
# Corpus: inputs that once failed (kept as explicit regression cases)
# --------------------------------------------------------------------------- #
def _corpus_files():
    return sorted(p for p in CORPUS.iterdir() if p.suffix in (".csv", ".parquet", ".toml"))


@pytest.mark.parametrize("path", _corpus_files(), ids=lambda p: p.name)
def test_corpus(path, tmp_path):
    """Each file was once a failure (see fuzz_corpus/README.md): now valid or a clear error."""
    expected = json.loads((CORPUS / "expected.json").read_text())[path.name]
    copy = tmp_path / path.name
    copy.write_bytes(path.read_bytes())
    if path.suffix == ".toml":
        from ajtwin.simulation.scenarios import load_scenario

        try:
            load_scenario(copy)
            outcome, text = "ok", ""
        except ValueError as exc:
            assert str(copy) in str(exc)
            outcome, text = "error", str(exc)
    else:
        result = read_outcome(copy)
        outcome, text = result[0], result[1] if result[0] == "error" else ""
    assert outcome == expected["outcome"], text
    assert expected.get("message", "") in text


FLOAT_OPTIONS = {
    "render": (["--out", "r.avi"], ["--fps", "--um-per-px", "--tilt", "--noise", "--blur",
                                    "--raggedness", "--linewidth", "--overspray", "--area",
                                    "--duration", "--start", "--platen-speed"]),
    "extract": (["src.avi", "--um-per-px", "0.75", "--out", "f.csv"],
                ["--um-per-px", "--fps", "--start-offset", "--camera-offset", "--platen-speed"]),
    "simulate": (["--scenario", "exp1", "--out", "x.parquet"], ["--duration-min"]),
    "estimate": (None, ["--gate", "--vial-ml"]),
}  # fmt: skip


@pytest.mark.parametrize("profile", PROFILES)
def test_fuzz_float_options_never_pass_nan_or_inf(profile, tmp_path):
    """Commands with their required arguments and any float option text: the value that
    reaches the command is finite (and in its range), or the parse is a usage error."""
    from ajtwin.cli import main

    record = tmp_path / "p.csv"
    base_table(5, 0).to_csv(record, index=False)
    commands = dict(FLOAT_OPTIONS)
    commands["estimate"] = ([str(record), "--out", "s.csv"], FLOAT_OPTIONS["estimate"][1])

    @settings(settings.get_profile(profile))
    @given(data=st.data(), name=st.sampled_from(sorted(commands)))
    def run(data, name):
        base, options = commands[name]
        chosen = data.draw(st.dictionaries(st.sampled_from(options), number_text, max_size=3))
        argv = list(base)
        for key, value in chosen.items():
            argv += [key, value.replace("\x00", "")]  # a shell cannot pass NUL
        try:
            ctx = main.get_command(None, name).make_context(name, argv)
        except click.exceptions.UsageError:
            OUTCOMES["usage error"] += 1
            return
        OUTCOMES["parsed"] += 1
        for key, value in ctx.params.items():
            if isinstance(value, float) and not (key == "gate" and value == math.inf):
                assert math.isfinite(value), (name, key, value)

    run()
