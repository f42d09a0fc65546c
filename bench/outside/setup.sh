#!/usr/bin/env bash
# Installs what the outside benchmark needs: Blender (Cycles) and COLMAP from Debian's
# packages, and a Python environment with numpy and Pillow for the second flight's camera.
set -euo pipefail
cd "$(dirname "$0")/../.."
need=()
command -v blender >/dev/null || need+=(blender)
command -v colmap >/dev/null || need+=(colmap)
if ((${#need[@]})); then
    SUDO=""
    [ "$(id -u)" -eq 0 ] || SUDO=sudo
    $SUDO apt-get update
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y "${need[@]}"
fi
if [ ! -x bench/.venv/bin/python ]; then
    python3 -m venv bench/.venv
fi
bench/.venv/bin/python -c "import numpy, PIL" 2>/dev/null ||
    bench/.venv/bin/pip install --quiet numpy pillow
blender --version | head -n 1
colmap -h 2>/dev/null | head -n 1 || true
