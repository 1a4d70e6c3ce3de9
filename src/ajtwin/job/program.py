"""Single-pass reader of Optomec Aerosol Jet ACSPL+ programs (``.prg``).

The reader runs the program the way the controller would, with two clocks:

* the *program clock* ``tp`` — where the buffer's execution is. ``wait N`` adds N ms,
  ``till`` on a motion flag (``#MOVE``, ``#INPOS``) waits for the queued motion to end,
  ``ptp/e`` waits for its own motion; shutter commands act at ``tp``;
* the *motion clock* ``tm`` — when the motion queued so far ends. A motion command starts
  at ``max(tp, tm)`` and runs at a constant speed per segment (docs/reference/job.md,
  "Motion profile"): straight lines and circular arcs in X-Y.

Out come *pieces* (one per straight line or arc moved, with start and end times),
*shutter events* (time, open/closed) and the provenance of every speed used. The
:class:`~ajtwin.job.Job` turns them into the timeline. Everything the reader cannot
interpret is refused with a :class:`~ajtwin.job.errors.ProgramError` naming the file,
the line and its text; with ``skip_unknown`` a command that does not move the stage is
skipped with one warning per kind.
"""

from __future__ import annotations

import ast
import math
import re
from dataclasses import dataclass, field

import numpy as np

from ajtwin.io.schema import MAX_PLATEN_SPEED_MM_S
from ajtwin.job.errors import ProgramError
from ajtwin.job.settings import ReaderSettings, Stage

__all__ = [
    "KIND_LINE",
    "KIND_ARC",
    "KIND_DWELL",
    "KIND_NAMES",
    "SpeedSource",
    "ParsedProgram",
    "parse_program",
    "AXIS_NUMBERS",
]

KIND_LINE, KIND_ARC, KIND_DWELL = 0, 1, 2
KIND_NAMES = ("line", "arc", "dwell")

# ACSPL+ predefined axis names and their numbers (X=0, Y=1, ...).
AXIS_NUMBERS = {"x": 0, "y": 1, "z": 2, "t": 3, "a": 4, "b": 5, "c": 6, "d": 7}

# Columns of the piece table (float64).
(
    P_KIND,
    P_X0,
    P_Y0,
    P_X1,
    P_Y1,
    P_CX,
    P_CY,
    P_R,
    P_A0,
    P_SWEEP,
    P_LEN,
    P_T0,
    P_T1,
    P_SPEED,
    P_LINE,
    P_FEATURE,
    P_SOURCE,
) = range(17)
N_PIECE_FIELDS = 17

TWO_PI = 2.0 * math.pi
_NAN = math.nan

# Commands that move the stage or change the program flow: never skipped, even with
# skip_unknown, because the timeline would be silently wrong without them.
_UNSUPPORTED_MOTION = {
    "jog": "JOG (motion at a velocity without an end)",
    "track": "TRACK (motion following a changing target)",
    "mpoint": "MPOINT/PATH (motion through a point table)",
    "path": "PATH (motion through a point table)",
    "pvspline": "PVSPLINE (spline motion)",
    "spline": "SPLINE (spline motion)",
    "blendedseg": "BLENDEDSEG (blended segmented motion)",
    "master": "MASTER/SLAVE (axes following other axes)",
    "slave": "MASTER/SLAVE (axes following other axes)",
    "go": "GO (start of motion held with /w)",
    "home": "HOME (homing)",
    "xsegment": "XSEGMENT",
    "goto": "GOTO (a jump: the program's order is no longer its text)",
    "call": "CALL (a subroutine: the program's order is no longer its text)",
    "ret": "RET (a subroutine)",
    "loop": "LOOP (a repeated block)",
    "while": "WHILE (a repeated block)",
}
_BLOCK_OPENERS = {"if", "while", "loop", "block"}
_MOTION_WORDS = {
    "ptp",
    "mseg",
    "xseg",
    "line",
    "arc1",
    "arc2",
    "ends",
    "halt",
    "kill",
    *_UNSUPPORTED_MOTION,
}

# G-code's motion words (G0 rapid, G1 line, G2/G3 arcs): they move the stage, so a G-code line
# in an ACSPL+ program is never skipped as a command "that does not move the stage"
_GCODE_MOTION = re.compile(r"g0*[0-3]")
# a number as written in a program: Python's float() also reads "1_0" as 10, which no
# controller does; a literal token with an underscore is refused
_LITERAL = re.compile(r"(?<![\w.])\d[\w.]*")
# An arc1 end this close to its start is the start (a full turn written as such, rounding
# of the coordinates aside); further, up to the join tolerance, a warning says it was read
# as a full turn [mm]
_SAME_POINT_MM = 1e-6
#: Largest feature number of a ``!Feature`` comment (an int32: controllers' integers).
MAX_FEATURE_NUMBER = 2**31 - 1

_HEAD = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)\s*(?:/\s*([A-Za-z]+))?\s*(.*)", re.S)
_FEATURE = re.compile(r"feature\s*[:#=]?\s*(-?\d+)\s*[:\-]?\s*(.*)", re.I)
_OUT = re.compile(r"out\(?(\d+)\)?\.(\d+)$")
_INDEXED = re.compile(r"([a-z_][a-z0-9_]*)\((.+)\)$")


@dataclass(frozen=True)
class SpeedSource:
    """Where a speed came from.

    Attributes
    ----------
    value_mm_s : float
    kind : str
        ``"program"`` (set by the program), ``"given"`` (the GUI value passed by the caller,
        e.g. ``--process-speed``) or ``"default"`` (the GUI value of ``stage.toml``).
    origin : str
        In words: ``"line 6: gDblProcessSpeed = 3"``, ``"the GUI's process speed (given)"`` …
    """

    value_mm_s: float
    kind: str
    origin: str


@dataclass
class ParsedProgram:
    """What one pass over a program yields (input of :class:`ajtwin.job.Job`).

    ``pieces`` is an ``(n, 17)`` float array, one row per straight line or arc the stage
    moves, in time order, with the columns ``P_*`` of this module.
    """

    path: str
    n_lines: int
    pieces: np.ndarray
    shutter_t: np.ndarray
    shutter_open: np.ndarray
    shutter_line: np.ndarray
    mark_t: np.ndarray
    mark_line: np.ndarray
    feature_t: np.ndarray
    feature_value: np.ndarray
    feature_names: dict[int, str]
    end_time_s: float
    start_xy: tuple[float, float] | None
    speed_sources: list[SpeedSource]
    return_source: int
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


class _Stop(Exception):
    """STOP reached: the program ends."""


