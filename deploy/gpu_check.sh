#!/usr/bin/env bash
# GPU check: run the encoder (NARADIO b and l, 224x224 and 640x480, fp16 / bf16), the mapper
# (throughput and online presets on the device) and the end-to-end chain on loopback, and
# print one JSON with the paper's Jetson AGX Orin figures beside ours
# (`rayfronts bench gpu`, apps/bench/gpu.py). Needs the project installed (make setup).
#
#   deploy/gpu_check.sh                         # cuda, full run; JSON on stdout
#   deploy/gpu_check.sh --json gpu.json         # also write it to a file
#   deploy/gpu_check.sh --device cpu --quick    # smoke test without a GPU (CI runs this)
#
# Extra options go to `rayfronts bench gpu` (see --help). Per-run JSONs and logs land in
# --workdir (default: a fresh temporary directory, printed in the JSON as "workdir").
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-}"
if [[ -z "$PY" ]]; then
  if [[ -x .venv/bin/python ]]; then PY=.venv/bin/python; else PY=python3; fi
fi
exec "$PY" -m apps.cli bench gpu "$@"
