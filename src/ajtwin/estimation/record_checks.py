"""Checks of a print record against the model before the twin runs, and what the data sees.

The record reader (:mod:`ajtwin.io.records`) knows columns and plausible ranges; only
here, with the model at hand, can a record be checked against what the machine must
produce and what the filter needs:

* :func:`check_model_inputs` — every second needs all three inputs inside the model's
  range, and a print at least 2 samples; errors name the file, row, time and column.
* :func:`check_output_scales` — the outputs the state barely changes (P_c, P_s, Q_m: set
  by the flows and the aerosol generation at the inputs) must be within a factor
  :data:`MAX_SCALE_RATIO` of the model's value at the record's inputs. A unit slip is a
  factor 60–1000 (Q_m in µL/s is ×1000 and passes any fixed range that admits every
  real printer); a real machine's spread, deposits included, stays well inside ×30.
* :func:`output_responds` — which states each output responds to (what a measured output sees)
  (the output Jacobian, scaled by the state's physical range from
  :class:`~ajtwin.model.limits.StateLimits` and the output's noise σ). A
  machine without a camera logs no L_w/L_o/Q_m: d_a and φ_A are then seen by nothing and
  run on their priors through the model; V_l is never measured (it follows the ink use).

Examples
--------
>>> import numpy as np
>>> try:
...     check_model_inputs(np.array([[375.0, 23.0, np.nan]] * 3), "p.csv")
... except ValueError as exc:
...     print(str(exc)[:57])
p.csv: row 1, column 'sheath_flow_sccm': input is missing
"""

from __future__ import annotations

import numpy as np

from ajtwin._aot import exported_jit
from ajtwin._jax import jax, jnp
from ajtwin.io.records import RecordError
from ajtwin.model import INPUT_NAMES, OUTPUT_NAMES
from ajtwin.model.system import INPUT_LIMITS, output_function, settled_outputs

#: Outputs compared with the model's value at the inputs (index in OUTPUT_NAMES): they
#: do not depend on the droplet size, so the model predicts them from the inputs alone.
SCALE_CHECKED_OUTPUTS = (2, 3, 4)
#: Largest ratio between a record's median output and the model's value at its inputs
#: that is still a machine (not a unit slip, which is ×60 … ×1000).
MAX_SCALE_RATIO = 30.0
#: An output "sees" a state when a change of the state over its whole physical range moves
#: it by at least this many noise σ's (a structural zero — V_l in any output, d_a in the
#: pressures — stays far below; every real dependence is far above).
SEEN_SENSITIVITY = 1.0


def _when(time_s, position: int, first_row: int = 0) -> str:
    if time_s is None:
        return f"row {first_row + position + 1}"
    return f"row {first_row + position + 1} (t = {float(time_s[position]):g} s)"


def check_model_inputs(inputs, where: str = "<record>", time_s=None) -> np.ndarray:
    """Inputs (T, 3) complete and inside the model's range; errors name file, row, column.

    Raises
    ------
    RecordError
        A NaN/inf input, one outside ``INPUT_LIMITS``, or fewer than 2 rows.
    """
    u = np.asarray(inputs, dtype=float)
    if u.ndim != 2 or u.shape[1] != len(INPUT_NAMES):
        raise RecordError(f"{where}: inputs must be a (T, 3) table; got shape {u.shape}")
    check_print_length(len(u), where)
    return check_input_rows(u, where, time_s)


def check_print_length(n: int, where: str = "<record>") -> None:
    """A print needs at least 2 samples (:class:`RecordError` otherwise)."""
    if n < 2:
        raise RecordError(
            f"{where}: the record has {n} row(s); a print needs at least 2 samples (1 s apart)"
        )