def _gui_speeds(stage: Stage, process_speed_mm_s, rapid_speed_mm_s) -> tuple[tuple, tuple]:
    """(value [mm/s], kind, origin) of the GUI's process and rapid speeds: the given ones,
    else the defaults of ``stage.toml``."""
    if process_speed_mm_s is None:
        proc = (
            stage.process_speed_mm_s,
            "default",
            f"the GUI's process speed, default of stage.toml ({stage.process_speed_source})",
        )
    else:
        proc = (
            _positive_speed(process_speed_mm_s, "process_speed_mm_s"),
            "given",
            "the GUI's process speed (given)",
        )
    if rapid_speed_mm_s is None:
        rapid = (
            stage.rapid_speed_mm_s,
            "default",
            f"the GUI's rapid speed, default of stage.toml ({stage.rapid_speed_source})",
        )
    else:
        rapid = (
            _positive_speed(rapid_speed_mm_s, "rapid_speed_mm_s"),
            "given",
            "the GUI's rapid speed (given)",
        )
    return proc, rapid


class _Reader:
    def __init__(
        self,
        path: str,
        settings: ReaderSettings,
        stage: Stage,
        process_speed_mm_s: float | None,
        rapid_speed_mm_s: float | None,
        skip_unknown: bool,
        axes: tuple[str | int, str | int],
        shutter_output: tuple[int, int],
        start_xy: tuple[float, float] | None,
    ):
        self.path = path
        self.tol = settings.join_tolerance_mm
        self.min_r = settings.min_arc_radius_mm
        self.cos_turn = math.cos(math.radians(settings.max_arc_turn_deg))
        self.max_time = settings.max_program_time_s
        self.skip_unknown = skip_unknown
        self.shutter_output = tuple(int(v) for v in shutter_output)
        self.x_axis, self.y_axis = (_axis_number(a) for a in axes)
        if self.x_axis is None or self.y_axis is None or self.x_axis == self.y_axis:
            raise ValueError(f"axes must name two different axes (X, Y, 0, 1, ...), got {axes}")

        self.sources: list[SpeedSource] = []
        self._source_index: dict[tuple, int] = {}
        proc, rapid = _gui_speeds(stage, process_speed_mm_s, rapid_speed_mm_s)
        # name -> (value or None, origin, kind, text when not computable)
        self.env: dict[str, tuple] = {
            "gdblprocessspeed": (proc[0], proc[2], proc[1], None),
            "gdblrapidspeed": (rapid[0], rapid[2], rapid[1], None),
            f"vel({self.x_axis})": (proc[0], proc[2], proc[1], None),
            f"vel({self.y_axis})": (proc[0], proc[2], proc[1], None),
            "gintsubbuffer": (1.0, "the GUI's shutter sub-buffer", "default", None),
            "gintfindfids": (0.0, "the GUI (fiducial search off)", "default", None),
        }
        self.rapid_default = self._source(rapid[0], rapid[1], rapid[2])

        self.x = self.y = None
        if start_xy is not None:
            self.x, self.y = (float(v) for v in start_xy)
            if not (math.isfinite(self.x) and math.isfinite(self.y)):
                raise ValueError(f"start position must be finite, got {start_xy}")
        self.start_xy = None if start_xy is None else (self.x, self.y)
        self.other: dict[int, float] = {}
        self.tp = 0.0
        self.tm = 0.0
        self.feature = -1
        self.last_motion_line = 0
        self.return_source = -1

        self.pieces: list[tuple] = []
        self.ev_t: list[float] = []
        self.ev_open: list[bool] = []
        self.ev_line: list[int] = []
        self.mark_t: list[float] = []
        self.mark_line: list[int] = []
        self.feat_t: list[float] = [0.0]
        self.feat_v: list[int] = [-1]
        self.feature_names: dict[int, str] = {}
        self.notes: list[str] = []
        self.warnings: list[str] = []
        self.skipped_kinds: dict[str, list] = {}
        self.ignored_targets: dict[str, int] = {}
        self.dynamics: dict[str, int] = {}
        self.shutter_is_open = False
        self.moving_shutter: dict[str, list] = {}

        # segmented path state
        self.seg_open = False
        self.seg_line = 0
        self.seg_axes: tuple = ()
        self.seg_t = 0.0
        self.seg_speed: tuple[float, int] | None = None
        self.prev_tangent: tuple[float, float] | None = None
        self.prev_is_arc = False
        self.prev_line = 0

        # If ... End blocks being skipped
        self.skip_depth = 0
        self.skip_start = 0
        self.skip_text = ""
        self.skip_motion = 0
        # Else branches being run (the If before each was skipped): (line, text)
        self.else_open: list[tuple[int, str]] = []
        # arc1s whose end lies within the join tolerance of their start: read as full turns
        self.full_turns: list = []

        self.axes_cache: dict[str, tuple] = {}
        self.handlers = self._command_handlers()

    def _command_handlers(self) -> dict:
        """The reader's method for each command word of the program (lower case)."""
        return {
            "ptp": self._ptp,
            "mseg": self._mseg,
            "xseg": self._mseg,
            "line": self._line,
            "arc1": self._arc1,
            "arc2": self._arc2,
            "ends": self._ends,
            "wait": self._wait,
            "till": self._till,
            "start": self._start,
            "if": self._if,
            "global": self._declare,
            "real": self._declare,
            "int": self._declare,
            "stop": self._stop,
            "halt": self._halt,
            "kill": self._halt,
            "end": self._end,
            "else": self._end_unmatched,
            "elseif": self._end_unmatched,
        }

    # -- errors, notes, provenance ---------------------------------------------------------

    def error(self, ln: int, raw: str, reason: str) -> ProgramError:
        return ProgramError(self.path, ln, raw, reason)

    def _source(self, value: float, kind: str, origin: str) -> int:
        key = (value, kind, origin)
        index = self._source_index.get(key)
        if index is None:
            index = self._source_index[key] = len(self.sources)
            self.sources.append(SpeedSource(value, kind, origin))
        return index

    # -- numbers and expressions -----------------------------------------------------------

    def _num(self, text: str, ln: int, raw: str, what: str) -> float:
        value = _plain_float(text)
        if value is None:
            value = self._expr(text, ln, raw, what)[0]
        if value - value != 0.0:  # NaN or infinite
            raise self.error(ln, raw, f"{what} is not a finite number: {text.strip()!r}")
        return value

    def _expr(self, text: str, ln: int, raw: str, what: str) -> tuple[float, str, str]:
        """Value, origin and kind of an expression (a number, a variable, arithmetic)."""
        src = text.strip()
        if not src:
            raise self.error(ln, raw, f"{what} is missing")
        key = src.lower().replace(" ", "")
        entry = self.env.get(key)
        if entry is None and _INDEXED.match(key):
            entry = self.env.get(self._index_key(key, ln, raw))
        if entry is not None:
            return self._entry_value(entry, src, ln, raw), entry[1], entry[2]
        for literal in _LITERAL.findall(src):
            if "_" in literal:
                raise self.error(ln, raw, f"unreadable number {literal!r} in {what}")
        try:
            tree = ast.parse(src, mode="eval")
            value = self._eval(tree.body, src, ln, raw, what)
        except (SyntaxError, ValueError) as exc:  # ValueError: an integer of > 4300 digits
            if isinstance(exc, ProgramError):
                raise
            raise self.error(ln, raw, f"unreadable number in {what}: {src!r}") from None
        except (RecursionError, MemoryError):
            raise self.error(
                ln,
                raw,
                f"{what} is an expression nested too deeply to read ({len(src)} characters); "
                "write its value",
            ) from None
        return value, f"line {ln}: {src}", "program"

    def _entry_value(self, entry: tuple, name: str, ln: int, raw: str) -> float:
        value, origin, _, text = entry
        if value is None:
            raise self.error(
                ln, raw, f"{name} has no value this reader can compute ({origin}: {text!r})"
            )
        return value

    def _eval(self, node, src: str, ln: int, raw: str, what: str) -> float:
        if isinstance(node, ast.Constant) and isinstance(node.value, int | float):
            try:
                return float(node.value)
            except OverflowError:  # an integer beyond any float
                raise self.error(
                    ln, raw, f"a number in {what} is too large ({len(str(node.value))} digits)"
                ) from None
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
            value = self._eval(node.operand, src, ln, raw, what)
            return -value if isinstance(node.op, ast.USub) else value
        if isinstance(node, ast.BinOp) and isinstance(
            node.op, ast.Add | ast.Sub | ast.Mult | ast.Div
        ):
            a = self._eval(node.left, src, ln, raw, what)
            b = self._eval(node.right, src, ln, raw, what)
            if isinstance(node.op, ast.Add):
                return a + b
            if isinstance(node.op, ast.Sub):
                return a - b
            if isinstance(node.op, ast.Mult):
                return a * b
            if b == 0.0:
                raise self.error(ln, raw, f"division by zero in {what}: {src!r}")
            return a / b
        if isinstance(node, ast.Name):
            entry = self.env.get(node.id.lower())
            if entry is None:
                raise self.error(ln, raw, f"unknown variable {node.id} in {what}: {src!r}")
            return self._entry_value(entry, node.id, ln, raw)
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Name)
            and len(node.args) == 1
            and not node.keywords
        ):
            name = node.func.id.lower()
            index = self._index_of(node.args[0], src, ln, raw, what)
            if name in ("apos", "rpos", "fpos"):  # a position: where the queued motion ends
                position = self._axis_position(int(index))
                if position is None:
                    raise self.error(
                        ln, raw, f"{node.func.id}({index}) is not known yet: no motion has set it"
                    )
                return position
            entry = self.env.get(f"{name}({index})")
            if entry is None:
                raise self.error(
                    ln, raw, f"unknown variable {node.func.id}({index}) in {what}: {src!r}"
                )
            return self._entry_value(entry, f"{node.func.id}({index})", ln, raw)
        raise self.error(ln, raw, f"unreadable number in {what}: {src!r}")

    def _index_of(self, node, src, ln, raw, what) -> str:
        if isinstance(node, ast.Name) and node.id.lower() in AXIS_NUMBERS:
            return str(AXIS_NUMBERS[node.id.lower()])
        value = self._eval(node, src, ln, raw, what)
        if not math.isfinite(value):
            raise self.error(ln, raw, f"index {value} is not a finite number in {what}: {src!r}")
        if value != int(value):
            raise self.error(ln, raw, f"index {value} is not an integer in {what}: {src!r}")
        return str(int(value))

    def _index_key(self, key: str, ln: int, raw: str) -> str:
        """Canonical name of an indexed variable: ``vel(x)`` -> ``vel(0)``."""
        m = _INDEXED.match(key)
        name, index = m.group(1), m.group(2)
        if index in AXIS_NUMBERS:
            return f"{name}({AXIS_NUMBERS[index]})"
        number = _plain_float(index)
        if number is None:
            number = self._expr(index, ln, raw, f"the index of {name}")[0]
        if not math.isfinite(number):
            raise self.error(ln, raw, f"the index of {name} is not a finite number: {index!r}")
        return f"{name}({int(number)})" if number == int(number) else f"{name}({index})"

    def _axis_position(self, axis: int) -> float | None:
        if axis == self.x_axis:
            return self.x
        if axis == self.y_axis:
            return self.y
        return self.other.get(axis)

    # -- speeds ----------------------------------------------------------------------------

    def _speed(self, arg: str | None, lead_axis: int, ln: int, raw: str) -> tuple[float, int]:
        if arg is None:
            entry = self.env.get(f"vel({lead_axis})")
            if entry is None:
                raise self.error(
                    ln,
                    raw,
                    f"no speed for axis {lead_axis}: the program sets no VEL({lead_axis}) and the "
                    "motion has no /v speed",
                )
            value, origin, kind = (
                self._entry_value(entry, f"VEL({lead_axis})", ln, raw),
                entry[1],
                entry[2],
            )
            if kind == "program":
                origin = f"VEL({lead_axis}) from {origin}"
        else:
            value = _plain_float(arg)
            if value is not None:
                origin, kind = f"line {ln}: {arg.strip()}", "program"
            else:
                value, origin, kind = self._expr(arg, ln, raw, "the speed")
        if not (value > 0.0 and math.isfinite(value)):
            raise self.error(
                ln, raw, f"speed {value} mm/s ({origin}) is not a positive finite speed"
            )
        if value > MAX_PLATEN_SPEED_MM_S:
            raise self.error(
                ln,
                raw,
                f"speed {value:g} mm/s ({origin}) is faster than any Aerosol Jet stage moves "
                f"(at most {MAX_PLATEN_SPEED_MM_S:g} mm/s): is it in another unit?",
            )
        return value, self._source(value, kind, origin)

    # -- the pass --------------------------------------------------------------------------

    def run(self, lines: list[str]) -> None:
        handlers = self.handlers
        head = _HEAD.match
        buffer_seen = False
        for ln, raw in enumerate(lines, 1):
            s = raw.strip()
            if not s:
                continue
            first = s[0]
            if first == "!":
                body = s[1:].lstrip()
                if body[:7].lower() == "feature" and not self.skip_depth:
                    self._feature(body, ln, s)
                continue
            if first == "#":
                if buffer_seen:
                    self.notes.append(
                        f"line {ln}: {s} starts another buffer; the rest of the file is not this "
                        "program and is not read"
                    )
                    break
                buffer_seen = True
                continue
            bang = s.find("!")
            if bang > 0:
                s = s[:bang].rstrip()
            for stmt in s.split(";") if ";" in s else (s,):
                stmt = stmt.strip()
                if not stmt:
                    continue
                m = head(stmt)
                if m is None:
                    raise self.error(ln, s, f"unreadable statement {stmt!r}")
                word = m.group(1).lower()
                if self.skip_depth:
                    self._skipping(word, ln)
                    continue
                handler = handlers.get(word)
                try:
                    if handler is not None:
                        handler(m.group(2) or "", m.group(3), ln, s)
                    elif word in _UNSUPPORTED_MOTION and not m.group(3).startswith("="):
                        # WHILE x = 1: ACSPL+ compares with "=", this is no assignment
                        self._unknown(word, stmt, ln, s)
                    elif "=" in stmt:
                        self._assign(stmt, ln, s)
                    elif stmt.endswith(":") and " " not in stmt:
                        continue  # a label: a jump target, no effect on a straight run
                    else:
                        self._unknown(word, stmt, ln, s)
                except _Stop:
                    self._after_stop(lines, ln)
                    return
        self._finish_checks(len(lines))

    def _after_stop(self, lines: list[str], ln: int) -> None:
        for later in range(ln, len(lines)):
            text = lines[later].strip()
            if text and not text.startswith("!"):
                if text.startswith("#"):
                    break
                self.notes.append(f"line {ln}: STOP ends the program; lines after it are not run")
                break
        self._finish_checks(ln)

    def _finish_checks(self, last_line: int) -> None:
        if self.skip_depth:
            raise self.error(self.skip_start, self.skip_text, "this block has no End")
        if self.else_open:
            line, text = self.else_open[-1]
            raise self.error(line, text, "this Else branch has no End")
        if self.seg_open:
            raise self.error(self.seg_line, "MSEG", "this segmented path is never closed by ENDS")
        for kind, (line, count) in self.skipped_kinds.items():
            self.warnings.append(
                f"skipped {count} '{kind}' statement(s) that do not move the stage (first at line "
                f"{line})"
            )
        for action, (line, count) in self.moving_shutter.items():
            self.warnings.append(
                f"the shutter is told to {action} while the stage is still moving ({count} "
                f"time(s), first at line {line}): the program does not wait for the motion "
                "(no till or /e before it), so it acts mid-move"
            )
        for target, line in self.ignored_targets.items():
            self.notes.append(
                f"line {line}: assignments to {target} do not change the timeline and are ignored"
            )
        if self.full_turns:
            line, chord, radius = self.full_turns[0]
            self.warnings.append(
                f"{len(self.full_turns)} arc1(s) end within the {_distance(self.tol)} join "
                f"tolerance of their start but not on it (first at line {line}: "
                f"{_distance(chord)} apart on a {radius:.4g} mm radius): read as full turns "
                f"({TWO_PI * radius:.4g} mm); write the end point equal to the start for a "
                "full turn, or use arc2 with the sweep for a short arc"
            )
        if not any(self.ev_open):
            self.warnings.append(self._nothing_printed())
        if self.dynamics:
            where = ", ".join(f"{name} (line {line})" for name, line in self.dynamics.items())
            self.notes.append(
                f"the program sets {where}; the timeline keeps a constant speed per segment, "
                "so each start and stop takes about speed/acceleration less time than on the "
                "machine"
            )

    def _nothing_printed(self) -> str:
        """Why the program prints nothing: the shutter output it never opens, and the other
        outputs it switches (a shutter wired to another port)."""
        port, bit = self.shutter_output
        text = (
            f"prints nothing: the program never opens the shutter (OUT{port}.{bit} or ShutterOpen)"
        )
        if self.ev_line:
            text += f"; it only closes it (line {self.ev_line[0]})"
        others = [f"{name.removeprefix('digital output ')} (line {line})"
                  for name, line in self.ignored_targets.items()
                  if name.startswith("digital output")]  # fmt: skip
        if others:
            text += (
                f"; it switches {', '.join(others)}: ajtwin reads OUT{port}.{bit} as the shutter"
            )
        return text

    # -- statements ------------------------------------------------------------------------

    def _skipping(self, word: str, ln: int) -> None:
        if word in _BLOCK_OPENERS:
            self.skip_depth += 1
        elif word == "end" or (word == "else" and self.skip_depth == 1):
            self.skip_depth -= 1
            if self.skip_depth == 0:
                moved = self.skip_motion
                text = (
                    f"lines {self.skip_start}-{ln}: block '{self.skip_text}' skipped "
                    "(alignment/fiducial block, run only on the GUI's request)"
                )
                if word == "else":  # its condition taken as false: the Else branch runs
                    text = (
                        f"lines {self.skip_start}-{ln}: the If branch of '{self.skip_text}' "
                        "skipped (its condition taken as false: alignment/fiducial blocks run "
                        f"only on the GUI's request); its Else branch from line {ln} is run"
                    )
                    self.else_open.append((ln, self.skip_text))
                if moved:
                    self.warnings.append(
                        f"{text}; it holds {moved} motion command(s) that are not in the timeline"
                    )
                else:
                    self.notes.append(text)
        elif word in _MOTION_WORDS:
            self.skip_motion += 1

    def _if(self, sw, rest, ln, raw):
        self.skip_depth, self.skip_start, self.skip_text, self.skip_motion = 1, ln, raw, 0

    def _end(self, sw, rest, ln, raw):
        if self.else_open:
            self.else_open.pop()  # the End of an Else branch that was run
            return
        self._end_unmatched(sw, rest, ln, raw)

    def _end_unmatched(self, sw, rest, ln, raw):
        raise self.error(ln, raw, "End/Else without a matching If")

    def _feature(self, body: str, ln: int, raw: str) -> None:
        m = _FEATURE.match(body)
        if m is None:
            self.notes.append(f"line {ln}: feature comment without a number ignored: {raw}")
            return
        if len(m.group(1).lstrip("-")) > 10 or abs(int(m.group(1))) > MAX_FEATURE_NUMBER:
            raise self.error(
                ln,
                raw,
                f"feature number {m.group(1)} is too large (features are numbered up to "
                f"{MAX_FEATURE_NUMBER})",
            )
        number = int(m.group(1))
        self.feature = number
        self.feat_t.append(self.tp)
        self.feat_v.append(number)
        name = m.group(2).strip()
        self.feature_names.setdefault(number, name)

    def _unknown(self, word: str, stmt: str, ln: int, raw: str) -> None:
        if _GCODE_MOTION.fullmatch(word):
            raise self.error(
                ln,
                raw,
                f"{word.upper()} is a G-code motion command: it moves the stage, and this "
                "reader reads ACSPL+ programs (.prg), not G-code",
            )
        if word in _UNSUPPORTED_MOTION:
            raise self.error(
                ln,
                raw,
                f"{_UNSUPPORTED_MOTION[word]} is not supported: it moves the stage or changes the "
                "program's order, so the timeline would be wrong",
            )
        if not self.skip_unknown:
            raise self.error(
                ln,
                raw,
                f"unknown command {word!r} (skip_unknown / --skip-unknown skips commands that do "
                "not move the stage)",
            )
        entry = self.skipped_kinds.setdefault(word, [ln, 0])
        entry[1] += 1

    def _declare(self, sw, rest, ln, raw):
        for name in rest.replace(",", " ").split():
            low = name.lower()
            if low in ("real", "int", "global", "static"):
                continue
            base = low.split("(")[0]
            if not base.isidentifier():
                raise self.error(ln, raw, f"unreadable declaration of {name!r}")
            self.env.setdefault(base, (0.0, f"line {ln}: declared", "program", None))

    def _assign(self, stmt: str, ln: int, raw: str) -> None:
        lhs, _, rhs = stmt.partition("=")
        target = lhs.strip().lower().replace(" ", "")
        m = _OUT.match(target)
        if m is not None:
            value = self._num(rhs, ln, raw, f"the value of {lhs.strip()}")
            if (int(m.group(1)), int(m.group(2))) == self.shutter_output:
                self._shutter(value != 0.0, ln)
            else:
                self.ignored_targets.setdefault(f"digital output OUT{m.group(1)}.{m.group(2)}", ln)
            return
        if "." in target or "#" in target:
            self.ignored_targets.setdefault(target.split(".")[0].upper() + " bit fields", ln)
            return
        if _INDEXED.match(target):
            target = self._index_key(target, ln, raw)
        elif not target.isidentifier():
            raise self.error(ln, raw, f"unreadable assignment target {lhs.strip()!r}")
        text = rhs.strip()
        value = _plain_float(text)
        if value is None:
            try:
                value = self._expr(text, ln, raw, f"the value of {lhs.strip()}")[0]
            except ProgramError:
                value = None  # refused only if the motion uses it
        if value is not None and value - value != 0.0:
            raise self.error(
                ln, raw, f"{lhs.strip()} is set to a value that is not a finite number: {text!r}"
            )
        origin = f"line {ln}: {lhs.strip()} = {text}"
        self.env[target] = (value, origin, "program", text)
        name = target.split("(")[0]
        if name in ("acc", "dec", "jerk", "kdec"):
            self.dynamics.setdefault(lhs.strip(), ln)

    def _shutter(self, is_open: bool, ln: int) -> None:
        if self.tm > self.tp:
            entry = self.moving_shutter.setdefault("open" if is_open else "close", [ln, 0])
            entry[1] += 1
        self.ev_t.append(self.tp)
        self.ev_open.append(is_open)
        self.ev_line.append(ln)
        self.mark_t.append(self.tp)
        self.mark_line.append(ln)
        self.shutter_is_open = is_open

    def _start(self, sw, rest, ln, raw):
        parts = [p.strip() for p in rest.split(",")]
        label = parts[-1].lower() if len(parts) >= 2 else ""
        if label == "shutteropen":
            self._shutter(True, ln)
        elif label == "shutterclose":
            self._shutter(False, ln)
        else:
            self._unknown(f"start {parts[-1]}", raw, ln, raw)

    def _wait(self, sw, rest, ln, raw):
        ms = self._num(rest, ln, raw, "the wait time")
        if ms < 0:
            raise self.error(ln, raw, f"negative wait time {ms} ms")
        self.mark_t.append(self.tp)
        self.mark_line.append(ln)
        self.tp = self._clock(self.tp + ms * 1e-3, ln, raw)

    def _till(self, sw, rest, ln, raw):
        condition = rest.lower()
        if "#move" in condition or "#inpos" in condition:
            if self.tm > self.tp:
                self.mark_t.append(self.tm)
                self.mark_line.append(ln)
                self.tp = self.tm
        elif "pst(" in condition and "#run" in condition:
            return  # waits for a sub-buffer (the shutter routine): taken as instantaneous
        else:
            self._unknown("till (on a condition other than motion or a sub-buffer)", raw, ln, raw)

    def _stop(self, sw, rest, ln, raw):
        raise _Stop

    def _clock(self, t: float, ln: int, raw: str) -> float:
        """``t``, a time the program reaches at line ``ln``, refused beyond the clock's bound."""
        if not t <= self.max_time:
            raise self.error(
                ln,
                raw,
                f"the program's clock reaches {t:.4g} s here, beyond the {self.max_time:.4g} s "
                "(job.toml max_program_time_s) a program may last: a wait or a move far too "
                "long (is it in the right unit?)",
            )
        return t

    def _halt(self, sw, rest, ln, raw):
        """HALT/KILL: the motion stops where it is at the program time."""
        t = self.tp
        self.seg_open = False
        if self.tm <= t:
            return
        pieces = self.pieces
        while pieces and pieces[-1][P_T0] >= t:
            dropped = pieces.pop()  # not started yet: the stage stays at its start
            self.x, self.y = dropped[P_X0], dropped[P_Y0]
        if pieces and pieces[-1][P_T1] > t:
            piece = pieces.pop()
            cut = _cut_piece(piece, (t - piece[P_T0]) / (piece[P_T1] - piece[P_T0]))
            pieces.append(cut)
            self.x, self.y = cut[P_X1], cut[P_Y1]
        self.tm = t
        self.notes.append(f"line {ln}: {raw} stops the motion at t = {t:.3f} s, before its end")

    # -- motion ----------------------------------------------------------------------------

    def _axes(self, text: str, ln: int, raw: str) -> tuple:
        cached = self.axes_cache.get(text)
        if cached is not None:
            return cached
        numbers = []
        for token in text.split(","):
            number = _axis_number(token.strip())
            if number is None:
                raise self.error(
                    ln,
                    raw,
                    f"unknown axis {token.strip()!r} (axes are X, Y, Z, T, A, B, C, D or numbers)",
                )
            numbers.append(number)
        numbers = tuple(numbers)
        if len(set(numbers)) != len(numbers):
            raise self.error(ln, raw, f"an axis appears twice in ({text})")
        ix = numbers.index(self.x_axis) if self.x_axis in numbers else -1
        iy = numbers.index(self.y_axis) if self.y_axis in numbers else -1
        result = (numbers, ix, iy)
        self.axes_cache[text] = result
        return result

    def _motion_args(self, word: str, sw: str, rest: str, ln: int, raw: str, n_extra: int):
        """Axes, X/Y positions in them, and the argument texts (checked for count)."""
        rest = rest.strip()
        if rest.startswith("("):
            close = rest.find(")")
            if close < 0:
                raise self.error(ln, raw, f"{word}: the axis list has no closing parenthesis")
            axes_text, args_text = rest[1:close], rest[close + 1 :].strip()
            if args_text.startswith(","):
                args_text = args_text[1:]
        else:
            axes_text, _, args_text = rest.partition(",")
        numbers, ix, iy = self._axes(axes_text, ln, raw)
        args = args_text.split(",") if args_text.strip() else []
        need = len(numbers) + n_extra + ("v" in sw)
        if len(args) != need:
            name = word + (f"/{sw}" if sw else "")
            raise self.error(
                ln, raw, f"{name} on {len(numbers)} axis(es) needs {need} values, got {len(args)}"
            )
        return numbers, ix, iy, args

    def _check_switches(self, word: str, sw: str, allowed: str, ln: int, raw: str) -> str:
        sw = sw.lower()
        for s in sw:
            if s not in allowed:
                raise self.error(
                    ln,
                    raw,
                    f"switch /{s} of {word} is not supported (supported: "
                    f"{', '.join('/' + a for a in allowed)})",
                )
        return sw

    def _mark_first_motion(self, speed_source: int) -> None:
        if self.return_source < 0:
            self.return_source = speed_source

    def _ptp(self, sw, rest, ln, raw, word="ptp"):
        sw = self._check_switches(word, sw, "evr", ln, raw)
        if self.seg_open:
            raise self.error(
                ln,
                raw,
                f"{word} inside the segmented path opened at line {self.seg_line} (expected line, "
                "arc1, arc2 or ends)",
            )
        axes, ix, iy, args = self._motion_args(word, sw, rest, ln, raw, 0)
        n = len(axes)
        values = [self._num(a, ln, raw, f"coordinate {i + 1}") for i, a in enumerate(args[:n])]
        speed, source = self._speed(args[n] if "v" in sw else None, axes[0], ln, raw)
        relative = "r" in sw
        other_sq = 0.0
        for j, axis in enumerate(axes):
            if j == ix or j == iy:
                continue
            current = self.other.get(axis)
            if current is None:
                if relative:
                    raise self.error(
                        ln, raw, f"relative move of axis {axis} before its position is known"
                    )
                self.other[axis] = values[j]
            else:
                target = current + values[j] if relative else values[j]
                other_sq += (target - current) ** 2
                self.other[axis] = target
        x0, y0 = self.x, self.y
        if relative and ((ix >= 0 and x0 is None) or (iy >= 0 and y0 is None)):
            raise self.error(ln, raw, "relative move before the stage's position is known")
        x1 = x0 if ix < 0 else (x0 + values[ix] if relative else values[ix])
        y1 = y0 if iy < 0 else (y0 + values[iy] if relative else values[iy])
        if ix >= 0 or iy >= 0:
            self._mark_first_motion(source)
        if x0 is None:
            x0 = x1
        if y0 is None:
            y0 = y1
        start = self.tp if self.tp > self.tm else self.tm
        end = self._move_line(x0, y0, x1, y1, other_sq, speed, source, (ln, raw), start)
        self.tm = end
        if "e" in sw:
            self.tp = end

    def _move_line(self, x0, y0, x1, y1, other_sq, speed, source, where, start) -> float:
        """Queue a straight move (``where``: its line and text); returns its end time.
        Unknown X or Y stays unknown."""
        ln, raw = where
        self.x, self.y = x1, y1
        if x0 is None or y0 is None or x1 is None or y1 is None:
            dxy = 0.0
        else:
            dxy = math.hypot(x1 - x0, y1 - y0)
        total = math.sqrt(dxy * dxy + other_sq) if other_sq else dxy
        if total == 0.0:
            return start
        duration = total / speed
        if not duration > 0.0:  # a move of a few 1e-300 mm at speed: no time a float holds
            raise self.error(
                ln,
                raw,
                f"a move of {total:.3g} mm at {speed:g} mm/s takes no time this clock can hold",
            )
        self._clock(start + duration, ln, raw)
        if dxy > 0.0:
            self.pieces.append(
                (
                    KIND_LINE,
                    x0,
                    y0,
                    x1,
                    y1,
                    _NAN,
                    _NAN,
                    _NAN,
                    _NAN,
                    0.0,
                    dxy,
                    start,
                    start + duration,
                    dxy / duration,
                    ln,
                    self.feature,
                    source,
                )
            )
            self.last_motion_line = ln
        return start + duration

    def _mseg(self, sw, rest, ln, raw):
        sw = self._check_switches("mseg", sw, "v", ln, raw)
        if self.seg_open:
            raise self.error(
                ln, raw, f"MSEG inside the segmented path opened at line {self.seg_line}"
            )
        axes, ix, iy, args = self._motion_args("mseg", sw, rest, ln, raw, 0)
        if len(axes) != 2 or ix < 0 or iy < 0:
            raise self.error(
                ln, raw, "segmented paths are read in the X-Y plane only: the axes must be (X,Y)"
            )
        x0 = self._num(args[ix], ln, raw, "the start X")
        y0 = self._num(args[iy], ln, raw, "the start Y")
        speed = self._speed(args[2] if "v" in sw else None, axes[0], ln, raw)
        if self.x is None or self.y is None:
            self.x, self.y = x0, y0
            self._mark_first_motion(self.rapid_default)
        else:
            gap = math.hypot(x0 - self.x, y0 - self.y)
            if gap > self.tol:
                where = (
                    f"the previous motion (line {self.last_motion_line})"
                    if self.last_motion_line
                    else "the program's start"
                )
                raise self.error(
                    ln,
                    raw,
                    f"the segmented path starts at ({x0:g}, {y0:g}) but {where} left the stage at "
                    f"({self.x:g}, {self.y:g}), {_distance(gap)} away (tolerance "
                    f"{_distance(self.tol)}): an arc or line before it does not end where the "
                    "program expects",
                )
        self.seg_open, self.seg_line, self.seg_axes = True, ln, axes
        self.seg_t = self.tp if self.tp > self.tm else self.tm
        self.seg_speed = speed
        self.prev_tangent, self.prev_is_arc, self.prev_line = None, False, ln

    def _ends(self, sw, rest, ln, raw):
        if not self.seg_open:
            raise self.error(ln, raw, "ENDS without an open segmented path (MSEG)")
        self.seg_open = False

    def _segment_speed(self, sw, args, n, ln, raw) -> tuple[float, int]:
        if "v" in sw:
            return self._speed(args[n], self.seg_axes[0], ln, raw)
        return self.seg_speed

    def _begin_segment(self, word, sw, rest, ln, raw, n_extra):
        """Shared start of line/arc1/arc2 inside a path; a lone one is a path of one segment."""
        sw = self._check_switches(word, sw, "v", ln, raw)
        implicit = not self.seg_open
        if implicit:
            if self.x is None or self.y is None:
                raise self.error(
                    ln, raw, f"{word} before the stage's position is known (start with ptp or MSEG)"
                )
            self.seg_t = self.tp if self.tp > self.tm else self.tm
            self.seg_speed = None
            self.prev_tangent, self.prev_is_arc, self.prev_line = None, False, ln
        axes, ix, iy, args = self._motion_args(word, sw, rest, ln, raw, n_extra)
        if len(axes) != 2 or ix < 0 or iy < 0:
            raise self.error(
                ln, raw, f"{word} is read in the X-Y plane only: the axes must be (X,Y)"
            )
        if not implicit and axes != self.seg_axes:
            raise self.error(
                ln, raw, f"{word} on other axes than its segmented path (line {self.seg_line})"
            )
        if implicit:
            self.seg_axes = axes
            self.seg_speed = self._speed(None, axes[0], ln, raw) if "v" not in sw else None
        speed = self._segment_speed(sw, args, 2 + n_extra, ln, raw)
        if implicit:
            self._mark_first_motion(speed[1])
        return sw, ix, iy, args, speed, implicit

    def _push_segment(
        self,
        piece: tuple,
        start_tangent,
        end_tangent,
        is_arc: bool,
        ln: int,
        raw: str,
        implicit: bool,
    ):
        prev = self.prev_tangent
        if prev is not None and (is_arc or self.prev_is_arc):
            cosine = prev[0] * start_tangent[0] + prev[1] * start_tangent[1]
            if cosine < self.cos_turn:
                angle = math.degrees(math.acos(max(-1.0, min(1.0, cosine))))
                which = "this arc" if is_arc else f"the arc at line {self.prev_line}"
                raise self.error(
                    ln,
                    raw,
                    f"the path turns back by {angle:.0f} deg where {which} joins the segment "
                    f"{'before' if is_arc else 'after'} it (line "
                    f"{self.prev_line if is_arc else ln}) at "
                    f"({piece[P_X0]:g}, {piece[P_Y0]:g}): an arc that retraces its neighbour has "
                    "the wrong "
                    "direction (arc1 +/-) or sweep sign (arc2)",
                )
        if not piece[P_T1] > piece[P_T0]:  # a length that takes no time at this speed
            raise self.error(
                ln, raw, f"a move of {piece[P_LEN]:.3g} mm takes no time this clock can hold"
            )
        self._clock(piece[P_T1], ln, raw)
        self.pieces.append(piece)
        self.last_motion_line = ln
        self.seg_t = piece[P_T1]
        self.tm = self.seg_t
        self.x, self.y = piece[P_X1], piece[P_Y1]
        self.prev_tangent, self.prev_is_arc, self.prev_line = end_tangent, is_arc, ln
        if implicit:
            self.seg_open = False

    def _line(self, sw, rest, ln, raw):
        sw, ix, iy, args, (speed, source), implicit = self._begin_segment(
            "line", sw, rest, ln, raw, 0
        )
        x1 = self._num(args[ix], ln, raw, "the end X")
        y1 = self._num(args[iy], ln, raw, "the end Y")
        x0, y0 = self.x, self.y
        length = math.hypot(x1 - x0, y1 - y0)
        if length == 0.0:
            return
        t0 = self.seg_t
        piece = (
            KIND_LINE,
            x0,
            y0,
            x1,
            y1,
            _NAN,
            _NAN,
            _NAN,
            _NAN,
            0.0,
            length,
            t0,
            t0 + length / speed,
            speed,
            ln,
            self.feature,
            source,
        )
        tangent = ((x1 - x0) / length, (y1 - y0) / length)
        self._push_segment(piece, tangent, tangent, False, ln, raw, implicit)

    def _arc(self, cx, cy, sweep, end, speed, source, ln, raw, implicit, word):
        x0, y0 = self.x, self.y
        radius = math.hypot(x0 - cx, y0 - cy)
        if radius < self.min_r:
            raise self.error(
                ln,
                raw,
                f"{word}: zero-radius arc (the centre ({cx:g}, {cy:g}) is the stage's position, "
                f"radius {radius:.3g} mm)",
            )
        a0 = math.atan2(y0 - cy, x0 - cx)
        a1 = a0 + sweep
        if end is None:
            end = (cx + radius * math.cos(a1), cy + radius * math.sin(a1))
        length = radius * abs(sweep)
        t0 = self.seg_t
        piece = (
            KIND_ARC,
            x0,
            y0,
            end[0],
            end[1],
            cx,
            cy,
            radius,
            a0,
            sweep,
            length,
            t0,
            t0 + length / speed,
            speed,
            ln,
            self.feature,
            source,
        )
        sign = 1.0 if sweep > 0 else -1.0
        start_tangent = (-sign * math.sin(a0), sign * math.cos(a0))
        end_tangent = (-sign * math.sin(a1), sign * math.cos(a1))
        self._push_segment(piece, start_tangent, end_tangent, True, ln, raw, implicit)

    def _arc1(self, sw, rest, ln, raw):
        """arc1 (X,Y), cx, cy, x_end, y_end, +|- : centre, end point and direction."""
        sw, ix, iy, args, (speed, source), implicit = self._begin_segment(
            "arc1", sw, rest, ln, raw, 3
        )
        cx = self._num(args[ix], ln, raw, "the centre X")
        cy = self._num(args[iy], ln, raw, "the centre Y")
        xe = self._num(args[2 + ix], ln, raw, "the end X")
        ye = self._num(args[2 + iy], ln, raw, "the end Y")
        direction = args[4].strip()
        if direction not in ("+", "-"):
            raise self.error(
                ln,
                raw,
                f"arc1 direction must be + (counter-clockwise) or - (clockwise), got {direction!r}",
            )
        x0, y0 = self.x, self.y
        r0 = math.hypot(x0 - cx, y0 - cy)
        r1 = math.hypot(xe - cx, ye - cy)
        if r0 < self.min_r:
            raise self.error(
                ln,
                raw,
                f"arc1: zero-radius arc (the centre ({cx:g}, {cy:g}) is the stage's position)",
            )
        if abs(r1 - r0) > self.tol:
            raise self.error(
                ln,
                raw,
                f"arc1: the end point ({xe:g}, {ye:g}) is not on the circle: it lies {r1:.6g} mm "
                "from "
                f"the centre, the start ({x0:g}, {y0:g}) {r0:.6g} mm (difference "
                f"{abs(r1 - r0) * 1000:.3g} um, "
                f"tolerance {self.tol * 1000:g} um)",
            )
        a0 = math.atan2(y0 - cy, x0 - cx)
        a1 = math.atan2(ye - cy, xe - cx)
        chord = math.hypot(xe - x0, ye - y0)
        full = chord <= self.tol
        if full and chord > _SAME_POINT_MM:  # a short arc or a full turn: both could be meant
            self.full_turns.append((ln, chord, r0))
        if direction == "+":
            sweep = TWO_PI if full else (a1 - a0) % TWO_PI
        else:
            sweep = -TWO_PI if full else -((a0 - a1) % TWO_PI)
        self._arc(cx, cy, sweep, (xe, ye), speed, source, ln, raw, implicit, "arc1")

    def _arc2(self, sw, rest, ln, raw):
        """arc2 (X,Y), cx, cy, sweep : centre and signed sweep [rad], + counter-clockwise."""
        sw, ix, iy, args, (speed, source), implicit = self._begin_segment(
            "arc2", sw, rest, ln, raw, 1
        )
        cx = self._num(args[ix], ln, raw, "the centre X")
        cy = self._num(args[iy], ln, raw, "the centre Y")
        sweep = self._num(args[2], ln, raw, "the sweep angle")
        if abs(sweep) > TWO_PI * (1 + 1e-9):
            raise self.error(
                ln,
                raw,
                f"arc2 sweeps {sweep:g} rad, more than a full turn: ACSPL+ takes the angle in "
                "radians (is it in degrees?)",
            )
        if sweep == 0.0:
            self.notes.append(f"line {ln}: arc2 with a zero sweep does not move the stage")
            if implicit:
                self.seg_open = False
            return
        self._arc(cx, cy, sweep, None, speed, source, ln, raw, implicit, "arc2")


