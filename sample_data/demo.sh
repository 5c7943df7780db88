#!/usr/bin/env bash
# make demo: a full static calibration of the bundled sample recording.
set -euo pipefail
cd "$(dirname "$0")/.."
out=demo_out
mkdir -p "$out"
echo "== import: detect the 12 static positions and tag them with the plan"
calib import csv sample_data/twelve_position.csv --plan sample_data/twelve_position.toml --out "$out/raw.h5"
echo "== fit: least squares of A = b + K f over the 12 known attitudes"
calib fit accel "$out/raw.h5" --out "$out/cal.h5"
echo "== apply: f = K^-1 (A - b), sample by sample"
calib apply "$out/cal.h5" "$out/raw.h5" --out "$out/corrected.h5"
echo "== show: the calibration, with sigma and the per-position |g| table"
calib show "$out/cal.h5"
calib show "$out/cal.h5" --json > "$out/cal.json"
echo "== done: outputs in $out/ (raw.h5, cal.h5, corrected.h5, cal.json)"
