"""ajtwin — a digital twin of Aerosol Jet (AJ) printers.

Areas (model reference §2): :mod:`ajtwin.model` (physics macro-model f, g),
:mod:`ajtwin.estimation` (initial fit, EKF, RTS, EM), :mod:`ajtwin.simulation`
(virtual printer, forecasts), :mod:`ajtwin.vision`, :mod:`ajtwin.profile_cnn`,
:mod:`ajtwin.cfd`, :mod:`ajtwin.apps`, :mod:`ajtwin.io`, :mod:`ajtwin.store`.
"""

__version__ = "0.1.0"
