#!/usr/bin/env bash
# Install posecell as a systemd service on a Debian cell PC (run as root from a checkout):
#   sudo deploy/install.sh            install or upgrade, enable and start
#   sudo deploy/install.sh --no-start install only (and `systemctl daemon-reload` when systemd runs)
# Layout: a virtual environment with posecell in /opt/posecell/.venv, configuration in
# /etc/posecell, state (database, calibrations, API token) in /var/lib/posecell, user "posecell".
# Only what the service needs is installed (no test tools, no browser).
set -euo pipefail
src=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
prefix=/opt/posecell
start=1
[ "${1:-}" = "--no-start" ] && start=0

if [ "$(id -u)" -ne 0 ]; then
    echo "install.sh: run as root (sudo deploy/install.sh)" >&2
    exit 2
fi

# PyGObject + Aravis from Debian (GigE Vision / USB3 Vision cameras)
apt_packages=(python3 python3-venv python3-gi gir1.2-aravis-0.8)
missing=()
for p in "${apt_packages[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
    DEBIAN_FRONTEND=noninteractive apt-get update -q
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends "${missing[@]}"
fi

id posecell >/dev/null 2>&1 || useradd --system --home-dir /var/lib/posecell --shell /usr/sbin/nologin posecell
for g in video plugdev; do getent group "$g" >/dev/null && usermod -a -G "$g" posecell; done

umask 022  # the service user must read the code
install -d -m 0755 "$prefix"
# Debian's own Python (not a developer's pyenv or conda first on PATH): readable by the service user,
# and the interpreter python3-gi is built for
if [ -x "$prefix/.venv/bin/python" ] && [ "$(readlink -f "$prefix/.venv/bin/python")" != "$(readlink -f /usr/bin/python3)" ]; then
    rm -rf "$prefix/.venv"
fi
[ -x "$prefix/.venv/bin/python" ] || /usr/bin/python3 -m venv "$prefix/.venv"
"$prefix/.venv/bin/python" -m pip install -q --upgrade pip
"$prefix/.venv/bin/python" -m pip install -q "$src[ur]"   # a regular (not editable) install, with ur-rtde
site=$("$prefix/.venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
[ -e "$site/gi" ] || ln -s /usr/lib/python3/dist-packages/gi "$site/gi"
install -m 0644 "$src/README.md" "$prefix/README.md"
chmod -R a+rX "$prefix"

install -d -m 0755 /etc/posecell
if [ ! -f /etc/posecell/posecell.toml ]; then
    install -m 0640 -g posecell "$src/deploy/posecell.example.toml" /etc/posecell/posecell.toml
    echo "install.sh: wrote /etc/posecell/posecell.toml (the simulated cell); edit it for your devices" >&2
fi
install -m 0644 "$src/deploy/posecell.service" /etc/systemd/system/posecell.service
# GigE Vision: large receive buffers so that no packet of a full frame is dropped
install -m 0644 "$src/deploy/99-posecell-gige.conf" /etc/sysctl.d/99-posecell-gige.conf
sysctl --quiet --load /etc/sysctl.d/99-posecell-gige.conf || echo "install.sh: sysctl not applied (container?)" >&2

# the numba kernels compiled now, into the service's own cache (posecell.service sets NUMBA_CACHE_DIR),
# so that the first start is ready in seconds instead of after a minute or two of compiling
install -d -m 0750 -o posecell -g posecell /var/lib/posecell /var/lib/posecell/numba-cache
runuser -u posecell -- env NUMBA_CACHE_DIR=/var/lib/posecell/numba-cache \
    "$prefix/.venv/bin/python" -m service.pipeline.compile

if [ -d /run/systemd/system ]; then
    systemctl daemon-reload
    if [ "$start" -eq 1 ]; then
        systemctl enable --now posecell.service
        systemctl --no-pager --lines=5 status posecell.service || true
        echo "install.sh: the API token is in /var/lib/posecell/api-token" >&2
    fi
else
    echo "install.sh: systemd is not running here; start posecell.service on the cell PC" >&2
fi
"$prefix/.venv/bin/posecell" --help >/dev/null && echo "install.sh: posecell installed in $prefix" >&2
