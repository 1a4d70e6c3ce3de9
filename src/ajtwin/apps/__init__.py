"""Applications of the twin: detection (:mod:`ajtwin.apps.detection`) and planning
(:mod:`ajtwin.apps.planning`)."""
