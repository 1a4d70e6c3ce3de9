"""Reading ajtwin's configuration: the one TOML loader, and the safe-file checks it rests on.

Every TOML file ajtwin reads goes through this module: the data files shipped inside the
package (``ajtwin/data/*.toml``, ``cfd/sweep.toml``, ``vision/optics.toml``,
``simulation/scenarios/*.toml`` ...) with :func:`packaged_toml`, and the files a user
hands over (a scenario, a parameter or alias file, a calibration) with :func:`read_toml`;
:func:`load_toml` is the usual "the user's file if given, else the packaged one". Errors
name the file (and the line, for text that is not UTF-8).

A path given on the command line can be anything the file system holds: a directory, a
FIFO (opening it blocks until a writer appears — a hang), ``/dev/zero`` (an endless
read), or a file far larger than any print record or scenario. :func:`check_regular_file`
refuses all of these before a single byte is read, with a message naming the path;
:func:`read_bounded_bytes` and :func:`read_toml` then read at most the stated size.
Parameters of the checks are the caller's (a scenario is kilobytes, a record may be a
week of 1 Hz samples), so each reader passes its own ``max_bytes``.

Examples
--------
>>> import tempfile, pathlib
>>> path = pathlib.Path(tempfile.mkdtemp()) / "s.toml"
>>> _ = path.write_text("[scenario]\\nduration_min = 5\\n")
>>> read_toml(path, what="scenario")["scenario"]["duration_min"]
5
>>> read_toml(path.parent, what="scenario")
Traceback (most recent call last):
...
ajtwin.config.InputFileError: ... is a directory, not a scenario file
>>> packaged_toml("data/vial.toml")["format_version"]
1
"""

from __future__ import annotations

import copy
import os
import stat
import tomllib
from dataclasses import fields
from importlib import resources
from pathlib import Path

#: Largest TOML configuration (scenario, alias file) read: real ones are a few kB.
MAX_TOML_BYTES = 1 << 20


class InputFileError(ValueError):
    """A path that is not a readable regular file of acceptable size; the message names it."""


def check_regular_file(path: str | Path, what: str = "input", max_bytes: int | None = None) -> int:
    """Refuse a path that is missing, not a regular file, or larger than ``max_bytes``.

    Uses ``stat`` only (never ``open``), so a FIFO or device is refused without blocking.

    Returns
    -------
    int
        The file's size in bytes.

    Raises
    ------
    FileNotFoundError
        The path does not exist.
    InputFileError
        A directory, FIFO, socket or device, or a file larger than ``max_bytes``.
    """
    path = Path(path)
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise FileNotFoundError(f"{what} file not found: {path}") from None
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read this {what} file: {exc.strerror}") from None
    except ValueError as exc:  # e.g. a NUL byte in the path
        raise InputFileError(f"{str(path)!r}: not a usable path: {exc}") from None
    mode = info.st_mode
    if stat.S_ISDIR(mode):
        raise InputFileError(f"{path}: is a directory, not a {what} file")
    if not stat.S_ISREG(mode):
        kind = (
            "a FIFO (named pipe)"
            if stat.S_ISFIFO(mode)
            else "a device"
            if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
            else "a socket"
            if stat.S_ISSOCK(mode)
            else "not a regular file"
        )
        raise InputFileError(
            f"{path}: is {kind}, not a regular {what} file; copy the data to a file first"
        )
    if max_bytes is not None and info.st_size > max_bytes:
        raise InputFileError(
            f"{path}: {info.st_size} bytes is larger than any {what} file ajtwin reads "
            f"(limit {max_bytes} bytes)"
        )
    return int(info.st_size)


def read_bounded_bytes(path: str | Path, what: str, max_bytes: int) -> bytes:
    """The bytes of a regular file, refusing it when it is (or grows) beyond ``max_bytes``."""
    check_regular_file(path, what, max_bytes)
    with open(path, "rb") as fh:
        data = fh.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise InputFileError(
            f"{path}: larger than any {what} file ajtwin reads ({max_bytes} bytes)"
        )
    return data


