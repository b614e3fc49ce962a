#!/usr/bin/env bash
# Debian/Ubuntu packages for the GUI tests and a real window on a machine without a display:
# Xvfb and the OpenGL / xcb libraries Qt and VTK load. Safe to re-run; needs root or sudo.
set -euo pipefail
export DEBIAN_FRONTEND=noninteractive
command -v apt-get >/dev/null 2>&1 || { echo "no apt-get: install Xvfb and Mesa OpenGL by hand" >&2; exit 0; }
SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
need=""
for pkg in xvfb xauth libgl1 libegl1 libgl1-mesa-dri libglu1-mesa libxrender1 libxt6 libxkbcommon-x11-0 \
           libxcb-cursor0 libxcb-icccm4 libxcb-keysyms1 libxcb-shape0 libxcb-xkb1 libxcb-render-util0 \
           libxcb-image0 libfontconfig1 libdbus-1-3; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need="$need $pkg"
done
if [ -n "$need" ]; then
  $SUDO apt-get update -q || true
  # shellcheck disable=SC2086
  $SUDO apt-get install -y -q --no-install-recommends $need
fi
