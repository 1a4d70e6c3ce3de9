"""Does ``extract --job`` tell a video's own program from another? Frames against programs.

Run as ``python -m ajtwin.studies.program_match [--out docs/results/program_match/match.json]``
(a few minutes on 2 cores). Frames are rendered from a program with known truth
(:mod:`ajtwin.vision.part_render`, default nuisances) and compared with a program
(:class:`ajtwin.vision.part_extract.PartExtractor`, :class:`ajtwin.vision.program_match.
ProgramMatch`): the frames compared, those showing a line where the program prints nothing,
those with no line where it prints one, and the verdict (``agree``, ``doubtful``: a warning,
``mismatch``: a refusal).

* ``own``: the scenes of :mod:`ajtwin.studies.vision_part` (straight strokes at 0-90° under a
  camera at 0° and 30°, arcs of 3-10 linewidths, lines of 30/20 and 60/35 µm, the part with
  every situation under a camera trailing 0.3 mm, the public ``2 and 6-Au.prg``), each
  compared with the program it was printed with: every line off the program is a false alarm.
* ``clock``: the part with every situation compared with its own program at the wrong time
  (a ``--start-offset`` off by 0.05-1 s).
* ``other``: a cross of two traces filmed by a camera trailing the second (20 frames/s, 640 x
  480 px, 0.75 µm/px), compared with its own program, with another whose trace near the
  camera moves the same way (an L and a Z), and with its second trace only.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import numpy as np

from ajtwin.job import read_program, read_program_text
from ajtwin.studies.vision_part import (
    PUBLIC,
    SEEDS,
    SIZE,
    arc_program,
    part_program,
    pass_times,
    straight_program,
)
from ajtwin.vision.camera import Camera
from ajtwin.vision.part_extract import PartExtractor
from ajtwin.vision.part_render import PartRenderer, PrintTruth
from ajtwin.vision.program_match import ProgramMatch

CROSS = (
    "ptp/ev (X,Y),0,0,10\nOUT0.0=1\nptp/e (X,Y),3,0\nOUT0.0=0\n"
    "ptp/ev (X,Y),1.5,-1.5,10\nOUT0.0=1\nptp/e (X,Y),1.5,1.5\nOUT0.0=0\n"
)
L_AND_Z = (
    "ptp/ev (X,Y),0,0,10\nOUT0.0=1\nwait 2\nMSEG (X,Y),0,0\nline (X,Y),3,0\nline (X,Y),3,3\n"
    "line (X,Y),0,3\nENDS (X,Y)\ntill (^X_AST.#MOVE) & (^Y_AST.#MOVE)\nOUT0.0=0\nwait 2\n"
    "ptp/ev (X,Y),0,1,10\nOUT0.0=1\nwait 2\nptp/e (X,Y),2,1\nptp/e (X,Y),2,2\n"
    "till (^X_AST.#MOVE) & (^Y_AST.#MOVE)\nOUT0.0=0\n"
)
SECOND_ONLY = CROSS.replace("OUT0.0=1\nptp/e (X,Y),3,0\n", "ptp/e (X,Y),3,0\n", 1)


def compare(filmed, program, camera, times, seed=0, shift_s=0.0, line=(43.0, 29.0)) -> dict:
    """Frames of ``filmed`` at ``times`` compared with ``program`` at ``times + shift_s``."""
    renderer = PartRenderer(filmed, camera, PrintTruth.constant(filmed.duration_s, *line),
                            seed=seed)  # fmt: skip
    extractor = PartExtractor(program, camera)
    match = ProgramMatch()
    readings = 0
    for index, t in enumerate(times):
        result = extractor.process(renderer.frame(t), index=index, time_s=t + shift_s)
        readings += result.n_readings
        match.add_frame(result)
    return {
        "frames": match.frames,
        "off_program": match.foreign_frames,
        "missing": match.missing_frames,
        "disagreeing": match.disagreeing,
        "readings": readings,
        "verdict": match.verdict,
    }


def _merged(rows) -> dict:
    out = {k: sum(r[k] for r in rows) for k in ("frames", "off_program", "missing",
                                                 "disagreeing", "readings")}  # fmt: skip
    verdicts = [r["verdict"] for r in rows]
    out["verdict"] = max(verdicts, key=("agree", "doubtful", "mismatch").index)
    return out


def _own(text, camera, line=(43.0, 29.0)) -> dict:
    job = read_program_text(text, process_speed_mm_s=2.0)
    times = pass_times(job)
    return _merged([compare(job, job, camera, times, seed, line=line) for seed in SEEDS])


def own() -> dict:
    """Every scene of the vision_part study against its own program."""
    rows = {}
    for rotation in (0.0, 30.0):
        camera = Camera(um_per_px=0.75, rotation_deg=rotation, **SIZE)
        rows[f"straight strokes 0-90° (7 angles), camera {rotation:g}°"] = _merged(
            [_own(straight_program(angle), camera) for angle in (0, 15, 30, 45, 60, 75, 90)]
        )
    camera = Camera(um_per_px=0.75, **SIZE)
    rows["arcs of 3, 5 and 10 linewidths"] = _merged(
        [_own(arc_program(factor * 0.043), camera) for factor in (3, 5, 10)]
    )
    rows["lines 30/20 and 60/35 µm"] = _merged(
        [_own(straight_program(20.0), camera, line) for line in ((30.0, 20.0), (60.0, 35.0))]
    )
    trailing = Camera(um_per_px=0.75, offset_mm=(-0.3, 0.0), **SIZE)
    job = read_program_text(part_program(), process_speed_mm_s=2.0)
    times = np.linspace(0.2, job.duration_s, 120)
    rows["part with every situation, 2 seeds x 120 frames"] = _merged(
        [compare(job, job, trailing, times, seed) for seed in SEEDS[:2]]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        public = read_program(PUBLIC / "2 and 6-Au.prg")
    times = np.linspace(1.0, public.duration_s, 150)
    rows["public 2 and 6-Au.prg, 150 frames"] = compare(public, public, trailing, times)
    return rows


def clock() -> dict:
    """The part with every situation against its own program with the clock off."""
    trailing = Camera(um_per_px=0.75, offset_mm=(-0.3, 0.0), **SIZE)
    job = read_program_text(part_program(), process_speed_mm_s=2.0)
    times = np.linspace(1.2, job.duration_s - 1.2, 60)
    return {
        f"part, clock {shift:+g} s": compare(job, job, trailing, times, shift_s=shift)
        for shift in (0.0, 0.05, -0.1, 0.1, 0.2, -0.3, 0.3, 1.0)
    }


def other() -> dict:
    """A cross against its own program, an L and a Z, and its second trace only."""
    camera = Camera(um_per_px=0.75, offset_mm=(0.1, -0.25), width_px=640, height_px=480)
    cross = read_program_text(CROSS, process_speed_mm_s=2.0)
    rows = {}
    for span, times in (
        ("18 frames from 2.3 s", 2.3 + np.arange(18) / 20.0),
        ("60 frames from 0.1 s", 0.1 + np.arange(60) / 20.0),
    ):
        for name, text in (("its own", CROSS), ("an L and a Z", L_AND_Z),
                           ("its second trace only", SECOND_ONLY)):  # fmt: skip
            program = read_program_text(text, process_speed_mm_s=2.0)
            rows[f"cross, {span}, against {name}"] = compare(cross, program, camera, times)
    return rows


def table(results: dict) -> str:
    """The results as the Markdown table of docs/validation.md."""
    lines = [
        "| case | frames compared | with a line off the program | without a trace the program "
        "prints | verdict |",
        "|---|---|---|---|---|",
    ]
    for group in ("own", "clock", "other"):
        for name, r in results[group].items():
            lines.append(
                f"| {name} | {r['frames']} | {r['off_program']} | {r['missing']} | {r['verdict']} |"
            )
    return "\n".join(lines)


def main(argv=None) -> dict:
    """Run the study, write its JSON and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/results/program_match/match.json"))
    args = parser.parse_args(argv)
    start = time.perf_counter()
    results = {"own": own(), "clock": clock(), "other": other()}
    results["seconds"] = round(time.perf_counter() - start, 1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2))
    print(table(results))
    print(f"wrote {args.out} ({results['seconds']} s)")
    return results


if __name__ == "__main__":
    main()
