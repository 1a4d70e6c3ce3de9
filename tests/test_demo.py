"""The end-to-end demo: a small real instance by default, the full one as a slow test."""

from __future__ import annotations

import re

import pytest
from click.testing import CliRunner

from ajtwin.cli.demo import demo_command


def _check_report(out):
    page = (out / "report.html").read_text(encoding="utf-8")
    # self-contained: every image is embedded, nothing is fetched
    sources = re.findall(r'src="([^"]*)"', page)
    assert len(sources) >= 6
    assert all(s.startswith("data:image/png;base64,") for s in sources)
    assert "<link" not in page and "http://" not in page and "https://" not in page
    for heading in ("Alarms", "Hidden states", "Detectors", "Forecast", "Input advice"):
        assert heading in page
    return page


def test_demo_small_instance(tmp_path):
    out = tmp_path / "demo"
    args = ["--out", str(out), "--clean-min", "2", "--fault-min", "6", "--onset-min", "3"]
    result = CliRunner().invoke(demo_command, args)
    assert result.exit_code == 0, result.output
    assert "[7/7]" in result.output and "re-ingest detected as duplicate: True" in result.output
    # the demo ends by telling how to open the dashboard on its registry
    assert f"ajtwin dashboard --store {out / 'registry.sqlite'}" in result.output
    page = _check_report(out)
    assert "nozzle starts to clog at <b>3.0 min</b>" in page
    # the clog comes with what to do about it, and the advice is for the cleaned nozzle
    assert "what to do: nozzle clogging since" in result.output
    assert "then `ajtwin machine maintain demo-aj300 --nozzle-cleaned`" in result.output
    assert "once the nozzle is cleaned" in result.output and "target reached" not in result.output
    words = re.sub(r"<img[^>]*>|<style>.*?</style>", "", page, flags=re.S)
    assert not re.search(r"\d[eE][+-]\d", words)  # numbers for people, no e-notation
    from ajtwin.store.registry import Registry

    reg = Registry(out / "registry.sqlite")
    assert reg.machine("demo-aj300")["n_prints"] == 2
    assert (out / "print2_camera.mp4").stat().st_size > 10_000


@pytest.mark.slow
def test_full_demo_detects_the_clog(tmp_path):
    out = tmp_path / "demo"
    result = CliRunner().invoke(demo_command, ["--out", str(out)])
    assert result.exit_code == 0, result.output
    _check_report(out)
    m = re.search(r"detected at [0-9.]+ min → delay ([0-9]+) s; cause: nozzle clog", result.output)
    assert m, result.output
    assert int(m.group(1)) <= 120
