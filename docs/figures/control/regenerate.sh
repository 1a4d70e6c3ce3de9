#!/usr/bin/env bash
# Reproduces docs/figures/control/ (docs/validation.md, "Control"): the closed-loop comparison, target
# 65 µm, on the first truth generator (which tuned the controller) and the second (`--truth
# alt`, evaluation only), merged into one table, plus the noise-floor benchmark.
#
#   docs/figures/control/regenerate.sh            # everything, ~1 h CPU on 2 cores
#   docs/figures/control/regenerate.sh exp1 ink_running_low_alt   # some runs, then the merge
#
# One run per scenario and generator into $WORK/<run>/ (records, commands, figure), then
# `ajtwin control merge` of every run found there into this folder: metrics.json (per seed
# and summaries; NAME@alt for the second generator), metrics.md (the table) and one figure
# per run (<run>.png). Runs are independent: start several at once on a bigger machine.
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
ROOT="$(cd "$HERE/../../.." && pwd)"
AJ="${AJTWIN:-$ROOT/.venv/bin/ajtwin}"
PY="${PYTHON:-$ROOT/.venv/bin/python}"
WORK="${WORK:-$ROOT/ctl-runs}"

declare -A RUNS=(
  [exp1]="--scenario exp1 --seeds 1-5"
  [slow_clog]="--scenario slow_clog --seeds 1-5"
  [ink_running_low]="--scenario ink_running_low --seeds 1-5"
  [clean_long]="--scenario clean_long --seeds 1-2"
  [exp1_alt]="--scenario exp1 --seeds 1-5 --truth alt"
  [ink_running_low_alt]="--scenario ink_running_low --seeds 1-5 --truth alt"
)
ORDER=(exp1 slow_clog ink_running_low exp1_alt ink_running_low_alt clean_long)
[ $# -gt 0 ] && ORDER=("$@")

for run in "${ORDER[@]}"; do
  [ -n "${RUNS[$run]:-}" ] || { echo "unknown run $run (one of ${!RUNS[*]})" >&2; exit 2; }
  # a finished run (metrics.json is written when its one scenario is done) is kept: delete
  # $WORK/<run> to run it again
  if [ -f "$WORK/$run/metrics.json" ]; then echo "$run: kept ($WORK/$run)"; continue; fi
  # shellcheck disable=SC2086
  "$AJ" control simulate ${RUNS[$run]} --target-linewidth 65 --no-progress --out "$WORK/$run"
done

done_runs=()
for dir in "$WORK"/*/; do
  [ -f "$dir/metrics.json" ] || continue  # unfinished: not merged
  done_runs+=("$dir")
  png=("$dir"*.png)
  [ -e "${png[0]}" ] && cp "${png[0]}" "$HERE/$(basename "$dir").png"
done
"$AJ" control merge "${done_runs[@]}" --out "$HERE"

# PI against the twin's MPC as the printer's noise is removed (docs/explanation/control-jitter-floor.md)
if [ $# -eq 0 ]; then
  "$PY" -m ajtwin.studies.control_limits --seeds 1-5 --minutes 30 --out "$HERE/limits.json"
fi
