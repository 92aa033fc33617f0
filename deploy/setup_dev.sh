#!/usr/bin/env bash
# Set up a development / CI machine from nothing: system packages, .venv, CPU torch,
# the project (editable, with the OpenVDB extension when OpenVDB is available).
# Called by `make setup` (and so by `make demo` / `make test`). Safe to re-run.
set -euo pipefail
PY=${PY:-python3}
VENV=${VENV:-.venv}
TORCH=${TORCH:-torch==2.13.0}
EXTRAS=${EXTRAS:-all,test}
APT_PKGS="g++ make libopenvdb-dev libboost-iostreams-dev openssl iproute2"

need_apt=""
for p in $APT_PKGS; do
  dpkg -s "$p" >/dev/null 2>&1 || need_apt="$need_apt $p"
done
if [ -n "$need_apt" ]; then
  if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
    echo "[setup] apt-get install:$need_apt"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $need_apt
  elif command -v apt-get >/dev/null 2>&1 && command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    echo "[setup] sudo apt-get install:$need_apt"
    sudo apt-get update -qq
    sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $need_apt
  else
    echo "[setup] WARNING: missing system packages:$need_apt"
    echo "[setup]   install them with:  sudo apt-get install -y$need_apt"
    echo "[setup]   (continuing: without libopenvdb-dev the mapper uses its torch occupancy backend)"
  fi
fi

if [ ! -x "$VENV/bin/python" ]; then
  echo "[setup] creating $VENV"
  if ! $PY -m venv "$VENV"; then
    echo "[setup] ERROR: '$PY -m venv' failed; on Debian/Ubuntu: sudo apt-get install -y python3-venv python3-dev" >&2
    exit 1
  fi
fi
"$VENV/bin/python" -m pip install -q --upgrade pip
# CPU torch first: an unpinned torch pulls a multi-GB CUDA build.
"$VENV/bin/python" -c "import torch" 2>/dev/null || "$VENV/bin/python" -m pip install -q "$TORCH"
echo "[setup] pip install -e .[$EXTRAS] (builds the OpenVDB extension, about a minute)"
"$VENV/bin/python" -m pip install -q -e ".[$EXTRAS]"
"$VENV/bin/python" - <<'PYEOF'
try:
    from mapper.occupancy import backend_name
    print(f"[setup] occupancy backend: {backend_name()}")
except Exception as e:  # the mapper may not be importable yet on a partial checkout
    print(f"[setup] occupancy backend: unknown ({e})")
PYEOF
echo "[setup] done"
