#!/usr/bin/env bash
# make screenshots: the HTML report of every method, rendered by headless
# Chromium at 1280 px wide, as PNGs in docs/figures/report-<method>.png.
# The inputs are simulated from `calib plan make` plans with fixed seeds.
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
plan() { calib -q plan make "$@"; }
plan static --out "$out/static.toml"
plan ferraris --out "$out/ferraris.toml"
plan align --duration 30 --out "$out/align.toml"
plan turntable --duration 60 --out "$out/turntable.toml"
plan rimu --out "$out/rimu.toml"
for p in static ferraris align turntable rimu; do
    calib -q simulate "$out/$p.toml" --out "$out/$p.h5" --seed 7
done
calib -q fit accel "$out/static.h5" --out "$out/accel.cal.h5"
calib -q fit gyro "$out/ferraris.h5" --out "$out/gyro.cal.h5"
calib -q fit align "$out/align.h5" --out "$out/align.cal.h5"
calib -q fit turntable "$out/turntable.h5" --out "$out/turntable.cal.h5"
calib -q fit rimu "$out/rimu.h5" --out "$out/rimu.cal.h5"
for pair in accel:static gyro:ferraris align:align turntable:turntable rimu:rimu; do
    m=${pair%%:*}; raw=${pair##*:}
    calib -q report "$out/$m.cal.h5" "$out/$raw.h5" --out "$out/report-$m"
    profile=$(mktemp -d)
    # a fresh profile, no network, no GPU, no sandbox (containers), no first-run UI
    "$CHROMIUM" --headless --no-sandbox --disable-gpu --no-first-run \
        --disable-background-networking --disable-component-update --disable-sync \
        --hide-scrollbars --user-data-dir="$profile" --window-size=1280,2400 \
        --screenshot="$PWD/docs/figures/report-$m.png" \
        "file://$PWD/$out/report-$m/report.html" >/dev/null 2>&1
    rm -rf "$profile"
    test -s "docs/figures/report-$m.png"
    echo "report-$m.png"
done
echo "== screenshots in docs/figures/ (reports in $out/)"
