"""Quality: which traces of a part are out of tolerance, and how likely.

* :mod:`~ajtwin.apps.quality.part_map` — the part map of a print: portions, the line the twin
  says was printed there, the probability of being out of tolerance.
* :mod:`~ajtwin.apps.quality.report` — the part report (HTML, a plot, tables).
* :mod:`~ajtwin.apps.quality.live_map` — the part map of a live print, step by step, and what
  the dashboard draws of it.
"""