def read_toml(
    path: str | Path, what: str = "configuration", max_bytes: int = MAX_TOML_BYTES
) -> dict:
    """Parse a user's TOML file after :func:`check_regular_file`; errors name the path.

    Parameters
    ----------
    path : str or Path
        The file.
    what : str
        What the file is ("scenario", "parameter" ...), for the messages.
    max_bytes : int
        Largest file read [bytes].

    Raises
    ------
    FileNotFoundError, InputFileError
        As :func:`check_regular_file`; also for text that is not UTF-8 or not valid TOML.
    """
    return parse_toml(read_bounded_bytes(path, what, max_bytes), path, what)


def parse_toml(data: bytes | str, where, what: str = "configuration") -> dict:
    """Parse TOML text (bytes must be UTF-8); errors name ``where`` (a path or a label).

    Raises
    ------
    InputFileError
        Bytes that are not UTF-8 (the message gives the line) or text that is not TOML.
    """
    if isinstance(data, bytes):
        try:
            data = data.decode("utf-8")
        except UnicodeDecodeError as exc:
            line = data[: exc.start].count(b"\n") + 1
            raise InputFileError(
                f"{where}: line {line}: not UTF-8 text (byte 0x{data[exc.start]:02x}); "
                f"a {what} file must be a UTF-8 TOML text file"
            ) from None
    # a byte-order mark (Windows Notepad writes one) is no TOML, but nothing is lost without it
    data = data.removeprefix("\ufeff")
    try:
        return tomllib.loads(data)
    except tomllib.TOMLDecodeError as exc:
        raise InputFileError(f"{where}: not valid TOML: {exc}") from None
    except RecursionError:  # tomllib recurses once per nested [ or {
        raise InputFileError(
            f"{where}: not a {what} file: its arrays or tables are nested too deeply to read"
        ) from None


def packaged_toml(name: str) -> dict:
    """A TOML file shipped inside ajtwin; ``name`` is its path in the package.

    Parameters
    ----------
    name : str
        E.g. ``"data/parameters.toml"``, ``"cfd/sweep.toml"``.

    Returns
    -------
    dict
        A new dict on every call (callers that read it often cache it themselves).
    """
    resource = resources.files("ajtwin").joinpath(*name.split("/"))
    try:
        data = resource.read_bytes()
    except FileNotFoundError:
        raise FileNotFoundError(f"ajtwin/{name}: no such packaged file") from None
    # parsed once per content: `estimate` reads transition.toml and mismatch.toml ~25 times
    # each, and a copy costs a thirtieth of a parse
    seen = _PARSED.get(name)
    if seen is None or seen[0] != data:
        seen = _PARSED[name] = (data, parse_toml(data, f"ajtwin/{name}"))
    return copy.deepcopy(seen[1])


#: packaged TOML files as read and parsed: name → (bytes, dict)
_PARSED: dict[str, tuple[bytes, dict]] = {}


def settings_from_table(cls, table: dict, overrides: dict, what: str):
    """A settings dataclass from a packaged TOML table, with keyword overrides.

    Keys of ``table`` that are not fields of ``cls`` are ignored (a table may hold several
    classes' settings); an override that is not a field is refused; ``None`` overrides are
    ignored (an option not given).

    Examples
    --------
    >>> from dataclasses import dataclass
    >>> @dataclass
    ... class Knobs:
    ...     a: float = 1.0
    ...     b: int = 2
    >>> settings_from_table(Knobs, {"a": 3.0, "c": 0}, {"b": None}, "knob")
    Knobs(a=3.0, b=2)
    """
    known = {f.name for f in fields(cls)}
    unknown = set(overrides) - known
    if unknown:
        raise TypeError(f"unknown {what} settings: {sorted(unknown)}")
    base = {k: v for k, v in table.items() if k in known}
    base.update({k: v for k, v in overrides.items() if v is not None})
    return cls(**base)


def load_toml(
    path: str | Path | None,
    packaged: str,
    what: str = "configuration",
    max_bytes: int = MAX_TOML_BYTES,
) -> dict:
    """The user's TOML file at ``path`` (:func:`read_toml`) or, when None, the packaged file
    ``packaged`` (:func:`packaged_toml`).

    Parameters
    ----------
    path : str, Path or None
        A user's file, or None for the packaged one.
    packaged : str
        Path of the packaged file inside ajtwin, e.g. ``"data/control.toml"``.
    what : str
        What the file is, for the messages.
    max_bytes : int
        Largest user file read [bytes].
    """
    if path is None:
        return packaged_toml(packaged)
    return read_toml(path, what, max_bytes)
