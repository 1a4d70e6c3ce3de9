"""Screenshots of every page a person reads, at 1400 px wide, each checked for layout faults.

    python scripts/screenshots.py --out build/screenshots/now
    python scripts/screenshots.py --out build/screenshots/main --rev main   # another commit

Makes, through the command line, a short demo (its report and registry), a short job print
of a public program with a clog (its part report, and stored with its job in the same
registry), then opens in Debian's chromium (Playwright) at 1400 × 900 px: the demo report, the
part report, the dashboard's fleet page, the demo machine's page (its prints were stored
without a program), the job machine's page (its part map), the page of a machine the model
does not fit (a model–machine mismatch) and the what-if page. Each page
is saved whole as ``NAME.png`` and checked (:func:`ajtwin.web.server.layout_faults`): nothing
wider than the
window, no chart text outside its chart or under its toolbar, no empty box and no broken
image. The faults found are written to ``problems.json`` and printed.

``--rev REV`` runs the commands and the dashboard of another commit (its ``src/`` exported
under ``build/``), the browser and these checks staying the same: before/after pictures.
``tests/test_page_layout.py`` runs the same on the current tree and asserts no fault.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROGRAM = ROOT / "tests" / "data" / "prg" / "prg2svg" / "1-nafbot.prg"
WIDTH, HEIGHT = 1400, 900
#: the job print: 6 min of the public program, the nozzle clogging from minute 3
JOB_SCENARIO = """[scenario]
description = "nozzle clog from 3 min, for the screenshots"
duration_min = 6.0
[fault]
kind = "nozzle_clog"
onset_min = 3.0
nozzle_deposition_multiplier = 50.0
"""


def ajtwin(*args, cwd: Path, env: dict) -> str:
    """One ``ajtwin`` command (of the tree ``env``'s PYTHONPATH names); its output."""
    done = subprocess.run(
        [sys.executable, "-m", "ajtwin.cli", *map(str, args)],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    if done.returncode != 0:
        raise RuntimeError(f"ajtwin {' '.join(map(str, args))}:\n{done.stdout}\n{done.stderr}")
    return done.stdout


def build(work: Path, env: dict) -> dict:
    """The inputs of the pages, made in ``work`` by the command line: the demo's report and
    registry, a job print's part report, the job print stored in the same registry, and a
    print of a machine the model does not fit (its guard fires).

    Returns the paths: ``registry``, ``demo_report``, ``part_report``."""
    work.mkdir(parents=True, exist_ok=True)
    demo = work / "demo"
    ajtwin("demo", "--out", demo, "--clean-min", "2", "--fault-min", "6", "--onset-min", "3",
           cwd=work, env=env)  # fmt: skip
    registry = demo / "registry.sqlite"
    scenario = work / "clog_at_3_min.toml"
    scenario.write_text(JOB_SCENARIO, encoding="utf-8")
    record = work / "job.parquet"
    ajtwin("simulate", "--job", PROGRAM, "--scenario", scenario, "--seed", "1", "--out", record,
           cwd=work, env=env)  # fmt: skip
    tolerance = "74+-3"
    ajtwin("machine", "add", "lab-part", "--store", registry, cwd=work, env=env)
    ajtwin("ingest", "--machine", "lab-part", "--job", PROGRAM, "--tolerance", tolerance,
           "--store", registry, record, cwd=work, env=env)  # fmt: skip
    ajtwin("job", "report", record, "--job", PROGRAM, "--tolerance", tolerance, "--out",
           work / "part", cwd=work, env=env)  # fmt: skip
    # a machine unlike the nominal one, never commissioned: the model–machine guard fires
    other = work / "other_machine.parquet"
    ajtwin("simulate", "--scenario", "exp1", "--seed", "5", "--duration-min", "6",
           "--machine-seed", "1", "--out", other, cwd=work, env=env)  # fmt: skip
    ajtwin("machine", "add", "lab-mismatch", "--store", registry, cwd=work, env=env)
    ajtwin("ingest", "--machine", "lab-mismatch", "--store", registry, other, cwd=work, env=env)
    return {
        "registry": registry,
        "demo_report": demo / "report.html",
        "part_report": work / "part" / "report.html",
    }


#: (page name, what the page's script has finished when it is ready; JS, None: at load)
DASHBOARD_PAGES = (
    ("fleet", "/", None),
    ("machine_demo", "/machine/demo-aj300", "window.__ajtwin.drawnPrint >= 1"),
    ("machine_part_map", "/machine/lab-part",
     "window.__ajtwin.part && window.__ajtwin.part.portions > 0"),
    ("machine_mismatch", "/machine/lab-mismatch", "window.__ajtwin.drawnPrint >= 1"),
    ("whatif", "/whatif/demo-aj300", None),
)  # fmt: skip


def shoot(page, url: str, ready: str | None, png: Path) -> list[str]:
    from ajtwin.web.server import layout_faults

    """Open ``url``, wait until ``ready`` (bounded), settle, save ``png``; its faults."""
    page.goto(url)
    if ready:
        page.wait_for_function(ready, timeout=180_000)
    page.wait_for_load_state("networkidle", timeout=60_000)
    time.sleep(1.0)  # plotly's relayout after the first draw
    page.screenshot(path=str(png), full_page=True)
    return layout_faults(page)


def screenshots(inputs: dict, out: Path, env: dict) -> dict:
    """Every page saved under ``out`` as NAME.png; {name: [faults]}."""
    from playwright.sync_api import sync_playwright

    from ajtwin.web.server import DashboardProcess, launch_chromium

    out.mkdir(parents=True, exist_ok=True)
    problems = {}
    saved = dict(os.environ)
    os.environ.clear()
    os.environ.update(env)  # the dashboard runs the commit under test
    try:
        with DashboardProcess(inputs["registry"], log_path=out / "dashboard.log") as dash:
            with sync_playwright() as p:
                browser = launch_chromium(p)
                try:
                    page = browser.new_page()
                    page.set_viewport_size({"width": WIDTH, "height": HEIGHT})
                    for name, key in (("demo_report", "demo_report"),
                                      ("part_report", "part_report")):  # fmt: skip
                        url = Path(inputs[key]).resolve().as_uri()
                        problems[name] = shoot(page, url, None, out / f"{name}.png")
                    for name, path, ready in DASHBOARD_PAGES:
                        problems[name] = shoot(
                            page, dash.page_url(path), ready, out / f"{name}.png"
                        )
                finally:
                    browser.close()
    finally:
        os.environ.clear()
        os.environ.update(saved)
    (out / "problems.json").write_text(json.dumps(problems, indent=1), encoding="utf-8")
    return problems


def tree_of(rev: str | None) -> Path:
    """The source tree of ``rev`` (None: this one): its src/ exported once under build/
    (``git archive``: nothing is checked out, no worktree is registered)."""
    if rev is None:
        return ROOT
    commit = subprocess.run(["git", "rev-parse", "--short", rev], cwd=ROOT, check=True,
                            capture_output=True, text=True).stdout.strip()  # fmt: skip
    tree = ROOT / "build" / f"tree-{commit}"
    if not (tree / "src").is_dir():
        tree.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "archive", commit, "src"], cwd=ROOT, check=True,
                                 capture_output=True).stdout  # fmt: skip
        subprocess.run(["tar", "-x", "-C", str(tree)], input=archive, check=True)
    return tree


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "build" / "screenshots" / "now")
    parser.add_argument("--rev", default=None, help="another commit's pages (git revision)")
    args = parser.parse_args(argv)
    tree = tree_of(args.rev)
    env = dict(os.environ, PYTHONPATH=str(tree / "src"), JAX_PLATFORMS="cpu")
    out = args.out.resolve()
    print(f"screenshots of {args.rev or 'this tree'} ({tree}) → {out}", flush=True)
    started = time.monotonic()
    inputs = build(out / "work", env)
    problems = screenshots(inputs, out, env)
    for name, found in problems.items():
        print(f"{name + '.png':<22} " + ("ok" if not found else "; ".join(found)))
    print(f"done in {time.monotonic() - started:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
