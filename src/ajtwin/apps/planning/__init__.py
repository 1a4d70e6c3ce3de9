"""Planning: what the inputs will do and which inputs to set.

* :mod:`~ajtwin.apps.planning.forecast` — outputs ± σ under an input schedule.
* :mod:`~ajtwin.apps.planning.advice` — settings that reach a target linewidth.
* :mod:`~ajtwin.apps.planning.mpc` — model-predictive control of linewidth.
* :mod:`~ajtwin.apps.planning.strategies` — open loop, PI and MPC controllers.
* :mod:`~ajtwin.apps.planning.closed_loop` — a controller driving the virtual printer.
"""
