#!/usr/bin/env bash
# One entry point for a developer or CI on a fresh Debian bookworm machine:
#   deploy/dev.sh setup   - apt packages, .venv, the project (editable) with its test extras
#   deploy/dev.sh serve   - setup, then run the service (simulated cell, API on 127.0.0.1)
#   deploy/dev.sh test    - setup, then run the whole test suite
# Re-running is cheap: apt and pip are skipped when nothing they own has changed.
set -euo pipefail

repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$repo"
venv="$repo/.venv"

# Debian packages the project needs at run or test time (kept in one place).
# python3-gi + gir1.2-aravis-0.8: the Aravis GigE Vision driver and its loopback stand-in camera;
# chromium + fonts-liberation: the dashboard's test in a real headless browser; systemd: the unit's check.
# mosquitto: the MQTT broker that the plant tests (tests/plant/) start on a loopback port of their own.
# libcairo2: cairo, which rasterises the printed target sheet for images posecell did not make (CairoSVG).
apt_packages=(python3 python3-venv python3-dev gcc python3-gi gir1.2-aravis-0.8 chromium fonts-liberation systemd
    mosquitto libcairo2)

as_root() {
    if [ "$(id -u)" -eq 0 ]; then "$@"; else sudo "$@"; fi
}

install_apt() {
    local missing=()
    for p in "${apt_packages[@]}"; do
        dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
    done
    if [ ${#missing[@]} -gt 0 ]; then
        echo "posecell setup: installing Debian packages: ${missing[*]}" >&2
        as_root env DEBIAN_FRONTEND=noninteractive apt-get update -q
        as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends "${missing[@]}"
    fi
}

install_venv() {
    local stamp="$venv/.posecell-installed"
    local want
    want=$(sha256sum pyproject.toml | cut -d' ' -f1)
    if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && [ -x "$venv/bin/posecell" ]; then
        return
    fi
    [ -x "$venv/bin/python" ] || python3 -m venv "$venv"
    "$venv/bin/python" -m pip install -q --upgrade pip
    "$venv/bin/python" -m pip install -q -e ".[test]"
    link_gi
    echo "$want" > "$stamp"
}

# PyGObject is not built from PyPI (it needs the GObject dev stack); Debian's python3-gi is built
# for CPython 3.11, the venv's version, so the venv sees exactly that one package and nothing else
# from the system site-packages.
link_gi() {
    local site
    site=$("$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
    [ -e "$site/gi" ] || ln -s /usr/lib/python3/dist-packages/gi "$site/gi"
}

setup() {
    install_apt
    install_venv
    # the first use of the numba kernels compiles them (~2.7 min on one core); two at a time here,
    # cached for every later process (a second when nothing changed)
    "$venv/bin/python" -m service.pipeline.compile
}

cmd=${1:-help}
shift || true
case "$cmd" in
    setup) setup ;;
    serve) setup; exec "$venv/bin/posecell" serve "$@" ;;
    test)
        setup
        # two workers (pytest-xdist), each taking a whole test file at a time (its module fixtures,
        # a running cell or a browser, are made once); the files that hold the cell to its real-time
        # rate run alone, last (tests/conftest.py, SOLO_MODULES). On this project's 2-core VM, in one
        # slow hour: 11.3 min against 15.6 in one process (9.8 since the files keep conftest's order).
        # One core: one process; "-n 0" after `test` runs everything in this process.
        workers=()
        [ "$(nproc)" -ge 2 ] && workers=(-n 2 --dist loadfile)
        exec "$venv/bin/python" -m pytest "${workers[@]}" "$@"
        ;;
    *) echo "usage: deploy/dev.sh setup|serve|test [args...]" >&2; exit 2 ;;
esac