def _distance(mm: float) -> str:
    return f"{mm:.4g} mm" if mm >= 1.0 else f"{mm * 1000:.4g} um"


def _axis_number(token) -> int | None:
    if isinstance(token, int):
        return token if token >= 0 else None
    low = str(token).strip().lower()
    if low in AXIS_NUMBERS:
        return AXIS_NUMBERS[low]
    return int(low) if low.isdigit() else None


def _positive_speed(value, name: str) -> float:
    value = float(value)
    if not (value > 0.0 and math.isfinite(value)):
        raise ValueError(f"{name} must be a positive finite speed in mm/s, got {value}")
    if value > MAX_PLATEN_SPEED_MM_S:
        raise ValueError(
            f"{name} = {value:g} mm/s is faster than any Aerosol Jet stage moves (at most "
            f"{MAX_PLATEN_SPEED_MM_S:g} mm/s)"
        )
    return value


def _plain_float(text: str) -> float | None:
    """``text`` as a plain number (None: not one). Python's float() reads ``1_0`` as 10;
    a program's number has no underscore."""
    if "_" in text:
        return None
    try:
        return float(text)
    except ValueError:
        return None


def _cut_piece(piece: tuple, fraction: float) -> tuple:
    """The first ``fraction`` of a piece (same start, earlier end)."""
    p = list(piece)
    if piece[P_KIND] == KIND_ARC:
        p[P_SWEEP] = piece[P_SWEEP] * fraction
        angle = piece[P_A0] + p[P_SWEEP]
        p[P_X1] = piece[P_CX] + piece[P_R] * math.cos(angle)
        p[P_Y1] = piece[P_CY] + piece[P_R] * math.sin(angle)
    else:
        p[P_X1] = piece[P_X0] + fraction * (piece[P_X1] - piece[P_X0])
        p[P_Y1] = piece[P_Y0] + fraction * (piece[P_Y1] - piece[P_Y0])
    p[P_LEN] = piece[P_LEN] * fraction
    p[P_T1] = piece[P_T0] + fraction * (piece[P_T1] - piece[P_T0])
    return tuple(p)


