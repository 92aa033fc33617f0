#!/usr/bin/env bash
# Set up a development / CI machine from nothing: system packages, .venv, CPU torch, the
# Python dependencies, then the project (editable, with its C++ extensions when a compiler
# and OpenVDB are there). Called by `make setup` (and so by `make demo` / `make test`).
# Safe to re-run: every stage that is already done is skipped and says so.
#
# Progress: one line per stage with the elapsed time ([setup m:ss]); pip's downloads and
# the C++ build show their own progress lines (filtered, so nothing is silent for minutes).
#
# The C++ build (semantic_map._vdbocc with OpenVDB, semantic_map._rfkernels) is the one slow step that
# need not be repeated: its outputs are cached under $RAYFRONTS_CACHE (default
# ~/.cache/rayfronts/ext/<key>), keyed by the C++ sources, the CMake files, the Python ABI,
# nanobind, the compiler and the OpenVDB package version. A fresh clone on a machine that
# has built the same sources before installs the cached modules instead of compiling
# (CMake option RAYFRONTS_PREBUILT, see CMakeLists.txt). RAYFRONTS_NO_EXT_CACHE=1 forces a build.
#
# EXTRAS with "test" also installs Debian's chromium (tests/test_browser_view.py drives it
# headless) and the independent readers of tests/test_export.py (OpenVDB's Python module and
# vdb_print, meshio; run by /usr/bin/python3); the demo alone does not need them.
set -euo pipefail
PY=${PY:-python3}
VENV=${VENV:-.venv}
TORCH=${TORCH:-torch==2.13.0}
EXTRAS=${EXTRAS:-all,test}
CACHE=${RAYFRONTS_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/rayfronts}
APT_PKGS="g++ make cmake libopenvdb-dev libboost-iostreams-dev openssl iproute2"
case ",$EXTRAS," in *,test,*) APT_PKGS="$APT_PKGS chromium python3-openvdb libopenvdb-tools python3-meshio" ;; esac
export PIP_DISABLE_PIP_VERSION_CHECK=1
export CMAKE_BUILD_PARALLEL_LEVEL=${CMAKE_BUILD_PARALLEL_LEVEL:-$(nproc 2>/dev/null || echo 2)}

T0=$(date +%s)
stamp() { local t=$(( $(date +%s) - T0 )); printf '%d:%02d' $((t / 60)) $((t % 60)); }
say() { echo "[setup $(stamp)] $*"; }
# prefix each line of a long step with the elapsed time; keep only the informative ones
progress() { while IFS= read -r line; do echo "[setup $(stamp)]   $line"; done; }
# run "$@" with its output filtered by the grep -E pattern $FILTER and time-stamped; the
# command's exit status is kept (a filter that matches nothing is not a failure)
filtered() {
  local st
  set +e
  "$@" 2>&1 | grep --line-buffered -E "$FILTER" | sed -u -E 's/^(.{0,140}).*/\1/' | progress
  st=${PIPESTATUS[0]}
  set -e
  return "$st"
}

say "start: venv $VENV, extras [$EXTRAS], $(nproc 2>/dev/null || echo ?) CPUs"
say "expect (measured on 2-core machines): ~1 GB of wheels (torch, rerun, transformers ...) in 0.5-4 min,"
say "  then the C++ build 0.5 min on 2 idle cores, up to 8 min when other jobs share them; skipped when"
say "  cached from an earlier build of the same sources; a re-run skips everything in seconds"

# ---------------------------------------------------------------- system packages
need_apt=""
for p in $APT_PKGS; do
  dpkg -s "$p" >/dev/null 2>&1 || need_apt="$need_apt $p"
done
if [ -z "$need_apt" ]; then
  say "system packages: all present (skipped)"
else
  if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then SUDO=""
  elif command -v apt-get >/dev/null 2>&1 && command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then SUDO="sudo"
  else SUDO="none"; fi
  if [ "$SUDO" != none ]; then
    say "apt-get install:$need_apt"
    $SUDO apt-get update -qq
    FILTER='^(Setting up|E:)' filtered $SUDO env DEBIAN_FRONTEND=noninteractive \
      apt-get install -y -q --no-install-recommends $need_apt
    say "system packages done"
  else
    say "WARNING: missing system packages:$need_apt"
    say "  install them with:  sudo apt-get install -y$need_apt"
    say "  (continuing: without libopenvdb-dev the mapper uses its torch occupancy backend;"
    say "   without chromium tests/test_browser_view.py fails)"
  fi
