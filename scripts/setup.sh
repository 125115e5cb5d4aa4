#!/usr/bin/env bash
# Creates .venv and installs the project with everything it needs, system packages
# included. Idempotent: a stamp keyed on pyproject.toml skips work already done.
set -euo pipefail
cd "$(dirname "$0")/.."

# open3d's wheel links against libusb-1.0 (Debian/Ubuntu package libusb-1.0-0).
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
    if command -v apt-get >/dev/null 2>&1; then
        SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
        echo "[setup] installing libusb-1.0-0 (needed by open3d)" >&2
        $SUDO apt-get update -qq >&2
        DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 >&2
    else
        echo "[setup] warning: libusb-1.0 not found and no apt-get; open3d may fail to import" >&2
    fi
fi

# Headless Chromium loads report.html in tests/test_report.py (which skips without it).
if ! command -v chromium >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then
    SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    echo "[setup] installing chromium (the report's browser test)" >&2
    { $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium; } >&2 \
        || echo "[setup] warning: could not install chromium; the browser tests will skip" >&2
fi

PY=${PYTHON:-python3}
stamp=.venv/.installed-$(sha1sum pyproject.toml | cut -c1-12)
if [ ! -f "$stamp" ]; then
    echo "[setup] creating .venv and installing calib3r-graph (first run takes a few minutes)" >&2
    [ -x .venv/bin/python ] || "$PY" -m venv .venv
    .venv/bin/python -m pip install -q --upgrade pip >&2
    .venv/bin/python -m pip install -q -e '.[test]' >&2
    rm -f .venv/.installed-*
    touch "$stamp"
fi
