"""Closed-loop control: CPU time of an MPC solve, warm-started and jitted, the way the closed
loop uses it: the twin's filtered states of a 10-min exp1 print (seed 0), one solve per 10-s
control period, each warm-started from the previous plan. CPU time (``time.process_time``)
per solve, so other load on the machine inflates it less than a wall clock would; the
compilation (``MPC.warm_up``) is timed apart."""

from __future__ import annotations

import time

import numpy as np


class MPCSolve:
    """The solves of a 10-min print's control periods (target 65 µm from 375/23/50)."""

    timeout = 600

    def setup_cache(self):
        from ajtwin.apps.planning.mpc import MPC, ControlSettings
        from ajtwin.estimation import Twin
        from ajtwin.simulation import simulate

        twin = Twin.default(em=False)
        settings = ControlSettings.load()
        record = simulate("exp1", seed=0, duration_min=10)
        run = twin.run(record)
        mpc = MPC(twin, settings)
        t0 = time.process_time()
        mpc.warm_up()
        compile_s = time.process_time() - t0
        means, covs = run.means, np.asarray(run.filtered.covariances)
        u = np.array([375.0, 23.0, 50.0])
        solve_ms = []
        for k in range(60, len(record), settings.period_s):
            sol = mpc.solve(means[k], covs[k], twin.theta, u, 65.0)
            u = sol.command
            solve_ms.append(sol.solve_s * 1e3)
        return {"compile_s": compile_s, "solve_ms": np.array(solve_ms)}

    def track_solve_cpu_ms_median(self, figures):
        return float(np.median(figures["solve_ms"]))

    def track_solve_cpu_ms_p95(self, figures):
        return float(np.percentile(figures["solve_ms"], 95))

    def track_solve_cpu_ms_max(self, figures):
        return float(np.max(figures["solve_ms"]))

    def track_compile_cpu_s(self, figures):
        return figures["compile_s"]

    for _method in (track_solve_cpu_ms_median, track_solve_cpu_ms_p95, track_solve_cpu_ms_max):
        _method.unit = "ms"
    track_compile_cpu_s.unit = "s"
    del _method
