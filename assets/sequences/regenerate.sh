#!/usr/bin/env bash
# Regenerate the committed test-bench sequences (320x240 grayscale, inverse-depth PNG).
# Usage (from the repository root):  bash assets/sequences/regenerate.sh
# Runs are resumable: finished frames are skipped. Delete a folder to render it again.
set -euo pipefail
cd "$(dirname "$0")/../.."
PY="${PYTHON:-.venv/bin/python}"
render() {  # scenario, frames A:B
  "$PY" -m simulation.cli render "$1" --out "assets/sequences/$1" --width 320 --height 240 \
    --grayscale --depth-format inv16 --frames "$2"
}
render default 0:110
render spiral 0:110
render rotation 40:150
render framedrop 0:140
render aggressive 0:60
