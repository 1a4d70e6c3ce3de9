"""The part map's report: ``strokes.csv``, ``part.png`` and a self-contained ``report.html``.

:func:`write_report` writes the three files of ``ajtwin job report`` into a folder. The
HTML page holds everything it shows (the picture as an embedded PNG, tables, style):
nothing is fetched from anywhere when it is opened.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

import numpy as np
import pandas as pd

from ajtwin import units
from ajtwin.apps.detection.causes import cause_action, cause_words, detector_words
from ajtwin.apps.quality.part_map import REPORT_COLUMNS, PartMap, cause_groups
from ajtwin.job.plot import plot_part_values

#: flagged portions listed on the page at most (all are in strokes.csv)
MAX_HTML_ROWS = 500

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5em; color: #222; max-width: 1200px; }
h1 { font-size: 1.4em; } h2 { font-size: 1.15em; margin-top: 1.6em; }
table { border-collapse: collapse; font-size: 0.85em; }
th, td { border: 1px solid #ccc; padding: 2px 6px; text-align: right; }
th { background: #f0f0f0; } td.text, th.text { text-align: left; }
dl { display: grid; grid-template-columns: max-content auto; gap: 2px 12px; }
dt { font-weight: 600; } img { max-width: 100%; border: 1px solid #ddd; }
.flag { color: #a00000; font-weight: 600; } .note { color: #555; }
"""


def _points_for_plot(part: PartMap) -> pd.DataFrame:
    """The map's points with the repetition of their portion (for the drawing)."""
    rep = part.portions["repetition"].to_numpy(dtype=np.int64)
    points = part.points
    return points.assign(repetition=rep[points["portion"].to_numpy(dtype=np.int64)])


def alarm_markers(part: PartMap) -> list[dict]:
    """The alarms as drawing markers: raised (cross) and onset (ring), labelled ``A1`` …"""
    markers = []
    for row in part.alarms.itertuples(index=False):
        label = f"A{row.alarm} {row.cause.replace('_', ' ')}"
        markers.append(
            {
                "x_mm": row.detected_x_mm,
                "y_mm": row.detected_y_mm,
                "repetition": row.detected_repetition,
                "kind": "raised",
                "label": f"{label} ({units.minutes_text(row.detected_s)})",
            }
        )
        markers.append(
            {
                "x_mm": row.onset_x_mm,
                "y_mm": row.onset_y_mm,
                "repetition": row.onset_repetition,
                "kind": "onset",
                "label": f"A{row.alarm} onset",
            }
        )
    return markers


def plot_part_map(part: PartMap, path) -> Path:
    """Draw the part coloured by L_w − target (µm), flagged portions outlined, alarms
    marked (``part.png``)."""
    target = part.tolerance.target_um if part.tolerance else float(np.nanmedian(
        part.points["lw_mean_um"]))  # fmt: skip
    values = part.points["lw_mean_um"].to_numpy(dtype=float) - target
    limit = None
    if part.tolerance is not None:
        limit = 0.5 * (part.tolerance.high_um - part.tolerance.low_um)
    flagged = part.portions["flagged"].to_numpy(dtype=bool)
    what = f"target {target:.4g} µm" if part.tolerance else f"median {target:.4g} µm"
    title = (
        f"{part.program}: L_w − {what}"
        + (f" (tolerance {part.tolerance.text})" if part.tolerance else "")
        + f"; {int(flagged.sum())} of {len(flagged)} portions flagged"
    )
    plot_part_values(
        part.job,
        _points_for_plot(part),
        values,
        path,
        value_label="L_w − target [µm]" if part.tolerance else "L_w − median [µm]",
        limit=limit,
        outlined=flagged,
        markers=alarm_markers(part),
        title=title,
    )
    return Path(path)


