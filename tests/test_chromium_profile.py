"""The browser the dashboard tests and benchmarks open leaves no profile folder behind."""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest

import ajtwin.web.server as server


class _Context:
    """What launch_chromium uses of Playwright's BrowserContext: ``on`` and ``close``."""

    def __init__(self, folder: str):
        self.folder = folder
        self._on_close = []

    def on(self, event, handler):
        assert event == "close"
        self._on_close.append(handler)

    def close(self):
        for handler in self._on_close:
            handler(self)
        # chromium writes its preferences as it exits, after the "close" event
        Path(self.folder, "Default").mkdir(parents=True, exist_ok=True)
        Path(self.folder, "Default", "Preferences").write_text("{}")


class _Chromium:
    def __init__(self, fail: bool = False):
        self.fail = fail
        self.folders: list[str] = []

    def launch_persistent_context(self, folder, **_options):
        self.folders.append(folder)
        Path(folder, "Default").mkdir()  # chromium writes its profile there
        if self.fail:
            raise RuntimeError("the browser did not start")
        return _Context(folder)


class _Playwright:
    def __init__(self, fail: bool = False):
        self.chromium = _Chromium(fail)


@pytest.fixture
def chromium_binary(tmp_path, monkeypatch):
    binary = tmp_path / "chromium"
    binary.write_text("")
    monkeypatch.setattr(server, "CHROMIUM", str(binary))
    # the folders it makes go under the test's own folder, even when a test fails
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))


def test_the_profile_folder_it_made_goes_when_the_browser_closes(chromium_binary):
    playwright = _Playwright()
    context = server.launch_chromium(playwright)
    folder = Path(playwright.chromium.folders[0])
    assert folder.name.startswith("ajtwin-chromium-") and folder.is_dir()
    context.close()
    assert not folder.exists()


def test_the_profile_folder_it_made_goes_when_the_browser_fails_to_start(chromium_binary):
    playwright = _Playwright(fail=True)
    with pytest.raises(RuntimeError, match="did not start"):
        server.launch_chromium(playwright)
    assert not Path(playwright.chromium.folders[0]).exists()


def test_a_profile_folder_the_caller_gave_is_kept(chromium_binary, tmp_path):
    given = tmp_path / "profile"
    given.mkdir()
    server.launch_chromium(_Playwright(), user_data_dir=given).close()
    assert (given / "Default").is_dir()