def check_input_rows(u, where: str = "<record>", time_s=None, first_row: int = 0) -> np.ndarray:
    """Rows of inputs (m, 3), the print's rows ``first_row`` on: complete and inside the
    model's range (:func:`check_model_inputs` without the print's length; a piece of a
    print at a time)."""
    u = np.asarray(u, dtype=float)
    for i, name in enumerate(INPUT_NAMES):
        column = u[:, i]
        missing = ~np.isfinite(column)
        if missing.any():
            position = int(np.flatnonzero(missing)[0])
            raise RecordError(
                f"{where}: {_when(time_s, position, first_row)}, column {name!r}: input is "
                f"missing ({column[position]!r}); the model needs all three inputs every "
                "second — fill them (e.g. hold the last set-point)"
            )
        low, high = INPUT_LIMITS[name]
        outside = (column <= low) | (column > high)
        if outside.any():
            position = int(np.flatnonzero(outside)[0])
            raise RecordError(
                f"{where}: {_when(time_s, position, first_row)}, column {name!r}: input "
                f"{column[position]:g} is outside the model's range ({low:g}, {high:g}]"
            )
    return u


def check_output_scales(
    params, coefficients, inputs, measurements, vial_fill_ml: float, where: str = "<record>"
) -> None:
    """Refuse a P_c, P_s or Q_m column whose scale is not the machine's (a unit slip).

    The median of each measured output of :data:`SCALE_CHECKED_OUTPUTS` is compared with
    g(x_nom, u_med): x_nom has no deposits and φ_A in balance with the generation at the
    median inputs u_med (d_a does not enter these outputs).

    Raises
    ------
    RecordError
        Naming the file, the column, both values and the ratio.
    """
    y = np.asarray(measurements, dtype=float)
    u_med = np.median(np.asarray(inputs, dtype=float), axis=0)
    medians = {j: finite_median(y[:, j]) for j in SCALE_CHECKED_OUTPUTS}
    check_output_medians(params, coefficients, u_med, medians, vial_fill_ml, where)


def finite_median(values) -> float | None:
    """The median of a column's finite values (None: none measured)."""
    values = np.asarray(values, dtype=float)
    finite = values[np.isfinite(values)]
    return float(np.median(finite)) if finite.size else None


def check_output_medians(
    params, coefficients, u_med, medians: dict, vial_fill_ml: float, where: str = "<record>"
) -> None:
    """:func:`check_output_scales` from the medians: the inputs' ``u_med`` (3,) and each
    output's of :data:`SCALE_CHECKED_OUTPUTS` over its finite values (``medians``: output
    index → median, None when never measured); what a print read a column at a time gives."""
    u_med = np.asarray(u_med, dtype=float)
    _, expected = settled_outputs(u_med, float(vial_fill_ml), params, coefficients)
    expected = np.asarray(expected)
    for j in SCALE_CHECKED_OUTPUTS:
        median = medians.get(j)
        if median is None or not expected[j] > 0:
            continue
        if median <= 0:
            continue  # the reader's ranges refuse negatives; an all-zero column is a dropout
        ratio = median / float(expected[j])
        if not 1.0 / MAX_SCALE_RATIO <= ratio <= MAX_SCALE_RATIO:
            name = OUTPUT_NAMES[j]
            raise RecordError(
                f"{where}: column {name!r}: median {median:.4g} is {ratio:.3g}× what the model "
                f"gives at this record's inputs ({float(expected[j]):.4g}); no machine state "
                f"explains a factor beyond {MAX_SCALE_RATIO:g} — is the column in another unit "
                f"(e.g. µL/s or nL/s for mL/s, hPa or kPa for Pa)?"
            )


def _output_jacobian(x, u, params, coefficients):
    return jax.jacfwd(output_function)(x, u, params, coefficients)


_output_jacobian = exported_jit(_output_jacobian)


def output_responds(params, coefficients, mean, state_range, u, measurement_std) -> np.ndarray:
    """Which state each output responds to: bool (5 outputs, 5 states).

    Output j responds to state i when |∂g_j/∂x_i| Δx_i ≥ :data:`SEEN_SENSITIVITY` σ_y,j,
    with Δx_i the state's physical range (``state_range``, upper − lower of StateLimits), at
    the state ``mean`` and inputs ``u`` (3,) (the output map is smooth over a print, so one
    Jacobian tells the structure). A state is *seen* at a second when some output measured
    then responds to it.
    """
    jac = np.asarray(
        _output_jacobian(jnp.asarray(mean, float), jnp.asarray(u, float), params, coefficients)
    )
    sensitivity = np.abs(jac) * np.asarray(state_range, float)[None, :]
    return sensitivity >= SEEN_SENSITIVITY * np.asarray(measurement_std, float)[:, None]
