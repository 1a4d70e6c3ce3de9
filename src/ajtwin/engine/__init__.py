"""The glue: wires read → twin → detectors → store → publish for a finished print, a live
machine and a reprocessing task; computes nothing itself (no physics, no filtering).

The contract
------------
- Every estimate comes from the one twin core, :class:`ajtwin.estimation.online.OnlineTwin`
  (batch through :meth:`ajtwin.estimation.Twin.run`, live through :class:`~.stream.TwinStream`);
  every verdict from the apps (:mod:`ajtwin.apps.detection`, :mod:`ajtwin.apps.quality`,
  :mod:`ajtwin.apps.planning`); every row kept through :mod:`ajtwin.store`.
- Engine imports no JAX, no filter and no model internals (only :mod:`ajtwin.model.names`
  and :mod:`ajtwin.model.limits`); ``tests/test_layers.py`` holds it to that.
- What it publishes is typed: :mod:`.messages` (``StepMessage``, ``LinkMessage``,
  ``FinishedMessage``), each with ``to_dict`` / ``from_dict`` for the wire and the store.

The modules
-----------
A finished print: :mod:`.ingest` (one transaction per print), :mod:`.estimate`
(``ajtwin estimate``), :mod:`.video` (the camera's readings joined to a record),
:mod:`.print_job` and :mod:`.job_samples` (the job a print ran), :mod:`.start` and
:mod:`.chain` (where the next print starts), :mod:`.commissioning`, :mod:`.parts` (the
per-second arrays stored as they come).

A live machine: :mod:`.stream` (one machine), :mod:`.fleet` (many in one process),
:mod:`.part_live` (a live part map), :mod:`.control` (a print under the MPC),
:mod:`.replay` (a virtual print as a live feed), :mod:`.views` (what the dashboard reads).

Many prints: :mod:`.reprocess` (the twin re-run over stored prints on Dask).
"""
