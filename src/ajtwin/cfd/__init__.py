"""CFD macro-model with OpenFOAM v1912 (model reference §8, paper §6.2, App. C–D).

* :mod:`~ajtwin.cfd.geometry` — deposition-head dimensions (``geometry.toml``), ΔR_N.
* :mod:`~ajtwin.cfd.case` — OpenFOAM case generator (axisymmetric wedge, simpleFoam).
* :mod:`~ajtwin.cfd.foam` — running OpenFOAM and reading its ASCII fields.
* :mod:`~ajtwin.cfd.tracker` — droplet tracking on the solved field (Cunningham slip).
* :mod:`~ajtwin.cfd.profile` — landing radii → height profile → L_w, L_o (model reference §8).
* :mod:`~ajtwin.cfd.sweep` — Dask sweep, resumable; designs in ``sweep.toml``.
* :mod:`~ajtwin.cfd.fit` — output-model coefficients and R_3^N(ΔR_N) fits.
* :mod:`~ajtwin.cli.cfd` — ``ajtwin cfd case|run|sweep|fit|report``.
"""
