#!/usr/bin/env bash
# make demo-all: every method on its example plan (sample_data/plans/):
# simulate (fixed seeds) -> fit -> report, into demo_out/all/<method>/.
# Takes a few minutes (the 9-cycle turntable fit alone ~20 s); `make demo` stays quick.
set -euo pipefail
cd "$(dirname "$0")/.."
out=demo_out/all
plans=sample_data/plans
mkdir -p "$out"
run() {  # run METHOD PLAN FIT-ARGS...: simulate (with $TRUTH if set), fit, report
    local m=$1 plan=$2; shift 2
    local d="$out/$m"
    rm -rf "$d"; mkdir -p "$d"
    echo "== $m: $plan"
    calib simulate "$plan" ${TRUTH:+--truth "$TRUTH"} --out "$d/raw.h5" --seed 7
    calib fit "$@" "$d/raw.h5" --out "$d/cal.h5"
    calib report "$d/cal.h5" "$d/raw.h5" --out "$d/report"
}
echo "== static: the bundled 12-position recording (as make demo)"
mkdir -p "$out/static"
calib import csv sample_data/twelve_position.csv --plan sample_data/twelve_position.toml \
    --out "$out/static/raw.h5"
calib fit accel "$out/static/raw.h5" --out "$out/static/cal.h5"
calib report "$out/static/cal.h5" "$out/static/raw.h5" --out "$out/static/report"
run ferraris "$plans/ferraris.toml" gyro
run align "$plans/align.toml" align
run rimu "$plans/rimu.toml" rimu
run turntable-3 "$plans/turntable_3cycle.toml" turntable
run turntable-9 "$plans/turntable_9cycle.toml" turntable
TRUTH="$plans/thermal_truth.toml" run thermal "$plans/thermal.toml" thermal
echo "== done: reports in $out/*/report/report.html (and report.md)"
