"""Click options and small functions shared by the commands: the registry option, bounded numbers,
the record-reading and video-join options, logging."""

from __future__ import annotations

import functools
import logging
import math
from pathlib import Path

import click
import numpy as np

from ajtwin import units
from ajtwin.config import packaged_toml
from ajtwin.io.dialect import DIALECT_CHOICES
from ajtwin.model.names import INPUT_NAMES, STATE_NAMES
from ajtwin.store.location import PASSWORD_FILE_ENV, parse_store


def csv_dialect_option(command):
    """``--csv-dialect``: how a record CSV writes its table (default: detected)."""
    return click.option(
        "--csv-dialect",
        "csv_dialect",
        type=click.Choice(DIALECT_CHOICES, case_sensitive=False),
        default="auto",
        show_default=True,
        help="Separator and decimal mark of a CSV/TSV record: 'auto' detects them "
        "(and says so when the file is ambiguous); e.g. semicolon-decimal-comma for a "
        "European spreadsheet export (5.741,6), tab for a .tsv.",
    )(command)


def aliases_option(command):
    """``--aliases``: the user's column-alias TOML file."""
    return click.option(
        "--aliases",
        type=click.Path(exists=True, dir_okay=False, path_type=Path),
        default=None,
        help="Extra column-alias TOML file for a machine log (docs/reference/record-format.md).",
    )(command)


def record_options(command):
    """``--csv-dialect`` and ``--aliases`` for a command that reads a print record."""
    return csv_dialect_option(aliases_option(command))


def switched_on_option(command):
    """``--switched-on``: when the record's atomizer was switched on (its run-in begins)."""
    return click.option(
        "--switched-on",
        "switched_on_s",
        type=click.FloatRange(min=0.0),
        default=None,
        metavar="SECONDS",
        help="The atomizer was switched on this many seconds into the record (0: as it "
        "starts): until the twin says ready to print, the run-in is a known phase, not a fault "
        "or a misfit. Overrides the record's atomizer_switched_on_s; without either, a "
        "switch-on shows only as a current rising through 50 mA.",
    )(command)


def join_options(filled: str, suffix: str, must_exist: bool = False):
    """``--join/--join-out/--start-offset/--camera-offset/--csv-dialect`` for a video reader.

    Parameters
    ----------
    filled : str
        The record columns the join fills (for the help text).
    suffix : str
        Default output name: ``RECORD_<suffix>.parquet``.
    must_exist : bool
        Let click reject a missing ``--join`` record before the command starts.
    """
    options = [
        click.option(
            "--join",
            "join_record",
            type=click.Path(exists=must_exist, dir_okay=False, path_type=Path),
            default=None,
            help=f"Print record whose {filled} to fill.",
        ),
        click.option(
            "--join-out",
            type=click.Path(dir_okay=False, path_type=Path),
            default=None,
            help=f"Where to write the joined record (default: RECORD_{suffix}.parquet).",
        ),
        click.option(
            "--start-offset",
            "start_offset_s",
            type=BoundedFloat(),
            default=0.0,
            show_default=True,
            help="Print time (s) of the first video frame.",
        ),
        click.option(
            "--camera-offset",
            "camera_offset_um",
            type=BoundedFloat(),
            default=0.0,
            show_default=True,
            help="Distance from nozzle to the camera's view centre along the print, µm.",
        ),
    ]

    def decorate(command):
        for option in reversed(options):
            command = option(command)
        return csv_dialect_option(command)

    return decorate


class ToleranceType(click.ParamType):
    """A linewidth tolerance: ``45±3``, ``45+-3`` or ``42:48`` [µm]
    (:func:`ajtwin.apps.quality.part_map.parse_tolerance`)."""

    name = "tolerance"

    def convert(self, value, param, ctx):
        """The value as a :class:`~ajtwin.apps.quality.part_map.Tolerance`, else a click error."""
        # lazy CLI loading: the part map's module loads JAX; --help must not
        from ajtwin.apps.quality.part_map import Tolerance, parse_tolerance

        if isinstance(value, Tolerance):
            return value
        try:
            return parse_tolerance(value)
        except ValueError as exc:
            self.fail(str(exc), param, ctx)