fi

# ---------------------------------------------------------------- venv, pip, torch
if [ -x "$VENV/bin/python" ]; then
  say "venv $VENV exists (skipped)"
else
  say "creating $VENV"
  if ! $PY -m venv "$VENV"; then
    echo "[setup] ERROR: '$PY -m venv' failed; on Debian/Ubuntu: sudo apt-get install -y python3-venv python3-dev" >&2
    exit 1
  fi
fi
VPY="$VENV/bin/python"
if "$VPY" -c 'import sys, pip; sys.exit(0 if int(pip.__version__.split(".")[0]) >= 23 else 1)' 2>/dev/null; then
  say "pip $("$VPY" -c 'import pip; print(pip.__version__)') is recent enough (skipped upgrade)"
else
  say "upgrading pip"
  "$VPY" -m pip install -q --upgrade pip
fi
# pip with its download lines shown, the "already satisfied" noise dropped; --no-compile: no
# byte-compiling of the ~15k installed .py files up front (minutes on 2 busy cores; Python
# compiles what it imports, once, on first use)
pip_progress() {
  FILTER='^(Collecting|Downloading|Installing collected|Successfully installed|ERROR|error:)' \
    filtered "$VPY" -m pip install --progress-bar off --no-compile "$@"
}
if "$VPY" -c "import torch" 2>/dev/null; then
  say "torch $("$VPY" -c 'import torch; print(torch.__version__)') present (skipped)"
else
  # CPU torch first: an unpinned torch pulls a multi-GB CUDA build.
  say "installing $TORCH (CPU build)"
  pip_progress "$TORCH"
fi

# ---------------------------------------------------------------- Python dependencies
DEPS=$("$VPY" - "$EXTRAS" <<'PYEOF'
import re, sys
try:
    import tomllib
except ImportError:  # Python 3.10: let pip resolve the dependencies in the project step
    sys.exit(0)
meta = tomllib.load(open("pyproject.toml", "rb"))["project"]
name, opt = meta["name"], meta.get("optional-dependencies", {})
want, seen, out = [e for e in sys.argv[1].split(",") if e], set(), list(meta.get("dependencies", []))
while want:
    e = want.pop()
    if e in seen:
        continue
    seen.add(e)
    for d in opt.get(e, []):
        m = re.match(rf"{re.escape(name)}\[([^\]]+)\]", d)
        if m:
            want += m.group(1).split(",")
        else:
            out.append(d)
print("\n".join(sorted(set(out))))
PYEOF
)
BUILD_DEPS="scikit-build-core>=0.10 nanobind>=2.0"
if [ -n "$DEPS" ]; then
  mapfile -t DEP_ARR <<<"$DEPS"
  if "$VPY" - "${DEP_ARR[@]}" $BUILD_DEPS <<'PYEOF' 2>/dev/null; then
import sys
from importlib.metadata import PackageNotFoundError, version
try:
    from packaging.requirements import Requirement
except ImportError:
    from pip._vendor.packaging.requirements import Requirement
for spec in sys.argv[1:]:
    r = Requirement(spec)
    if r.marker is not None and not r.marker.evaluate():
        continue
    try:
        v = version(r.name)
    except PackageNotFoundError:
        sys.exit(1)
    if r.specifier and not r.specifier.contains(v, prereleases=True):
        sys.exit(1)
PYEOF
    say "Python dependencies: all ${#DEP_ARR[@]} present (skipped)"
  else
    say "installing the Python dependencies of [$EXTRAS] and the build tools (${#DEP_ARR[@]} requirements)"
    pip_progress "${DEP_ARR[@]}" $BUILD_DEPS
  fi
else
  pip_progress $BUILD_DEPS
fi

