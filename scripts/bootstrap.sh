#!/usr/bin/env bash
# Bootstrap landbench on a fresh Debian/Ubuntu machine:
#   1. system packages: a Python >= 3.11 with venv, Mesa's headless OpenGL
#      (EGL + OSMesa software rendering) and Chromium (the HTML report's browser
#      test), installed through apt when missing;
#   2. .venv with landbench installed (editable) with its test, Ray and study (cvxpy, SALib, Gymnasium) extras,
#      by uv when it can be had (pip otherwise).
# Idempotent: re-running does nothing when everything is in place.
set -euo pipefail
cd "$(dirname "$0")/.."

GL_PKGS=(libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6)
BROWSER_PKGS=(chromium)  # headless Chromium: the test that opens landbench compare's report.html
VENV=.venv
STAMP=$VENV/.landbench-installed

have_pkg() { dpkg-query -W -f='${Status}' "$1" 2>/dev/null | grep -q "install ok installed"; }

apt_install() {
  # Install Debian packages, as root or through passwordless sudo; otherwise say exactly what to run.
  local pkgs=("$@")
  local cmd=(apt-get install -y --no-install-recommends "${pkgs[@]}")
  if [ "$(id -u)" -eq 0 ]; then
    DEBIAN_FRONTEND=noninteractive apt-get update -qq && DEBIAN_FRONTEND=noninteractive "${cmd[@]}" -qq
  elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    sudo DEBIAN_FRONTEND=noninteractive apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive "${cmd[@]}" -qq
  else
    echo "landbench: missing system packages: ${pkgs[*]}" >&2
    echo "landbench: not root and no passwordless sudo, so they cannot be installed automatically. Run:" >&2
    echo "    sudo apt-get install -y ${pkgs[*]}" >&2
    echo "then run make again." >&2
    exit 1
  fi
}

# --- Python >= 3.11 with venv ------------------------------------------------
find_python() {
  for c in "${PYTHON:-}" python3 python3.13 python3.12 python3.11; do
    [ -n "$c" ] && command -v "$c" >/dev/null 2>&1 || continue
    if "$c" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' 2>/dev/null; then
      echo "$c"; return 0
    fi
  done
  return 1
}
PY=$(find_python || true)
if [ -z "$PY" ]; then
  if command -v dpkg-query >/dev/null 2>&1; then
    apt_install python3.11 python3.11-venv
    PY=$(find_python)
  else
    echo "landbench: needs Python >= 3.11 (set PYTHON=/path/to/python3.11)" >&2; exit 1
  fi
fi
if [ ! -x "$VENV/bin/python" ] && ! "$PY" -c 'import ensurepip, venv' >/dev/null 2>&1; then
  ver=$("$PY" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')
  apt_install "python${ver}-venv"
fi

# --- Mesa headless OpenGL, and Chromium for the report test ---------------------
if command -v dpkg-query >/dev/null 2>&1; then
  missing=()
  for p in "${GL_PKGS[@]}"; do have_pkg "$p" || missing+=("$p"); done
  if [ ${#missing[@]} -gt 0 ]; then
    echo "landbench: installing Mesa headless OpenGL: ${missing[*]}"
    apt_install "${missing[@]}"
  fi
  # Debian's chromium for the report's browser test (tests/test_compare_report.py). Not fatal when it cannot be
  # installed: that test is then skipped locally, and fails under CI (CI set), which must run it.
  if [ ! -x /usr/bin/chromium ] && ! have_pkg chromium; then
    echo "landbench: installing headless Chromium for the report test: ${BROWSER_PKGS[*]}"
    ( apt_install "${BROWSER_PKGS[@]}" ) || echo "landbench: chromium was not installed; the browser test will be skipped (and fail under CI)" >&2
  fi
else
  echo "landbench: not a Debian/Ubuntu system; make sure Mesa EGL or OSMesa is installed (and chromium for the report test)." >&2
fi

# --- virtual environment ---------------------------------------------------------
if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
fi
if [ ! -f "$STAMP" ] || [ pyproject.toml -nt "$STAMP" ]; then
  # ray: the tests run the Ray backend too; studies: G-FOLD, sweeps, Gymnasium; geo: GeoTIFF DEMs.
  EXTRAS='.[dev,ray,studies,geo]'
  # uv (from PyPI) resolves and installs the same versions as pip in about a fifth of its time (13 s
  # against 58 s on a 2-core machine, a quarter of a clean clone's make test before the tests start); pip
  # is the fallback wherever uv cannot be had or cannot reach the index. Neither byte-compiles here:
  # compileall does, on every core, below.
  if ! { "$VENV/bin/python" -m pip install -q uv >/dev/null 2>&1 \
         && "$VENV/bin/python" -m uv pip install -q --python "$VENV/bin/python" -e "$EXTRAS"; }; then
    echo "landbench: installing with pip (uv was not available)" >&2
    "$VENV/bin/python" -m pip install -q --upgrade pip
    "$VENV/bin/python" -m pip install -q --no-compile -e "$EXTRAS"
  fi
  # Left uncompiled (a third of the files, half the time): the packages' own test suites, pip and
  # setuptools, and the Ray libraries landbench never imports (RLlib, Data, Train, Tune, Serve, LLM);
  # whatever is imported from them anyway still works, compiled in memory.
  "$VENV/bin/python" -m compileall -q -j 0 -x '/tests/|/ray/(rllib|data|train|tune|llm|serve)/|/(pip|setuptools)/' \
    "$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')" >/dev/null || true
  touch "$STAMP"
fi
# landbench's own modules, byte-compiled where they changed (an editable install leaves them to the first
# import, which cannot cache them where PYTHONDONTWRITEBYTECODE is set, as on some CI images: every
# process, test workers and the CLI runs the tests start, then compiles them again, 0.3-0.4 s each).
"$VENV/bin/python" -m compileall -q -j 0 bench gnc models vision >/dev/null || true
