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

from ajtwin.apps.quality.part_map import PartMap
from ajtwin.job.plot import plot_part_values

#: flagged portions listed on the page at most (all are in strokes.csv)
MAX_HTML_ROWS = 500

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5em; color: #222; max-width: 1200px; }
h1 { font-size: 1.4em; } h2 { font-size: 1.15em; margin-top: 1.6em; }
table { border-collapse: collapse; font-size: 0.85em; }
th, td { border: 1px solid #ccc; padding: 2px 6px; text-align: right; }
th { background: #f0f0f0; } td.text { text-align: left; }
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
                "label": f"{label} ({row.detected_s / 60:.1f} min)",
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


def _table(frame: pd.DataFrame, text_columns=(), digits: int = 3) -> str:
    """An HTML table of ``frame`` with every value escaped."""
    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in frame.columns)
    rows = []
    for values in frame.itertuples(index=False):
        cells = []
        for column, value in zip(frame.columns, values):
            if isinstance(value, float | np.floating):
                text = "" if not np.isfinite(value) else f"{value:.{digits}g}"
            else:
                text = str(value)
            css = ' class="text"' if column in text_columns else ""
            cells.append(f"<td{css}>{html.escape(text)}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table>"


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
         f"{facts['printed_mm']:.1f} mm"),
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
    alarms = part.alarms.drop(columns=["detected_repetition", "onset_repetition"])
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
<h2>Per feature</h2>
{_table(part.feature_summary(), text_columns=("name",))}
<h2>Flagged portions, most probably out of tolerance first</h2>
{_table(shown[list(_FLAGGED_COLUMNS)]) if len(shown) else "<p>none</p>"}
{more}
<h2>Alarms on the part</h2>
{
        _table(alarms, text_columns=("cause", "description", "detectors"))
        if len(alarms)
        else "<p>none</p>"
    }
<p class="note">L_w and L_o along every stroke from the twin's smoothed states (mean ± 2σ);
a portion's probability of being out of tolerance is that of its worst point. Coordinates in
the program's millimetres; times in seconds from the start of the print.</p>
<script type="application/json" id="facts">{_script_json(facts)}</script>
</body></html>
"""


def _script_json(value) -> str:
    """JSON safe inside a ``<script>`` element (no ``</`` to end it early)."""
    return json.dumps(value).replace("</", "<\\/")


_FLAGGED_COLUMNS = (
    "feature",
    "stroke",
    "portion",
    "repetition",
    "from_x_mm",
    "from_y_mm",
    "to_x_mm",
    "to_y_mm",
    "length_mm",
    "printed_from_s",
    "printed_to_s",
    "lw_mean_um",
    "lw_lo_um",
    "lw_hi_um",
    "p_out",
)


def write_report(part: PartMap, out_dir) -> dict[str, Path]:
    """Write ``strokes.csv``, ``part.png`` and ``report.html`` into ``out_dir`` (created);
    the paths by name."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {name: out / name for name in ("strokes.csv", "part.png", "report.html")}
    part.portions.to_csv(paths["strokes.csv"], index=False, float_format="%.6g")
    plot_part_map(part, paths["part.png"])
    page = report_html(part, paths["part.png"].read_bytes())
    paths["report.html"].write_text(page, encoding="utf-8")
    return paths
