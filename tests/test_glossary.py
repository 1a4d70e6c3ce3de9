"""The glossary: the words the tool uses, in plain words, linked from the top-level help."""

from __future__ import annotations

import re
from pathlib import Path

from click.testing import CliRunner

from ajtwin.apps.detection.causes import CAUSES, _advice, detector_words
from ajtwin.apps.detection.settings import CUSUM_CHANNELS
from ajtwin.cli import main

ROOT = Path(__file__).resolve().parents[1]
GLOSSARY = "docs/explanation/glossary.md"


def test_the_top_level_help_points_to_the_glossary_which_explains_the_jargon():
    result = CliRunner().invoke(main, ["--help"])
    assert result.exit_code == 0 and GLOSSARY in " ".join(result.output.split())
    page = (ROOT / GLOSSARY).read_text(encoding="utf-8")
    for word in ("θ", "NIS", "EM", "CUSUM", "EKF", "ΔR_N", "φ_A", "deposit push", "P_c+P_s"):
        assert re.search(rf"\*\*[^*]*{re.escape(word)}[^*]*\*\*", page), word
    assert GLOSSARY.removeprefix("docs/") in (ROOT / "mkdocs.yml").read_text(encoding="utf-8")


def test_every_cause_and_detector_has_words_and_a_fault_an_action():
    causes = _advice()["causes"]
    assert set(causes) == set(CAUSES)
    for key, entry in causes.items():
        assert entry["words"] and entry["status"], key
        if entry["fault"]:
            assert "ajtwin machine maintain {machine}" in entry["action"], key
    # the CUSUM labels as the detector writes them (a minus sign, not a hyphen, for falling)
    cusums = [f"cusum{sign} {channel}" for channel in CUSUM_CHANNELS for sign in "+−"]
    for label in (*cusums, "windowed NIS", "deposit push ΔR_N", "V_l low",
                  "ΔR_N beyond the model's range"):  # fmt: skip
        words = detector_words(label)
        assert words.endswith(f"({label})") and len(words) > len(label) + 3, label
