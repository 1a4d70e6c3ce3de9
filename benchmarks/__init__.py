"""ajtwin's speed benchmarks, run by asv (``asv.conf.json``; ``make bench``).

Each module holds asv classes: ``time_*`` (wall time, asv repeats and keeps the
statistics), ``peakmem_*`` (peak resident memory) and ``track_*`` (a figure the benchmark
computes itself: a ratio, a throughput). Accuracy is not measured here: the studies
(``python -m ajtwin.studies.…``) do that.
"""
