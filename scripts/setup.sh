#!/usr/bin/env bash
# One-time setup: find Python 3.12, install the Debian libraries for headless rendering and video
# decoding, create .venv and install this package into it. Safe to run again (it skips finished work).
set -euo pipefail
cd "$(dirname "$0")/.."

find_python312() {
  local candidates=()
  [ -n "${PYTHON:-}" ] && candidates+=("$PYTHON")
  command -v python3.12 >/dev/null 2>&1 && candidates+=("$(command -v python3.12)")
  if command -v pyenv >/dev/null 2>&1; then
    local root; root="$(pyenv root)"
    for p in "$root"/versions/3.12*/bin/python3.12; do [ -x "$p" ] && candidates+=("$p"); done
  fi
  for p in "${candidates[@]}"; do
    # pyenv shims exist on PATH even when they cannot run: check that the interpreter really starts.
    if "$p" -c 'import sys; assert sys.version_info[:2] == (3, 12)' >/dev/null 2>&1; then
      echo "$p"; return 0
    fi
  done
  return 1
}

apt_install() {
  local sudo=""; [ "$(id -u)" -ne 0 ] && sudo="sudo"
  echo "setup: installing $*"
  $sudo apt-get update -qq && DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "$@" >/dev/null
}

missing_debs() {
  for pkg in "$@"; do dpkg -s "$pkg" >/dev/null 2>&1 || echo "$pkg"; done
}

install_system_libs() {
  command -v dpkg >/dev/null 2>&1 || { echo "setup: not a Debian-like system; make sure libEGL (Mesa) and FFmpeg's libraries are installed"; return 0; }
  # EGL through Mesa: MuJoCo's headless rendering (MUJOCO_GL=egl) on a machine without a GPU.
  local egl; egl=$(missing_debs libegl1 libegl-mesa0 libgl1 libgles2)
  if [ -n "$egl" ]; then
    apt_install $egl || { echo "setup: could not install $egl (needed for rendering)" >&2; return 1; }
  fi
  # FFmpeg's shared libraries: torchcodec (LeRobot's default video decoder) loads them at run time.
  # Their package names carry the ABI version (libavcodec59 on Debian 12), so ask apt for them.
  local ffmpeg=()
  for lib in libavcodec libavformat libavutil libswscale libswresample libavdevice libavfilter; do
    local name; name=$(apt-cache pkgnames "$lib" 2>/dev/null | grep -E "^${lib}[0-9]+$" | sort -V | tail -1)
    [ -n "$name" ] && ffmpeg+=("$name")
  done
  local need; need=$(missing_debs "${ffmpeg[@]}")
  if [ -n "$need" ]; then
    apt_install $need || echo "setup: WARNING: FFmpeg libraries not installed; torchcodec cannot decode: use --dataset.video_backend=pyav (bcrl_frame_cache falls back to PyAV itself)" >&2
  fi
}

PY=$(find_python312) || {
  echo "setup: Python 3.12 is required (lerobot 0.6.1 needs it) and none was found." >&2
  echo "       Put python3.12 on PATH, install it with pyenv ('pyenv install 3.12'), or set PYTHON=/path/to/python3.12." >&2
  exit 1
}
echo "setup: using $PY"
install_system_libs

if [ ! -x .venv/bin/python ] || ! .venv/bin/python -c 'import sys; assert sys.version_info[:2] == (3, 12)' 2>/dev/null; then
  rm -rf .venv
  "$PY" -m venv .venv
fi
stamp=.venv/.installed-$(cat pyproject.toml scripts/constraints.txt | sha1sum | cut -c1-12)
if [ ! -f "$stamp" ]; then
  # The environment takes ~8 GB (PyPI's torch brings its CUDA libraries even on a CPU machine), and pip holds the
  # downloaded wheels (~3.5 GB) until it has installed them all. pip's cache would keep another copy of them, so it
  # is off (pybullet, which has no wheel for Python 3.12, is then built again on each fresh install).
  free_gb=$(df -Pk . | awk 'NR==2 {print int($4 / 1048576)}')
  if [ "${free_gb:-0}" -lt 12 ]; then
    echo "setup: WARNING: ${free_gb} GB free under $(pwd); installing .venv needs about 12 GB (8 GB once done)" >&2
  fi
  .venv/bin/python -m pip install -q --no-cache-dir --upgrade pip
  # Every package at the exact version of scripts/constraints.txt (within pyproject.toml's ranges).
  .venv/bin/python -m pip install -q --no-cache-dir -c scripts/constraints.txt -e '.[test,ray]' || {
    echo "setup: pip install failed; if it says 'No space left on device', free about 12 GB under $(pwd) and run again" >&2
    exit 1
  }
  rm -f .venv/.installed-*; touch "$stamp"
fi
echo "setup: done (.venv ready)"
