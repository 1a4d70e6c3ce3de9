"""Every page a person reads, at 1400 px wide, free of layout faults: ``scripts/screenshots.py``
run whole (the demo's report, a part report, the dashboard's fleet, machine, part-map and
what-if pages), as ``make screenshots`` runs it.

Slow (a short demo and a job print through the command line, ~1 min): the default suite checks
the dashboard's pages with the same :func:`ajtwin.web.server.layout_faults` in
``tests/test_web_browser.py`` and ``tests/test_part_map_web.py``.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import pytest

from ajtwin.web.server import CHROMIUM

ROOT = Path(__file__).resolve().parents[1]
pytest.importorskip("playwright.sync_api")
pytestmark = pytest.mark.skipif(not Path(CHROMIUM).exists(), reason="run `make chromium`")


def _script():
    spec = importlib.util.spec_from_file_location(
        "screenshots", ROOT / "scripts" / "screenshots.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_every_page_at_1400_px_has_no_overflow_clipped_text_or_empty_box(tmp_path):
    shots = _script()
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"), JAX_PLATFORMS="cpu")
    inputs = shots.build(tmp_path / "work", env)
    problems = shots.screenshots(inputs, tmp_path / "shots", env)
    assert set(problems) == {
        "demo_report", "part_report", "fleet", "machine_demo", "machine_part_map",
        "machine_mismatch", "whatif",
    }  # fmt: skip
    assert all((tmp_path / "shots" / f"{name}.png").stat().st_size > 10_000 for name in problems)
    assert problems == {name: [] for name in problems}
