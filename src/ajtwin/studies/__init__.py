"""Studies: evaluation that is not the product — the paper's experiments, the detector and
control studies, soaks, the accuracy studies of the twin on held-out virtual machines.

Nothing in the library imports this package (the commands that run a study do). Each
study runs as ``python -m ajtwin.studies.<name>`` or through its command.
"""
