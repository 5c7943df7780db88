#!/usr/bin/env bash
# make screenshots: the HTML report of every kind of calibration file (each fit
# method, data in counts, each --with effect, each method's diagnosis), rendered
# by headless Chromium at 1280 px wide, as PNGs in docs/figures/report-<case>.png.
# The inputs are simulated from `calib plan make` plans (and the shipped thermal
# plan with its truth) with fixed seeds: calib_cli/validation/report_cases.py.
set -euo pipefail
cd "$(dirname "$0")/.."
out=demo_out/screenshots
rm -rf "$out"
mkdir -p "$out" docs/figures
CHROMIUM=${CHROMIUM:-$(command -v chromium || command -v chromium-browser || true)}
if [ -z "$CHROMIUM" ]; then
    echo "make screenshots: no chromium on PATH (apt-get install chromium)" >&2
    exit 3
fi
python -m calib_cli.validation.report_cases "$out" --png docs/figures
echo "== screenshots in docs/figures/ (reports in $out/)"