def load_camera_option(camera_path):
    """The camera file of ``--camera`` (beside ``--job``); a usage error without one."""
    if camera_path is None:
        raise click.UsageError("--job needs --camera camera.toml (the camera's geometry)")
    # lazy CLI loading: the libraries a command needs are imported when it runs, never for
    # --help (this module is imported by every command's definition)
    from ajtwin.vision.camera import CameraFileError, load_camera

    try:
        return load_camera(camera_path)
    except (CameraFileError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None


def load_job_option(job_path, *, meta=None, process_speed=None, rapid_speed=None, repeat_to=None):
    """The program of ``--job`` as the print ran it
    (:func:`ajtwin.estimation.print_time.job_as_printed`: speeds and looping from the record's
    metadata ``meta`` where not given, and refused when the record names another program)."""
    if job_path is None:
        raise click.UsageError("--camera needs --job PROGRAM.prg")
    # lazy CLI loading: JAX comes with the twin's print-time module
    from ajtwin.estimation.print_time import job_as_printed
    from ajtwin.job import ProgramError

    info = (meta or {}).get("job")
    try:
        return job_as_printed(
            job_path,
            info if isinstance(info, dict) else None,
            process_speed_mm_s=process_speed,
            rapid_speed_mm_s=rapid_speed,
            repeat_to_s=repeat_to,
        )
    except (ProgramError, ValueError) as exc:
        raise click.ClickException(str(exc)) from None


class BoundedFloat(click.ParamType):
    """A float inside (low, high) (or [low, high] with ``closed``); NaN is always refused.

    ``inf`` passes only when ``high`` is ``inf`` and ``allow_inf`` is set (e.g. ``--gate inf``
    = off). Click's FloatRange lets NaN through (every comparison with NaN is false), which
    made ``--gate nan`` silently drop every measurement.

    Examples
    --------
    >>> BoundedFloat(0.0, float("inf"), allow_inf=True).convert("inf", None, None)
    inf
    """

    name = "float"

    def __init__(
        self,
        low: float | None = None,
        high: float | None = None,
        *,
        closed: bool = False,
        allow_inf: bool = False,
    ):
        self.low, self.high, self.closed, self.allow_inf = low, high, closed, allow_inf

    def convert(self, value, param, ctx):
        """The value as a float inside the bounds, else a click error naming the bound."""
        if isinstance(value, float | int) and not isinstance(value, bool):
            number = float(value)
        else:
            try:
                number = float(str(value).strip())
            except ValueError:
                self.fail(f"{value!r} is not a number", param, ctx)
        if math.isnan(number):
            self.fail("NaN is not a value", param, ctx)
        if math.isinf(number) and not (self.allow_inf and number > 0):
            self.fail(f"{number} is not a finite number", param, ctx)
        low_ok = self.low is None or (number >= self.low if self.closed else number > self.low)
        high_ok = (
            self.high is None
            or (math.isinf(number) and self.allow_inf)
            or (number <= self.high if self.closed else number < self.high)
        )
        if not (low_ok and high_ok):
            left, right = ("[", "]") if self.closed else ("(", ")")
            low = "-inf" if self.low is None else f"{self.low:g}"
            high = "inf" if self.high is None else f"{self.high:g}"
            self.fail(f"{number:g} is outside {left}{low}, {high}{right}", param, ctx)
        return number


class ProcessSpeed(click.ParamType):
    """``--process-speed``: one speed [mm/s] (the GUI's process speed where the program sets
    none), or speeds per layer, stroke or feature: ``2,4,3`` (successive layers, repeating),
    ``stroke:2,4,3``, ``feature:…`` or a schedule file ``speeds.toml``
    (:class:`ajtwin.job.SpeedSchedule`).

    Examples
    --------
    >>> ProcessSpeed().convert("3", None, None)
    3.0
    >>> ProcessSpeed().convert("2,4,3", None, None).describe()
    'per layer: 2, 4, 3 mm/s, repeating'
    """

    name = "MM_S|[UNIT:]V1,V2,…|FILE.toml"

    def convert(self, value, param, ctx):
        """A float for one speed, a :class:`~ajtwin.job.SpeedSchedule` otherwise."""
        # lazy CLI loading: the job package when a speed is read, not for --help
        from ajtwin.job.speeds import SpeedSchedule

        if isinstance(value, float | SpeedSchedule):
            return value
        text = str(value).strip()
        if "," not in text and ":" not in text and not text.lower().endswith(".toml"):
            return BoundedFloat(0.0, 10_000.0).convert(text, param, ctx)
        try:
            return SpeedSchedule.parse(text)
        except (ValueError, OSError) as exc:
            self.fail(str(exc), param, ctx)


def process_speed_option(command):
    """``--process-speed`` beside ``--job``: one speed, or speeds per layer, stroke or
    feature (:class:`ProcessSpeed`)."""
    return click.option(
        "--process-speed",
        type=ProcessSpeed(),
        default=None,
        help="With --job: the process speed [mm/s], or speeds per layer, e.g. 2,4,3 (successive "
        "layers, repeating), stroke:2,4,3, feature:… or a schedule file speeds.toml.",
    )(command)


def job_speeds(process_speed) -> dict:
    """``--process-speed``'s value as keywords of the job readers: ``process_speed_mm_s``
    (one speed) or ``speed_schedule`` (speeds per layer, stroke or feature)."""
    # lazy CLI loading: the job package when a speed is read, not for --help
    from ajtwin.job.speeds import SpeedSchedule

    if isinstance(process_speed, SpeedSchedule):
        return {"process_speed_mm_s": None, "speed_schedule": process_speed}
    return {"process_speed_mm_s": process_speed, "speed_schedule": None}


class OffsetMM(click.ParamType):
    """``DX[,DY]`` in mm (DY = 0 when left out); finite numbers only."""

    name = "DX[,DY]"
    #: what a value beyond 1 m would be (the error says so)
    beyond_1_m = "an offset beyond 1 m is not a camera on the head"

    def convert(self, value, param, ctx):
        """``"DX"`` or ``"DX,DY"`` [mm] → (dx, dy); click's error names the option."""
        if isinstance(value, tuple):
            return value
        parts = [p.strip() for p in str(value).split(",")]
        if not 1 <= len(parts) <= 2:
            self.fail(f"{value!r}: give DX or DX,DY in mm", param, ctx)
        numbers = [BoundedFloat().convert(p, param, ctx) for p in parts]
        if len(numbers) == 1:
            numbers.append(0.0)
        if any(abs(v) > 1000.0 for v in numbers):
            self.fail(f"{value!r}: {self.beyond_1_m}", param, ctx)
        return tuple(numbers)


class PitchMM(OffsetMM):
    """``DX[,DY]`` in mm between parts of a looped job, within the stage (1 m)."""

    beyond_1_m = "a pitch beyond 1 m does not fit on a printer's stage"


def check_vial_fill(ctx, param, value):
    """Click callback: the vial fill level must be in (0, V_v) mL (V_v from parameters.toml)."""
    if value is None:
        return value
    # lazy CLI loading: the model's parameters when a fill is checked
    from ajtwin.model import load_parameters

    capacity = units.m3_to_ml(load_parameters().vial_volume)
    if not 0.0 < value < capacity:
        raise click.BadParameter(
            f"{value:g} mL is outside (0, {capacity:g}) mL (the vial's capacity V_v)"
        )
    return value


def transition_option(func):
    """``--transition NAME``: the twin's droplet-size row, a variant of data/transition.toml
    (None: that file's default, read when the twin is made)."""
    default = packaged_toml("data/transition.toml")["default"]
    return click.option(
        "--transition",
        default=None,
        help="Droplet-size row of the twin: a variant of ajtwin/data/transition.toml — "
        "input_following (d_a follows Q_c/I_A), paper (the paper's model unchanged), "
        "mean_reverting; docs/explanation/forecast-droplet-dynamics.md. "
        f"[default: {default}]",
    )(func)


def transition_overrides(transition) -> dict:
    """Twin overrides of a ``--transition`` value ({} = the default variant); an unknown
    variant is a clear usage error."""
    if transition is None:
        return {}
    # lazy CLI loading: imported when the command runs, not for --help
    from ajtwin.model.droplet_dynamics import transition_variants

    if transition not in transition_variants():
        raise click.BadParameter(
            f"no transition variant {transition!r}; choose one of "
            f"{', '.join(transition_variants())}",
            param_hint="--transition",
        )
    return {"transition": transition}


def store_location(store, password_file=None):
    """The :class:`~ajtwin.store.location.StoreLocation` of ``--store`` and
    ``--store-password-file`` (an unknown URL scheme, a password in the URL: a usage error
    that says so)."""
    # lazy CLI loading: the registry (pandas) when a command opens one
    from ajtwin.store.registry import RegistryError

    try:
        return parse_store(store, password_file)
    except RegistryError as exc:
        raise click.BadParameter(str(exc), param_hint="--store") from None


def store_option(func):
    """``--store PATH|URL`` (or ``$AJTWIN_STORE``) and ``--store-password-file FILE`` (or
    ``$AJTWIN_STORE_PASSWORD_FILE``): the registry a command reads or writes, an SQLite
    file or a PostgreSQL database (:mod:`ajtwin.store.location`). The command gets it as
    ``store``: a :class:`~ajtwin.store.location.StoreLocation`."""

    @functools.wraps(func)
    def command(*args, store=None, store_password_file=None, **kwargs):
        return func(*args, store=store_location(store, store_password_file), **kwargs)

    command = click.option(
        "--store-password-file",
        "store_password_file",
        type=click.Path(dir_okay=False, path_type=Path),
        default=None,
        envvar=PASSWORD_FILE_ENV,
        help="PostgreSQL registry: a file whose first line is the password (never give it in "
        "the URL; libpq's $PGPASSWORD and ~/.pgpass work too).",
    )(command)
    return click.option(
        "--store",
        "store",
        default=None,
        envvar="AJTWIN_STORE",
        metavar="PATH|URL",
        help="The registry: an SQLite file, or a PostgreSQL URL "
        "(postgresql://user@host:5432/dbname?sslmode=verify-full); default $AJTWIN_STORE, "
        "else ~/.local/share/ajtwin/registry.sqlite.",
    )(command)


def open_registry(store, create: bool = False, write: bool | None = None):
    """The registry at ``store``; read-only commands (the default) never create it.

    A command that writes (``write``; default: when it may ``create``) is refused at once,
    before any work, when the registry cannot be written (read-only file, journal or folder).
    A registry of an older schema is migrated on open (each migration said on stderr);
    one from before the chain's range check gets its impossible prints excluded
    (:func:`ajtwin.engine.chain.open_registry`).
    """
    # lazy CLI loading: the registry and the twin's chain when a command opens one
    from ajtwin.engine.chain import open_registry as open_checked_registry
    from ajtwin.store.registry import RegistryError

    try:
        reg = open_checked_registry(store, create=create, write=create if write is None else write)
    except RegistryError as exc:
        raise click.ClickException(str(exc)) from None
    for message in reg.migrated:
        click.echo(message, err=True)
    return reg


def configure_logging(verbose: bool) -> None:
    """Log to stderr (DEBUG with ``--verbose``, else INFO); asyncua only its errors."""
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    # asyncua logs every request at INFO
    logging.getLogger("asyncua").setLevel(logging.ERROR)


def parse_seeds(text: str) -> list[int]:
    """Seeds from ``1-5``, ``1,3,7`` or a mix; click errors for anything else."""
    seeds: list[int] = []
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        try:
            if "-" in part:
                a, b = (int(v) for v in part.split("-", 1))
                if b < a:
                    raise ValueError
                seeds += list(range(a, b + 1))
            else:
                seeds.append(int(part))
        except ValueError:
            raise click.BadParameter(
                f"cannot read seeds {text!r} (use e.g. 1-5 or 1,3,7)"
            ) from None
    if not seeds or any(s < 0 for s in seeds):
        raise click.BadParameter(f"seeds must be non-negative integers, got {text!r}")
    return seeds


#: (state name, symbol, display unit) of the five states, as the commands print them
STATE_LABELS = tuple(
    (name, units.display(name).symbol, units.display(name).unit) for name in STATE_NAMES
)
#: the factor from a state's model unit to the unit of :data:`STATE_LABELS` (φ_A → ppm)
STATE_DISPLAY_SCALE = tuple(units.display(name).scale for name in STATE_NAMES)


def theta_text(theta) -> str:
    """The drift rates θ [1/s] as a person reads them: words first, per cent of each state
    per hour."""
    rates = ", ".join(
        f"{short} {units.readable(units.drift_rate_percent_per_hour(float(v)), 2, 1e-4)}"
        for (_, short, _), v in zip(STATE_LABELS, theta, strict=True)
    )
    return f"drift rates θ learned by EM [%/h]: {rates}"


#: symbol and unit of each input and output, as the commands print them
SHORT = {
    name: (units.display(name).symbol, units.display(name).unit)
    for name in (*INPUT_NAMES, "linewidth_um", "overspray_um", "carrier_pressure_Pa",
                 "sheath_pressure_Pa")
}  # fmt: skip


def parse_inputs(text):
    """``I_A,Q_c,Q_s`` [mA, sccm, sccm] → array (3,); None stays None."""
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise click.BadParameter(f"expected I_A,Q_c,Q_s (mA, sccm, sccm), got {text!r}")
    return np.array(values)
