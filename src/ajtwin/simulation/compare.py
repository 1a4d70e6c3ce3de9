"""How a virtual print's truth differs from the nominal digital model.

:func:`difference_from_nominal` runs the nominal model open loop (θ = 0, Euler at 1 s)
from the print's *true* initial state with its measured inputs, and reports truth minus
nominal; :func:`scenario_table` does it over scenarios and seeds (docs/reference/scenarios.md).

Examples
--------
>>> from ajtwin.simulation import run_virtual_print
>>> d = difference_from_nominal(run_virtual_print("exp1", seed=0, duration_min=10))
>>> sorted(d)[:3]
['L_o_um', 'L_w_um', 'P_c_Pa']
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from ajtwin.model import DigitalModel
from ajtwin.simulation.printer import run_virtual_print
from ajtwin.simulation.scenarios import list_scenarios
from ajtwin.units import um_to_nm


def difference_from_nominal(virtual_print, last_s: int = 300) -> dict:
    """Truth minus nominal open loop, averaged over the last ``last_s`` seconds.

    Returns
    -------
    dict
        ``d_a_um``, ``phi_A_percent``, ``V_l_mL``, ``dR_N_nm`` (states, truth − nominal),
        ``L_w_um``, ``L_o_um``, ``P_c_Pa``, ``Q_m_percent`` (measured − nominal outputs),
        ``rms_L_w_um`` (measured − nominal L_w over the whole print).
    """

    model = DigitalModel.default()
    record = virtual_print.record
    x = virtual_print.states
    u = record.inputs
    nominal = model.simulate(x[0], u[:-1])
    y_nominal = model.outputs(nominal, u)
    y = record.outputs
    last = slice(-last_s, None)
    return {
        "d_a_um": x[last, 0].mean() - nominal[last, 0].mean(),
        "phi_A_percent": 100 * (x[last, 4].mean() / nominal[last, 4].mean() - 1),
        "V_l_mL": x[-1, 1] - nominal[-1, 1],
        "dR_N_nm": um_to_nm(x[-1, 3] - nominal[-1, 3]),
        "L_w_um": np.nanmean(y[last, 0]) - y_nominal[last, 0].mean(),
        "L_o_um": np.nanmean(y[last, 1]) - y_nominal[last, 1].mean(),
        "P_c_Pa": np.nanmean(y[last, 2]) - y_nominal[last, 2].mean(),
        "Q_m_percent": 100 * (np.nanmean(y[last, 4]) / y_nominal[last, 4].mean() - 1),
        "rms_L_w_um": float(np.sqrt(np.nanmean((y[:, 0] - y_nominal[:, 0]) ** 2))),
    }


def scenario_table(scenarios=None, seeds=range(5)):
    """A pandas table: per scenario, mean/min/max over seeds of :func:`difference_from_nominal`."""

    rows = []
    for name in scenarios or list_scenarios():
        for seed in seeds:
            rows.append(
                {
                    "scenario": name,
                    "seed": seed,
                    **difference_from_nominal(run_virtual_print(name, seed)),
                }
            )
    frame = pd.DataFrame(rows).drop(columns="seed")
    return frame.groupby("scenario").agg(["mean", "min", "max"])


if __name__ == "__main__":
    import pandas as pd

    with pd.option_context("display.width", 250, "display.max_columns", 40, "display.precision", 3):
        print(scenario_table())
