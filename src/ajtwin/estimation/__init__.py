"""State and parameter estimation (paper §7, model reference §7): initial fit, EKF, RTS, EM."""

from ajtwin.estimation.em import m_step, run_em
from ajtwin.estimation.filters import (
    DEFAULT_SCALING,
    EKFCarry,
    EKFStepOutput,
    FilterResult,
    ModelSpec,
    Scaling,
    SmootherResult,
    ekf,
    ekf_fleet,
    ekf_fleet_threaded,
    ekf_init,
    ekf_step,
    rts_smoother,
)
from ajtwin.estimation.initial import InitialFit, fit_initial_state
from ajtwin.estimation.twin import Twin, TwinConfig, TwinRun

__all__ = [
    "ekf",
    "ekf_fleet",
    "ekf_fleet_threaded",
    "ekf_step",
    "ekf_init",
    "EKFCarry",
    "EKFStepOutput",
    "rts_smoother",
    "run_em",
    "m_step",
    "fit_initial_state",
    "Twin",
    "TwinConfig",
    "TwinRun",
    "ModelSpec",
    "Scaling",
    "DEFAULT_SCALING",
    "FilterResult",
    "SmootherResult",
    "InitialFit",
]
