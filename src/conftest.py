"""The docstring examples of ``src/ajtwin`` run as doctests in the suite (``--doctest-modules``).

Each example runs in a fresh temporary folder. An example that reads a file a user would
have — ``print.parquet``, ``print.csv`` — finds a small one there, made for it (a 2-min
print from the virtual printer; a three-row CSV log), so the example reads as a user would
write it and still runs in a second or two.

This file sits beside the package, not in it: it is not installed with ajtwin.
"""

from __future__ import annotations

import os

import pytest

#: the columns of a live CSV log as a machine writes it: time, the inputs, the outputs
CSV_COLUMNS = (
    "time_s,atomizer_current_mA,carrier_flow_sccm,sheath_flow_sccm,carrier_pressure_Pa,"
    "sheath_pressure_Pa,linewidth_um,overspray_um,material_flow_mL_s"
)


def _print_csv(path, seconds: int = 40) -> None:
    """A machine's log of ``seconds`` s (more than the reader holds back to judge its
    columns): the inputs steady, the outputs moving by their gauges' steps."""
    rows = [CSV_COLUMNS]
    for t in range(seconds):
        wobble = (t * 3 + 2) % 5 - 2  # 0 at the start, -2 … 2: no gauge looks stuck
        rows.append(
            f"{t},375,23,50,{5661.3 + 0.4 * wobble:.1f},{5641.2 - 0.3 * wobble:.1f},"
            f"{43.2 + 0.1 * wobble:.1f},{29.1 - 0.1 * wobble:.1f},{1.5e-08 + 1e-10 * wobble:.3e}"
        )
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")


def _print_parquet(path) -> None:
    from ajtwin.io.records import write_record
    from ajtwin.simulation import simulate

    write_record(simulate("exp1", seed=1, duration_min=2), path)


def _print_mp4(path) -> None:
    """The alignment camera's video of a 6-s print (6 frames, 1280 x 1024)."""
    from ajtwin.simulation import simulate
    from ajtwin.vision.record_render import render_record_video

    render_record_video(simulate("exp1", seed=1, duration_min=0.1), path, progress=False)


#: file name an example may open → how to make a small one
INPUTS = {
    "print.parquet": _print_parquet,
    "print.mp4": _print_mp4,
    "print.csv": _print_csv,
}


@pytest.fixture(autouse=True)
def _doctest_folder(request, tmp_path):
    """Doctests run in their own temporary folder, with the inputs their text names."""
    # every item under src/ is a doctest (the tests live in tests/)
    text = "\n".join(example.source for example in request.node.dtest.examples)
    for name, make in INPUTS.items():
        if name in text:
            make(tmp_path / name)
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        yield
    finally:
        os.chdir(cwd)