def parse_program(
    text: str,
    path: str,
    *,
    settings: ReaderSettings,
    stage: Stage,
    process_speed_mm_s: float | None = None,
    rapid_speed_mm_s: float | None = None,
    skip_unknown: bool = False,
    axes: tuple = ("X", "Y"),
    shutter_output: tuple[int, int] = (0, 0),
    start_xy: tuple[float, float] | None = None,
) -> ParsedProgram:
    """Run the program text once; see the module docstring and docs/reference/job.md.

    Raises
    ------
    ProgramError
        Unknown command (unless ``skip_unknown`` and it does not move the stage), an
        unreadable or non-finite number, an arc off its circle, a zero-radius arc, a
        segmented path that does not start where the stage is, an arc that retraces its
        neighbour, an unclosed block or path.
    """
    reader = _Reader(
        path,
        settings,
        stage,
        process_speed_mm_s,
        rapid_speed_mm_s,
        skip_unknown,
        axes,
        shutter_output,
        start_xy,
    )
    lines = text.splitlines()
    reader.run(lines)
    pieces = (
        np.array(reader.pieces, dtype=float) if reader.pieces else np.zeros((0, N_PIECE_FIELDS))
    )
    start = reader.start_xy
    if start is None and len(pieces):
        start = (float(pieces[0, P_X0]), float(pieces[0, P_Y0]))
    return ParsedProgram(
        path=path,
        n_lines=len(lines),
        pieces=pieces,
        shutter_t=np.array(reader.ev_t, dtype=float),
        shutter_open=np.array(reader.ev_open, dtype=bool),
        shutter_line=np.array(reader.ev_line, dtype=np.int64),
        mark_t=np.array(reader.mark_t, dtype=float),
        mark_line=np.array(reader.mark_line, dtype=np.int64),
        feature_t=np.array(reader.feat_t, dtype=float),
        feature_value=np.array(reader.feat_v, dtype=np.int64),
        feature_names=reader.feature_names,
        end_time_s=max(reader.tp, reader.tm),
        start_xy=start,
        speed_sources=reader.sources,
        return_source=reader.return_source if reader.return_source >= 0 else reader.rapid_default,
        notes=reader.notes,
        warnings=reader.warnings,
    )