# ---------------------------------------------------------------- the project + C++ extensions
KEY=$("$VPY" - <<'PYEOF'
import glob, hashlib, subprocess, sys, sysconfig
h = hashlib.sha256()
for f in sorted(["CMakeLists.txt", *glob.glob("semantic_map/csrc/*")]):
    h.update(f.encode()); h.update(open(f, "rb").read())
try:  # of pyproject.toml only what the build reads (not the dependency lists)
    import tomllib
    t = tomllib.load(open("pyproject.toml", "rb"))
    h.update(repr((t.get("build-system"), t.get("tool", {}).get("scikit-build"))).encode())
except ImportError:
    h.update(open("pyproject.toml", "rb").read())
def out(cmd):
    try:
        return subprocess.run(cmd, capture_output=True, text=True).stdout
    except OSError:
        return ""
try:
    import nanobind; h.update(nanobind.__version__.encode())
except ImportError:
    pass
h.update((sys.version + sysconfig.get_platform() + str(sysconfig.get_config_var("EXT_SUFFIX"))).encode())
h.update(out(["c++", "--version"]).encode())
h.update(out(["dpkg-query", "-W", "-f=${Version}", "libopenvdb-dev"]).encode())
print(h.hexdigest()[:20])
PYEOF
)
EXT_CACHE="$CACHE/ext/$KEY"
SITE=$("$VPY" -c 'import sysconfig; print(sysconfig.get_paths()["platlib"])')
INSTALLED_KEY=$(cat "$VENV/.rayfronts-ext-key" 2>/dev/null || true)
if [ "$INSTALLED_KEY" = "$KEY:$(pwd)" ] && "$VPY" -c "import apps.cli" 2>/dev/null; then
  say "project already installed from this checkout with these C++ sources (skipped)"
else
  PIP_EXT=(--no-build-isolation --no-deps -e . -v)
  if [ -z "${RAYFRONTS_NO_EXT_CACHE:-}" ] && ls "$EXT_CACHE"/*.so >/dev/null 2>&1; then
    say "installing the project; C++ extensions from the cache $EXT_CACHE (no compile)"
    rc=0
    FILTER='(reusing prebuilt|Successfully installed|ERROR|CMake Error)' \
      filtered "$VPY" -m pip install "${PIP_EXT[@]}" -Ccmake.define.RAYFRONTS_PREBUILT="$EXT_CACHE" || rc=$?
  else
    say "installing the project and building its C++ extensions ($CMAKE_BUILD_PARALLEL_LEVEL jobs; 0.5-1 min on 2 idle cores, longer under load)"
    rc=0
    # RAYFRONTS_PREBUILT set empty: a build dir that once reused the cache keeps the define in
    # its CMakeCache.txt and would install the old extensions again instead of compiling
    FILTER='(^ *\[ *[0-9]+%\]|^ *\[[0-9]+/[0-9]+\]|^ *\*\*\* (Configuring|Building|Installing)|will NOT be built|CMake Error|error:|Successfully installed|ERROR)' \
      filtered "$VPY" -m pip install "${PIP_EXT[@]}" -Ccmake.define.RAYFRONTS_PREBUILT= || rc=$?
    if [ "$rc" = 0 ] && [ -z "${RAYFRONTS_NO_EXT_CACHE:-}" ] && ls "$SITE"/semantic_map/_*.so >/dev/null 2>&1; then
      mkdir -p "$EXT_CACHE" && cp "$SITE"/semantic_map/_*.so "$EXT_CACHE"/ && say "cached the built extensions in $EXT_CACHE"
    fi
  fi
  if [ "$rc" != 0 ]; then
    echo "[setup] ERROR: pip install -e . failed (exit $rc); rerun '$VPY -m pip install --no-build-isolation -e .' to see why" >&2
    exit "$rc"
  fi
  echo "$KEY:$(pwd)" > "$VENV/.rayfronts-ext-key"
fi
"$VPY" - <<'PYEOF'
try:
    from semantic_map.occupancy import backend_name
    print(f"[setup] occupancy backend: {backend_name()}")
except Exception as e:  # the mapper may not be importable yet on a partial checkout
    print(f"[setup] occupancy backend: unknown ({e})")
PYEOF
case ",$EXTRAS," in *,test,*)
  command -v chromium >/dev/null 2>&1 && say "browser for the tests: $(chromium --version 2>/dev/null | head -1)" \
    || say "WARNING: chromium not installed: tests/test_browser_view.py will fail" ;;
esac
say "done"
