"""Run every benchmark (benchmarks/bench_*.py) and collect their figures.

Each bench module defines ``main() -> dict`` returning named figures (with units
in the names); this runner prints them and writes ``benchmarks/results.json``.
Figures are measured on whatever machine runs them; the note in each result
says what was timed.
"""

from __future__ import annotations

import importlib.util
import json
import platform
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main(selected: list[str]) -> int:
    results = {"machine": platform.platform(), "python": sys.version.split()[0], "benches": {}}
    failed = []
    for path in sorted(HERE.glob("bench_*.py")):
        name = path.stem.removeprefix("bench_")
        if selected and name not in selected:
            continue
        print(f"== {name}", flush=True)
        spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(spec)
        t0 = time.perf_counter()
        try:
            spec.loader.exec_module(module)
            # a bench with its own options reads none of run_all's argv (its defaults)
            argv, sys.argv = sys.argv, [str(path)]
            try:
                figures = module.main()
            finally:
                sys.argv = argv
        except (Exception, SystemExit) as exc:  # a broken bench must not hide the others
            print(f"   FAILED: {type(exc).__name__}: {exc}", flush=True)
            failed.append(name)
            continue
        figures["bench_wall_s"] = round(time.perf_counter() - t0, 2)
        for key, value in figures.items():
            print(f"   {key}: {value}", flush=True)
        results["benches"][name] = figures
    (HERE / "results.json").write_text(json.dumps(results, indent=2))
    print(f"wrote {HERE / 'results.json'}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
