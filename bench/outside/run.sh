#!/usr/bin/env bash
# The outside benchmark in one command: installs Blender, COLMAP and the Python packages,
# renders both scenes, builds their maps, runs every method and the COLMAP peer on the three
# query sets and prints the table (also written to WORK/table.md; WORK defaults to
# target/outside). Arguments go to `outside.py all` (e.g. --scenes rubble --width 1152
# --height 864 --work target/outside-1152). Resumes where a previous run stopped.
set -euo pipefail
cd "$(dirname "$0")/../.."
bench/outside/setup.sh
exec bench/.venv/bin/python bench/outside/outside.py all "$@"
