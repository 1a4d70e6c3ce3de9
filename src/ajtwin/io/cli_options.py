"""Click options shared by every command that joins video-derived values onto a print record."""

from __future__ import annotations

from pathlib import Path

import click


def join_options(filled: str, suffix: str, must_exist: bool = False):
    """``--join/--join-out/--start-offset/--camera-offset`` for a video reader.

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
            type=float,
            default=0.0,
            show_default=True,
            help="Print time (s) of the first video frame.",
        ),
        click.option(
            "--camera-offset",
            "camera_offset_um",
            type=float,
            default=0.0,
            show_default=True,
            help="Distance from nozzle to the camera's view centre along the print, µm.",
        ),
    ]

    def decorate(command):
        for option in reversed(options):
            command = option(command)
        return command

    return decorate
