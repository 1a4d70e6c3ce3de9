"""Run the dashboard in a child process (tests, benchmarks, scripts) and a headless browser.

:class:`DashboardProcess` starts ``ajtwin dashboard`` on 127.0.0.1 and a free port, waits
(bounded) until it answers, and stops it by its own PID. :func:`launch_chromium` opens
Debian's ``/usr/bin/chromium`` through Playwright (``playwright install`` cannot download
a browser here) with a fresh user-data folder and no background networking.

Example
-------
>>> with DashboardProcess("registry.sqlite") as dash:            # doctest: +SKIP
...     print(dash.url)
http://127.0.0.1:40123/
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

from ajtwin.web.access import TOKEN_ENV, check_access
from ajtwin.web.app import create_app
from ajtwin.web.websocket import SERVER_OPTIONS

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class DashboardProcess:
    """``ajtwin dashboard`` in a child process on 127.0.0.1 (module docstring).

    Parameters
    ----------
    store : registry path
    token : str, optional, passed in ``$AJTWIN_DASHBOARD_TOKEN`` (never on the command line)
    extra_args : list of str, more ``ajtwin dashboard`` options
    startup_timeout_s : float, bound on the wait for the first answer
    log_path : where the server's output goes (default: a temporary file)
    """

    def __init__(
        self,
        store,
        *,
        token: str | None = None,
        extra_args=(),
        startup_timeout_s: float = 120.0,
        log_path=None,
    ):
        self.store = str(store)
        self.token = token
        self.port = free_port()
        self.host = "127.0.0.1"
        self.url = f"http://{self.host}:{self.port}/"
        self.extra_args = list(extra_args)
        self.startup_timeout_s = float(startup_timeout_s)
        self.log_path = Path(log_path) if log_path else Path(tempfile.mkstemp(suffix=".log")[1])
        self.proc: subprocess.Popen | None = None

    def start(self) -> DashboardProcess:
        """Start ``ajtwin dashboard`` as a child process and wait (bounded) until it answers."""
        cmd = [sys.executable, "-m", "ajtwin.cli", "dashboard", "--store", self.store]
        cmd += ["--host", self.host, "--port", str(self.port), *self.extra_args]
        env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONUNBUFFERED="1")
        env.pop(TOKEN_ENV, None)
        if self.token:  # in the environment: a command line is visible to every user
            env[TOKEN_ENV] = self.token
        self._log = open(self.log_path, "wb")  # noqa: SIM115 (closed in stop)
        self.proc = subprocess.Popen(cmd, stdout=self._log, stderr=subprocess.STDOUT, env=env)
        deadline = time.monotonic() + self.startup_timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(
                    f"dashboard exited with {self.proc.returncode}: {self.log_path.read_text()}"
                )
            try:
                self.get("api/fleet", timeout=2.0)
                return self
            except (urllib.error.URLError, ConnectionError, TimeoutError):
                time.sleep(0.2)
        self.stop()
        raise TimeoutError(f"dashboard did not answer within {self.startup_timeout_s:g} s")

    def get(self, path: str, timeout: float = 10.0, token: str | None = None):
        """(status, body bytes) of GET ``path``; the server's token unless ``token`` says."""
        req = urllib.request.Request(self.url + path.lstrip("/"))
        use = self.token if token is None else token
        if use:
            req.add_header("Authorization", f"Bearer {use}")
        try:
            with urllib.request.urlopen(req, timeout=timeout) as r:
                return r.status, r.read()
        except urllib.error.HTTPError as exc:
            return exc.code, exc.read()

    def page_url(self, path: str = "") -> str:
        """Address a browser opens (carries the token once; the server sets a cookie)."""
        url = self.url + path.lstrip("/")
        if self.token:
            url += ("&" if "?" in url else "?") + f"token={self.token}"
        return url

    def stop(self, timeout_s: float = 15.0) -> None:
        """Stop the child by its PID (SIGTERM, then SIGKILL after ``timeout_s``)."""
        if self.proc is not None and self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                os.kill(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=timeout_s)
        if getattr(self, "_log", None) is not None:
            self._log.close()
            self._log = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


