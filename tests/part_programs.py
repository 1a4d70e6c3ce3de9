"""Small AJ programs (ACSPL+ text) for the camera-on-parts tests: strokes, arcs, parts.

Each returns program text in the public programs' dialect: rapids with the shutter closed,
``OUT0.0`` switching the shutter, ``MSEG … ENDS`` paths with ``till`` before the shutter
closes. :func:`park` ends a program by moving the stage (shutter closed) to a point and
waiting there, so frames taken after the print look at that point of the part.
"""

from __future__ import annotations

import math


def stroke(x0, y0, x1, y1) -> str:
    """A straight printed stroke from (x0, y0) to (x1, y1) mm (rapid to its start first)."""
    return f"ptp/e (X,Y),{x0:.6f},{y0:.6f}\nOUT0.0=1\nptp/e (X,Y),{x1:.6f},{y1:.6f}\nOUT0.0=0\n"


def path(x0, y0, *moves) -> str:
    """A printed path: ``("line", x, y)`` and ``("arc", cx, cy, sweep_rad)`` moves."""
    lines = [f"ptp/e (X,Y),{x0:.6f},{y0:.6f}", "OUT0.0=1", f"MSEG (X,Y),{x0:.6f},{y0:.6f}"]
    for move in moves:
        if move[0] == "line":
            lines.append(f"line (X,Y),{move[1]:.6f},{move[2]:.6f}")
        else:
            lines.append(f"arc2 (X,Y),{move[1]:.6f},{move[2]:.6f},{move[3]:.12f}")
    lines += ["ENDS (X,Y)", "till ^X_AST.#MOVE", "OUT0.0=0"]
    return "\n".join(lines) + "\n"


def travel(x0, y0, *moves) -> str:
    """The same motion as :func:`path` with the shutter closed (an inspection pass)."""
    lines = [f"ptp/e (X,Y),{x0:.6f},{y0:.6f}", f"MSEG (X,Y),{x0:.6f},{y0:.6f}"]
    for move in moves:
        if move[0] == "line":
            lines.append(f"line (X,Y),{move[1]:.6f},{move[2]:.6f}")
        else:
            lines.append(f"arc2 (X,Y),{move[1]:.6f},{move[2]:.6f},{move[3]:.12f}")
    lines += ["ENDS (X,Y)", "till ^X_AST.#MOVE"]
    return "\n".join(lines) + "\n"


def park(x, y, wait_ms=2000) -> str:
    """Move (shutter closed) to (x, y) and stay there ``wait_ms``."""
    return f"ptp/e (X,Y),{x:.6f},{y:.6f}\nwait {int(wait_ms)}\n"


def angled_line(angle_deg: float, length_mm: float = 1.5) -> tuple[str, tuple]:
    """A straight stroke at an angle through the origin's side, then an inspection pass.

    Returns the program and the inspection pass's ``(start_s_fraction, ...)`` are not
    needed: frames taken during the pass (the second half of the job) see the finished
    stroke centred in view.
    """
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    x1, y1 = length_mm * c, length_mm * s
    return stroke(0, 0, x1, y1) + travel(x1, y1, ("line", 0.0, 0.0))


def arc_and_pass(radius_mm: float) -> str:
    """A printed half circle of ``radius_mm`` (counter-clockwise), then an inspection pass."""
    top = 2 * radius_mm
    return path(0, 0, ("arc", 0.0, radius_mm, math.pi)) + travel(
        0, top, ("arc", 0.0, radius_mm, -math.pi)
    )


def serpentine(x0, y0, legs: int, leg_mm: float, pitch_mm: float) -> str:
    """A filled area: vertical legs ``pitch_mm`` apart joined by half-circle U-turns (the
    public Nafion programs' fill, drawn as two quarter arcs like theirs)."""
    r = 0.5 * pitch_mm
    moves = []
    x, y = x0, y0
    for k in range(legs):
        up = k % 2 == 0
        y = y0 + leg_mm if up else y0
        moves.append(("line", x, y))
        if k < legs - 1:
            sweep = -math.pi / 2 if up else math.pi / 2
            moves += [("arc", x + r, y, sweep), ("arc", x + r, y, sweep)]
            x += pitch_mm
    return path(x0, y0, *moves)


def job_print_table(job, linewidth_um, overspray_um, *, duration_s=None):
    """A job print's 1 Hz table (record format 2 columns) with the given per-second truth.

    ``linewidth_um``/``overspray_um``: a number or a function of the second's start time.
    Rows carry constant nominal inputs and pressures, no camera measurement, the shutter
    state and platen speed at t_k, and the truth of the line printed at t_k (NaN while the
    shutter is closed), as the virtual printer's job print does.
    """
    import numpy as np
    import pandas as pd

    n = int(math.ceil(job.duration_s if duration_s is None else duration_s)) + 1
    t = np.arange(n, dtype=float)
    state = job.state_at(t)
    lw = np.array([linewidth_um(v) if callable(linewidth_um) else linewidth_um for v in t])
    ov = np.array([overspray_um(v) if callable(overspray_um) else overspray_um for v in t])
    open_ = state.shutter_open
    return pd.DataFrame(
        {
            "time_s": t,
            "atomizer_current_mA": 375.0,
            "carrier_flow_sccm": 23.0,
            "sheath_flow_sccm": 50.0,
            "carrier_pressure_Pa": 5661.0,
            "sheath_pressure_Pa": 5641.0,
            "linewidth_um": np.nan,
            "overspray_um": np.nan,
            "material_flow_mL_s": np.nan,
            "shutter_open": open_.astype(int),
            "platen_speed_mm_s": state.speed_mm_s,
            "true_linewidth_um": np.where(open_, lw, np.nan),
            "true_overspray_um": np.where(open_, ov, np.nan),
        }
    )
