"""Figures and the self-contained HTML report of the demo (PNG figures embedded as base64)."""

from __future__ import annotations

import base64
import html
import io

import numpy as np

from ajtwin import units
from ajtwin.apps.detection.settings import cusum_thresholds
from ajtwin.estimation.plotting import OUTPUT_LABELS, OUTPUT_SCALE, STATE_LABELS, STATE_SCALE


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def figure_png(fig) -> bytes:
    """A matplotlib figure as PNG bytes (the figure is closed)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    _plt().close(fig)
    return buf.getvalue()


def img_tag(png: bytes, alt: str) -> str:
    """An ``<img>`` with the PNG embedded (base64)."""
    data = base64.b64encode(png).decode()
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def _marks(ax, onset_s, events):
    """The true fault onset (dashed) and the alarms (red) on a print-time axis [min]."""
    if onset_s is not None:
        ax.axvline(units.print_minutes(onset_s), color="k", ls="--", lw=1)
    for ev in events:
        ax.axvline(units.print_minutes(ev.detected_s), color="tab:red", lw=1.2)


def _print_columns(prints, title):
    """A figure of five rows (one per quantity) and one column per print, each on its own
    print time (minutes past that print's start) — the Detectors figure's time base."""
    plt = _plt()
    widths = [max(float(np.asarray(p["time_s"])[-1]), 60.0) for p in prints]
    fig, axes = plt.subplots(
        5, len(prints), figsize=(11, 11), sharey="row", squeeze=False,
        gridspec_kw={"width_ratios": widths},
    )  # fmt: skip
    for column, p in enumerate(prints):
        axes[0, column].set_title(p["label"], fontsize=9)
        axes[-1, column].set_xlabel("print time [min]")
    fig.suptitle(title)
    return fig, axes


def _dress(ax, p, label) -> None:
    """One panel's label (first column only), the print's onset and alarms, the grid."""
    if label:
        ax.set_ylabel(label)
    _marks(ax, p.get("fault_onset_s"), p["events"])
    ax.grid(alpha=0.3)


def _finished(fig, axes) -> bytes:
    """The legend, the layout, the PNG."""
    axes[0, 0].legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    return figure_png(fig)


def outputs_figure(prints, fault_onset_s=None) -> bytes:
    """Measured vs one-step predicted outputs, one column per print, in print time.

    ``prints``: list of dicts with time_s, measured (T,5), predicted (T,5), events, label.
    """
    fig, axes = _print_columns(
        prints, "Outputs: measured vs twin; dashed = true fault onset, red = alarm"
    )
    for column, p in enumerate(prints):
        t = units.print_minutes(np.asarray(p["time_s"], dtype=float))
        for i in range(5):
            ax = axes[i, column]
            y = np.asarray(p["measured"])[:, i] * OUTPUT_SCALE[i]
            ok = np.isfinite(y)
            first = column == 0
            ax.plot(t[ok], y[ok], ".", ms=2, color="0.55", label="measured" if first else None)
            ax.plot(
                t,
                np.asarray(p["predicted"])[:, i] * OUTPUT_SCALE[i],
                lw=1.2,
                color="tab:blue",
                label="twin (one-step prediction)" if first else None,
            )
            _dress(ax, p, OUTPUT_LABELS[i] if first else None)
    return _finished(fig, axes)


def states_figure(prints) -> bytes:
    """Estimated states ±2σ (and the virtual printer's truth), one column per print, in
    print time."""
    fig, axes = _print_columns(prints, "Hidden states: twin estimate vs truth")
    for column, p in enumerate(prints):
        t = units.print_minutes(np.asarray(p["time_s"], dtype=float))
        m, s = np.asarray(p["means"]) * STATE_SCALE, np.asarray(p["stds"]) * STATE_SCALE
        first = column == 0
        for i in range(5):
            ax = axes[i, column]
            ax.fill_between(
                t,
                m[:, i] - 2 * s[:, i],
                m[:, i] + 2 * s[:, i],
                alpha=0.25,
                color="tab:blue",
                label="twin ±2σ" if first else None,
            )
            ax.plot(t, m[:, i], lw=1.2, color="tab:blue")
            if p.get("truth") is not None:
                ax.plot(
                    t,
                    np.asarray(p["truth"])[:, i] * STATE_SCALE[i],
                    lw=1,
                    color="k",
                    ls=":",
                    label="truth (virtual printer)" if first else None,
                )
            _dress(ax, p, STATE_LABELS[i] if first else None)
    return _finished(fig, axes)


def detectors_figure(detection, fault_onset_s=None) -> bytes:
    """Normalised innovations, CUSUM statistics and windowed-NIS over a print, with the onset and
    alarms."""
    plt = _plt()
    fig, axes = plt.subplots(3, 1, figsize=(10, 7), sharex=True)
    t = detection.time_s / 60
    e = detection.normalised_innovations
    for i, name in enumerate(("L_w", "L_o", "P_c", "P_s", "Q_m")):
        ok = np.isfinite(e[:, i])
        axes[0].plot(t[ok], e[ok, i], lw=0.6, label=name)
    axes[0].set_ylabel("normalised\ninnovation [σ]")
    axes[0].set_ylim(-8, 8)
    # each channel over its own decision interval h: an alarm where a line crosses ±1
    h = cusum_thresholds(detection.settings)
    for i, name in enumerate(("L_w", "L_o", "P_c", "P_s", "Q_m", "P_c+P_s")):
        g = (detection.cusum_pos[:, i] - detection.cusum_neg[:, i]) / h[i]
        axes[1].plot(t, g, lw=1, label=name)
    axes[1].axhline(1.0, color="tab:red", ls=":")
    axes[1].axhline(-1.0, color="tab:red", ls=":")
    axes[1].set_ylabel("CUSUM (g⁺ − g⁻) / h")
    axes[2].semilogy(t, np.maximum(detection.window_nis_p, 1e-300), lw=1)
    axes[2].axhline(detection.settings.nis_alpha, color="tab:red", ls=":")
    axes[2].set_ylabel(f"windowed NIS\np ({detection.settings.nis_window_s} s)")
    axes[2].set_xlabel("print time [min]")
    for ax in axes:
        _marks(ax, fault_onset_s, detection.events)
        ax.grid(alpha=0.3)
    axes[0].legend(ncol=5, fontsize=8, loc="upper left")
    axes[1].legend(ncol=6, fontsize=8, loc="upper left")
    fig.suptitle("Anomaly detectors on the twin's innovations")
    fig.tight_layout()
    return figure_png(fig)


def forecast_figure(fc, title) -> bytes:
    """The four outputs' forecast ± 2σ."""
    plt = _plt()
    fig, axes = plt.subplots(2, 2, figsize=(10, 6), sharex=True)
    t = fc.time_s / 60
    for i, ax in enumerate(axes.ravel()):
        mu, sd = fc.output_means[:, i] * OUTPUT_SCALE[i], fc.output_stds[:, i] * OUTPUT_SCALE[i]
        ax.fill_between(t, mu - 2 * sd, mu + 2 * sd, alpha=0.3, label="±2σ")
        ax.plot(t, mu, lw=1.5, label="forecast")
        ax.set_ylabel(OUTPUT_LABELS[i])
        ax.grid(alpha=0.3)
    axes[1, 0].set_xlabel("minutes from the end of the print")
    axes[1, 1].set_xlabel("minutes from the end of the print")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return figure_png(fig)


def frame_png(bgr) -> bytes:
    """A BGR video frame as PNG bytes."""
    import cv2

    ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise RuntimeError("could not encode a video frame as PNG")
    return buf.tobytes()


def table_html(header, rows) -> str:
    """An HTML table (cells escaped)."""
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


CSS = """
body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;color:#222;line-height:1.4}
img{max-width:100%;border:1px solid #ddd;margin:0.5em 0}
table{border-collapse:collapse;margin:0.5em 0;font-size:0.9em}
td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}
th{background:#f3f3f3} .note{color:#555;font-size:0.9em} h2{margin-top:1.6em}
.alarm{color:#b00;font-weight:bold}
"""


def html_page(title: str, sections: list[tuple[str, str]]) -> str:
    """One self-contained HTML page: a title and (heading, HTML) sections."""
    parts = [
        f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
    ]
    parts.append(f"<style>{CSS}</style></head><body><h1>{html.escape(title)}</h1>")
    for heading, body in sections:
        if heading:
            parts.append(f"<h2>{html.escape(heading)}</h2>")
        parts.append(body)
    parts.append("</body></html>")
    return "\n".join(parts)


def mismatch_html(statuses) -> str:
    """The model–machine fit of each print: ``[(label, mismatch status dict), ...]``."""
    rows = []
    for label, status in statuses:
        if not status:
            rows.append([label, "not checked", "–"])
        elif status.get("mismatch"):
            rows.append(
                [label, f"MISMATCH from {status['first_s']:.0f} s", "; ".join(status["fixes"])]
            )
        else:
            rows.append([label, "fits", "–"])
    return table_html(["print", "model–machine fit", "likely fix"], rows)