class BackgroundServer:
    """The dashboard served from a thread of the calling process (a live engine's).

    ``ajtwin live … --dashboard`` runs its twin in its own process; it creates a
    :class:`~ajtwin.web.publisher.LivePublisher`, starts this, and calls
    ``publisher.publish(sample)`` for every sample. Same access rule as the CLI: another
    host than the loopback needs a token.

    Parameters
    ----------
    store : registry path; publisher : LivePublisher
    host, port, token : as ``ajtwin dashboard`` (port 0: a free one)
    startup_timeout_s : bound on the wait until it listens
    """

    def __init__(self, store, publisher, *, host="127.0.0.1", port=8050, token=None,
                 startup_timeout_s: float = 30.0):  # fmt: skip
        import uvicorn

        check_access(host, token)
        self.port = free_port() if not port else int(port)
        self.url = f"http://{host}:{self.port}/"
        app = create_app(store, token=token, publisher=publisher)

        config = uvicorn.Config(
            app, host=host, port=self.port, log_level="warning", **SERVER_OPTIONS
        )
        self._server = uvicorn.Server(config)
        self._thread = threading.Thread(target=self._server.run, name="dashboard", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + startup_timeout_s
        while not self._server.started:
            if time.monotonic() > deadline or not self._thread.is_alive():
                self.stop()
                raise RuntimeError(f"dashboard did not start on {host}:{self.port}")
            time.sleep(0.05)

    def stop(self, timeout_s: float = 10.0) -> None:
        """Stop serving; an open page's websocket must not keep the thread alive.

        A graceful exit waits for open connections (a page left open never closes its
        websocket), so after half the bound uvicorn is told to exit without waiting.
        """
        self._server.should_exit = True
        self._thread.join(min(1.0, timeout_s / 2))
        if self._thread.is_alive():
            self._server.force_exit = True
            self._thread.join(timeout_s)
        if self._thread.is_alive():
            raise RuntimeError(f"dashboard on port {self.port} did not stop in {timeout_s:g} s")


def launch_chromium(playwright, user_data_dir=None):
    """A headless Debian chromium (persistent context in a fresh user-data folder).

    Returns the Playwright BrowserContext; close it when done. A user-data folder this call
    made is removed when the context closes (or when the browser fails to start).
    """
    if not Path(CHROMIUM).exists():
        raise FileNotFoundError(f"{CHROMIUM} not found: run `make chromium`")
    made = None if user_data_dir else tempfile.mkdtemp(prefix="ajtwin-chromium-")
    try:
        context = playwright.chromium.launch_persistent_context(
            str(user_data_dir or made),
            executable_path=CHROMIUM,
            args=CHROMIUM_ARGS,
            headless=True,
            viewport={"width": 1400, "height": 900},
        )
    except BaseException:
        if made:
            shutil.rmtree(made, ignore_errors=True)
        raise
    if made:
        # a profile is ~1 MB of files: every browser test left one behind. Removed once
        # close() has returned (chromium writes its preferences as it exits, after the
        # context's "close" event), and on that event too if the browser went by itself.
        close = context.close

        def close_and_remove(*args, **kwargs):
            try:
                return close(*args, **kwargs)
            finally:
                shutil.rmtree(made, ignore_errors=True)

        context.close = close_and_remove
        context.on("close", lambda _context: shutil.rmtree(made, ignore_errors=True))
    return context


# ---------------------------------------------------------------- a page's layout, checked
#: a page's layout faults as sentences (run in the page by :func:`layout_faults`)
LAYOUT_FAULTS_JS = r"""() => {
  const out = [];
  const W = window.innerWidth;
  const name = (e) => e.tagName.toLowerCase() + (e.id ? "#" + e.id : "") +
    (e.classList.length ? "." + [...e.classList].join(".") : "");
  const meets = (p, q) => Math.min(p.right, q.right) > Math.max(p.left, q.left) + 1 &&
    Math.min(p.bottom, q.bottom) > Math.max(p.top, q.top) + 1;
  const shown = (e) => e.getClientRects().length > 0 && getComputedStyle(e).visibility !== "hidden";
  const page = document.documentElement.scrollWidth;
  if (page > W + 1) out.push(`the page is ${page} px wide in a ${W}-px window`);
  for (const e of document.querySelectorAll("body *")) {
    const r = e.getBoundingClientRect();
    if (shown(e) && r.width > 0 && r.right > W + 1) {
      out.push(`${name(e)} runs past the window's right edge (to ${Math.round(r.right)} px)`);
      break;
    }
  }
  for (const chart of document.querySelectorAll(".js-plotly-plot")) {
    const box = chart.getBoundingClientRect();
    const bar = chart.querySelector(".modebar");
    const tools = bar ? bar.getBoundingClientRect() : null;
    for (const t of chart.querySelectorAll(".cbtitle, .gtitle, .xtitle, .ytitle, .legendtext")) {
      const r = t.getBoundingClientRect();
      if (!r.width || !t.textContent.trim()) continue;
      const label = `"${t.textContent.trim().slice(0, 40)}" of ${name(chart)}`;
      if (r.left < box.left - 1 || r.right > box.right + 1 || r.top < box.top - 1 ||
          r.bottom > box.bottom + 1) out.push(`${label} is cut by its chart's edge`);
      if (tools && tools.width && meets(r, tools)) {
        out.push(`${label} is under the chart's toolbar`);
      }
    }
  }
  for (const e of document.querySelectorAll("img")) {
    if (shown(e) && (!e.complete || e.naturalWidth === 0)) out.push(`broken image ${name(e)}`);
  }
  for (const e of document.querySelectorAll(".plot, .card, .plots > div, figure, section")) {
    if (!shown(e)) continue;
    const r = e.getBoundingClientRect();
    if (r.height < 60) continue;
    const held = e.innerText.trim() || e.querySelector("svg, canvas, img, video, table");
    const size = `${Math.round(r.width)} × ${Math.round(r.height)}`;
    if (!held) out.push(`${name(e)} is an empty ${size}-px box`);
  }
  return out;
}"""


def layout_faults(page) -> list[str]:
    """What is wrong with the layout of the page open in ``page`` (a Playwright page), in
    sentences; [] when nothing: no horizontal overflow of the window, no chart title, axis
    title or legend text cut by its chart's edge or under its toolbar, no broken image, no
    empty box (a chart, card or section ≥ 60 px high holding nothing). The browser tests
    and ``scripts/screenshots.py`` check every page with it."""
    return list(page.evaluate(LAYOUT_FAULTS_JS))
