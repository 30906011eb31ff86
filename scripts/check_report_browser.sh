#!/usr/bin/env bash
# Open a `nehad report` page in headless Chromium, offline, and check that the browser decodes
# every image; save a screenshot to look at.
#
#   scripts/check_report_browser.sh [--install] [REPORT.html] [SCREENSHOT.png]
#
# Without REPORT.html it makes one: a tiny synthetic scene, a `test`-preset run (seconds) and
# `nehad report`, in a temporary folder. The page's own load handler counts the decoded images
# into <html data-images-total=N data-images-ok=M>; Chromium's --dump-dom prints the DOM after
# the load, and the check passes when M == N > 0. The screenshot goes to SCREENSHOT.png
# (default report_check.png).
#
# Chromium: Debian's `chromium` package (apt-get install chromium). --install runs that apt-get
# when no Chromium is found (needs root and the Debian package index). From PyPI, playwright and
# pyppeteer download their browser at run time and kaleido>=1 needs an installed Chrome, so none
# of them works offline; PyQt6-WebEngine-Qt6 does ship QtWebEngine (Chromium's engine, with
# QtWebEngineProcess) in its wheel, but it is a Qt widget, not a headless Chromium, and is not
# used here. $NEHAD_CHROMIUM may name another Chromium/Chrome binary.
#
# tests/test_report.py::test_report_in_headless_chromium runs the same check (skipped when no
# Chromium is installed).
set -euo pipefail

install=0
if [[ "${1:-}" == "--install" ]]; then install=1; shift; fi
report="${1:-}"
shot="${2:-report_check.png}"

find_chromium() {
    for c in "${NEHAD_CHROMIUM:-}" chromium chromium-browser google-chrome chrome-headless-shell; do
        if [[ -n "$c" ]] && command -v "$c" >/dev/null 2>&1; then command -v "$c"; return 0; fi
    done
    return 1
}

if ! chrome="$(find_chromium)"; then
    if [[ $install == 1 ]]; then
        echo "installing Debian's chromium (apt-get) ..." >&2
        apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
        chrome="$(find_chromium)"
    else
        echo "error: no Chromium found; install it (apt-get install chromium), rerun with" \
             "--install, or set NEHAD_CHROMIUM" >&2
        exit 2
    fi
fi

work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
if [[ -z "$report" ]]; then
    echo "making a report of a tiny run in $work ..." >&2
    export NUMBA_NUM_THREADS="${NUMBA_NUM_THREADS:-1}" OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
    nehad synth "$work/data" --resolution 32 --frames 8 --gaussians 0 >/dev/null
    nehad train "$work/data" -o "$work/run" --preset test --quiet >/dev/null
    nehad eval "$work/run" --no-lpips --quiet >/dev/null
    report="$work/report.html"
    nehad report "$work/run" -o "$report" >/dev/null
fi
[[ -f "$report" ]] || { echo "error: $report: no such file" >&2; exit 2; }
url="file://$(cd "$(dirname "$report")" && pwd)/$(basename "$report")"

# the flags this machine needs: no sandbox as root, no GPU, and no background connections (the
# network is closed; Chromium would retry them)
flags=(--headless --no-sandbox --disable-gpu --disable-quic --no-first-run
       --disable-background-networking --disable-component-update --disable-sync
       "--user-data-dir=$work/profile")

dom="$("$chrome" "${flags[@]}" --virtual-time-budget=5000 --dump-dom "$url" 2>/dev/null)"
total="$(grep -o 'data-images-total="[0-9]*"' <<<"$dom" | grep -o '[0-9]*' || true)"
ok="$(grep -o 'data-images-ok="[0-9]*"' <<<"$dom" | grep -o '[0-9]*' || true)"
"$chrome" "${flags[@]}" --hide-scrollbars --window-size=1200,4000 "--screenshot=$shot" "$url" \
    >/dev/null 2>&1 || true

echo "$("$chrome" --version 2>/dev/null | head -1): $report"
if [[ -z "$total" || -z "$ok" ]]; then
    echo "FAIL: the page's load handler did not run (no data-images-* in the DOM)"
    exit 1
fi
echo "images decoded by the browser: $ok of $total; screenshot: $shot"
if [[ "$total" -gt 0 && "$ok" == "$total" ]]; then
    echo "PASS"
else
    echo "FAIL"
    exit 1
fi
