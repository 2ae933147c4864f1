#!/usr/bin/env bash
# Install posecell as a systemd service on a Debian cell PC (run as root from a checkout):
#   sudo deploy/install.sh            install or upgrade, enable and start
#   sudo deploy/install.sh --no-start install only
# Layout: code in /opt/posecell (with its .venv), configuration in /etc/posecell,
# state (database, calibrations, API token) in /var/lib/posecell, user "posecell".
set -euo pipefail
src=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
prefix=/opt/posecell
start=1
[ "${1:-}" = "--no-start" ] && start=0

if [ "$(id -u)" -ne 0 ]; then
    echo "install.sh: run as root (sudo deploy/install.sh)" >&2
    exit 2
fi

id posecell >/dev/null 2>&1 || useradd --system --home-dir /var/lib/posecell --shell /usr/sbin/nologin posecell
for g in video plugdev; do getent group "$g" >/dev/null && usermod -a -G "$g" posecell; done

mkdir -p "$prefix"
# the code, without the developer's venv, caches or git metadata
tar -C "$src" --exclude=.venv --exclude=.git --exclude='__pycache__' --exclude='.pytest_cache' -cf - . | tar -C "$prefix" -xf -
"$prefix/deploy/dev.sh" setup

install -d -m 0755 /etc/posecell
if [ ! -f /etc/posecell/posecell.toml ]; then
    install -m 0640 -g posecell "$src/deploy/posecell.example.toml" /etc/posecell/posecell.toml
    echo "install.sh: wrote /etc/posecell/posecell.toml (the simulated cell); edit it for your devices" >&2
fi
install -m 0644 "$src/deploy/posecell.service" /etc/systemd/system/posecell.service
# GigE Vision: large receive buffers so that no packet of a full frame is dropped
install -m 0644 "$src/deploy/99-posecell-gige.conf" /etc/sysctl.d/99-posecell-gige.conf
sysctl --quiet --load /etc/sysctl.d/99-posecell-gige.conf || true

systemctl daemon-reload
if [ "$start" -eq 1 ]; then
    systemctl enable --now posecell.service
    systemctl --no-pager --lines=5 status posecell.service || true
    echo "install.sh: the API token is in /var/lib/posecell/api-token" >&2
fi
