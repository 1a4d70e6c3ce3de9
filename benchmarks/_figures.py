"""Figures measured once per benchmark run, as asv ``track_*`` benchmarks.

A measurement that yields several figures at once (latency percentiles of one live print,
a page's load times) runs in the class's ``setup_cache``, which returns them as a dict;
:func:`tracked` gives the class a ``track_<name>`` benchmark per figure.
"""

from __future__ import annotations


def tracked(units: dict[str, str]):
    """Class decorator: ``track_<name>`` returning ``figures[name]`` for each name of ``units``
    (name → unit), ``figures`` being what the class's ``setup_cache`` returned."""

    def decorate(cls):
        for name, unit in units.items():

            def track(self, figures, name=name):
                return figures[name]

            track.__name__ = f"track_{name}"
            track.unit = unit
            setattr(cls, track.__name__, track)
        return cls

    return decorate