def _table(frame: pd.DataFrame, text_columns=()) -> str:
    """An HTML table of ``frame`` (values already formatted as text) with every value
    escaped; numbers not yet formatted are written with :func:`ajtwin.units.readable`."""
    text_class = ' class="text"'
    head = "".join(
        f"<th{text_class if c in text_columns else ''}>{html.escape(str(c))}</th>"
        for c in frame.columns
    )
    rows = []
    for values in frame.itertuples(index=False):
        cells = []
        for column, value in zip(frame.columns, values):
            if isinstance(value, float | np.floating):
                text = units.readable(value)
            else:
                text = str(value)
            css = ' class="text"' if column in text_columns else ""
            cells.append(f"<td{css}>{html.escape(text)}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table>"


def _xy(x, y) -> str:
    """A point of the part, program millimetres to 0.01 mm."""
    return f"({x:.2f}, {y:.2f})"


def flagged_rows(part: PartMap, flagged: pd.DataFrame) -> pd.DataFrame:
    """The flagged portions as the report lists them: run counted from 1 (the map's
    "run N"), times in minutes past the print's start, lengths in mm, the cause."""
    frame = pd.DataFrame(
        {
            "run": (flagged["repetition"].to_numpy(dtype=np.int64) + 1).astype(str),
            "stroke": flagged["stroke"].astype(str).to_numpy(),
            "portion": flagged["portion"].astype(str).to_numpy(),
            "from [mm]": [_xy(x, y) for x, y in zip(flagged["from_x_mm"], flagged["from_y_mm"])],
            "to [mm]": [_xy(x, y) for x, y in zip(flagged["to_x_mm"], flagged["to_y_mm"])],
            "length [mm]": [f"{v:.2f}" for v in flagged["length_mm"]],
            "printed [min]": [f"{units.print_minutes(v):.1f}" for v in flagged["printed_from_s"]],
            "L_w [µm]": [f"{v:.1f}" for v in flagged["lw_mean_um"]],
            "±2σ band [µm]": [
                f"{lo:.1f} – {hi:.1f}" for lo, hi in zip(flagged["lw_lo_um"], flagged["lw_hi_um"])
            ],
            "P(out)": [f"{v:.2f}" for v in flagged["p_out"]],
            "cause": [_cause_cell(row) for row in flagged.itertuples(index=False)],
        }
    )
    if part.has_features:
        frame.insert(0, "feature", [part.feature_label(f) for f in flagged["feature"]])
    if part.job.repetitions <= 1:
        frame = frame.drop(columns=["run"])
    return frame


def _cause_cell(row) -> str:
    """``A1 nozzle clogging`` or ``no alarm``."""
    alarm = int(getattr(row, "alarm", 0) or 0)
    if not alarm:
        return "no alarm"
    return f"A{alarm} {cause_words(row.cause)}"


def alarm_rows(part: PartMap) -> pd.DataFrame:
    """The alarms as the report lists them: cause and action in words, print times in
    minutes, where the nozzle was (mm), the detectors in words."""
    alarms = part.alarms
    return pd.DataFrame(
        {
            "alarm": [f"A{a}" for a in alarms["alarm"]],
            "cause": [cause_words(c) for c in alarms["cause"]],
            "what to do": [cause_action(c, part.machine) for c in alarms["cause"]],
            "onset [min]": [f"{units.print_minutes(v):.1f}" for v in alarms["onset_s"]],
            "raised [min]": [f"{units.print_minutes(v):.1f}" for v in alarms["detected_s"]],
            "raised at [mm]": [
                _xy(x, y) for x, y in zip(alarms["detected_x_mm"], alarms["detected_y_mm"])
            ],
            "detectors": [
                "; ".join(detector_words(d.strip()) for d in str(text).split(",") if d.strip())
                for text in alarms["detectors"]
            ],
        }
    )


def groups_rows(groups: list[dict]) -> pd.DataFrame:
    """The flagged portions' causes as the report lists them (:func:`cause_groups`)."""
    return pd.DataFrame(
        {
            "why": [g["sentence"] for g in groups],
            "what the twin reads": [g["driver"] for g in groups],
            "portions": [str(g["portions"]) for g in groups],
            "length [mm]": [f"{g['length_mm']:.1f}" for g in groups],
            "printed [min]": [f"{g['from_min']:.1f} – {g['to_min']:.1f}" for g in groups],
        }
    )


def summary_facts(part: PartMap) -> dict:
    """The report's headline figures (also printed by ``ajtwin job report``)."""
    table = part.portions
    flagged = table["flagged"].to_numpy(dtype=bool)
    return {
        "program": part.program,
        "print": part.source,
        "tolerance_um": None if part.tolerance is None else list(part.tolerance),
        "flag_probability": part.flag_probability,
        "strokes": int(table["stroke"].nunique()),
        "portions": int(len(table)),
        "printed_mm": float(table["length_mm"].sum()),
        "flagged_portions": int(flagged.sum()),
        "flagged_mm": float(table.loc[flagged, "length_mm"].sum()),
        "flagged_strokes": int(table.loc[flagged, "stroke"].nunique()),
        "lw_mean_um": float(np.average(table["lw_mean_um"], weights=table["length_mm"]))
        if table["length_mm"].sum() > 0
        else float("nan"),
        "alarms": int(len(part.alarms)),
        "speed_law": None if part.speed_exponents is None else part.speed_exponents.describe(),
        "print_min": units.print_minutes(float(table["printed_to_s"].max())) if len(table) else 0.0,
    }


def report_html(part: PartMap, png: bytes) -> str:
    """The self-contained report page (the picture embedded)."""
    facts = summary_facts(part)
    tolerance = part.tolerance.text if part.tolerance else "none given (no portion flagged)"
    dl = [
        ("program", part.program),
        ("print", part.source),
        ("tolerance", tolerance),
        ("flagged when", f"P(L_w outside the tolerance) ≥ {part.flag_probability:g} at the "
         "portion's worst point"),
        ("printed", f"{facts['strokes']} strokes, {facts['portions']} portions, "
         f"{facts['printed_mm']:.1f} mm over {facts['print_min']:.1f} min"),
        ("flagged", f"{facts['flagged_portions']} portions ({facts['flagged_mm']:.1f} mm) on "
         f"{facts['flagged_strokes']} strokes"),
        ("alarms", str(facts["alarms"])),
    ]  # fmt: skip
    if facts["speed_law"]:
        dl.append(("speed law", facts["speed_law"]))
    flagged = part.flagged()
    shown = flagged.head(MAX_HTML_ROWS)
    more = (
        f'<p class="note">{len(flagged) - len(shown)} more flagged portions in strokes.csv.</p>'
        if len(flagged) > len(shown)
        else ""
    )
    groups = cause_groups(part)
    notes = "".join(f'<p class="note">{html.escape(n)}</p>' for n in part.notes)
    image = base64.b64encode(png).decode("ascii")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<title>Part map: {html.escape(part.program)}</title>
<style>{_STYLE}</style></head><body>
<h1>Which traces of this part are out of tolerance?</h1>
<dl>{"".join(f"<dt>{html.escape(k)}</dt><dd>{html.escape(v)}</dd>" for k, v in dl)}</dl>
{notes}
<img alt="the part, traces coloured by the linewidth's deviation from the target"
 src="data:image/png;base64,{image}">
{_feature_section(part)}
<h2>Why they are out</h2>
{
        _table(groups_rows(groups), text_columns=("why", "what the twin reads"))
        if groups
        else "<p>no portion flagged</p>"
    }
<h2>Flagged portions, most probably out of tolerance first</h2>
{
        _table(flagged_rows(part, shown), text_columns=("feature", "cause"))
        if len(shown)
        else "<p>none</p>"
    }
{more}
<h2>Alarms on the part</h2>
{
        _table(alarm_rows(part), text_columns=("cause", "what to do", "detectors"))
        if len(part.alarms)
        else "<p>none</p>"
    }
<p class="note">L_w and L_o along every stroke from the twin's smoothed states (mean ± 2σ);
a portion's probability of being out of tolerance is that of its worst point. Coordinates in
the program's millimetres; times in minutes past the print's start; a looped job's runs are
counted from 1. What the twin reads: the hidden state (or the input settings) whose change
since the first trace moved the linewidth most at the portion.</p>
<script type="application/json" id="facts">{_script_json(facts)}</script>
</body></html>
"""


def _feature_section(part: PartMap) -> str:
    """The per-feature table, or a sentence when the program names no features."""
    if not part.has_features:
        return '<p class="note">The program names no features (no !Feature comments).</p>'
    summary = part.feature_summary().drop(columns=["feature"])
    for column in ("printed_mm", "flagged_mm", "lw_mean_um", "lw_min_um", "lw_max_um"):
        summary[column] = [f"{v:.1f}" for v in summary[column]]
    summary["p_out_max"] = [f"{v:.2f}" if np.isfinite(v) else "–" for v in summary["p_out_max"]]
    return "<h2>Per feature</h2>" + _table(summary, text_columns=("name",))


def _script_json(value) -> str:
    """JSON safe inside a ``<script>`` element (no ``</`` to end it early)."""
    return json.dumps(value).replace("</", "<\\/")


def write_report(part: PartMap, out_dir) -> dict[str, Path]:
    """Write ``strokes.csv``, ``part.png`` and ``report.html`` into ``out_dir`` (created);
    the paths by name."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {name: out / name for name in ("strokes.csv", "part.png", "report.html")}
    table = part.portions[[c for c in REPORT_COLUMNS if c in part.portions.columns]]
    table.to_csv(paths["strokes.csv"], index=False, float_format="%.6g")
    plot_part_map(part, paths["part.png"])
    page = report_html(part, paths["part.png"].read_bytes())
    paths["report.html"].write_text(page, encoding="utf-8")
    return paths
