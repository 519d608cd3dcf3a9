#!/usr/bin/env bash
# Set up RecGS on a fresh Debian/Ubuntu machine: system libraries Blender needs (installed
# with apt-get when missing and we are root or have sudo), then a virtual environment in
# .venv with the pinned requirements. Safe to run again: it only does what is missing.
#   bash scripts/setup.sh          runtime dependencies
#   bash scripts/setup.sh --dev    plus the test tools (and Ray)
#   bash scripts/setup.sh --ray    plus Ray, for training in blocks (train --blocks N)
set -euo pipefail
cd "$(dirname "$0")/.."
DEV=0
[ "${1:-}" = "--dev" ] && DEV=1
[ "${1:-}" = "--ray" ] && DEV=ray

# Libraries `import bpy` needs, plus EGL/Mesa for EEVEE without a display.
DEB_PKGS="libx11-6 libxrender1 libxfixes3 libxi6 libxkbcommon0 libsm6 libgl1 libegl1 libgl1-mesa-dri"
missing=""
for p in $DEB_PKGS; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
done
if [ -n "$missing" ]; then
  echo "setup: installing system libraries:$missing"
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  if [ -n "$SUDO" ] && ! command -v sudo >/dev/null; then
    echo "setup: please install these Debian packages as root:$missing" >&2
    exit 1
  fi
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq --no-install-recommends $missing >/dev/null
fi

PY="${PYTHON:-}"
if [ -z "$PY" ]; then
  for cand in python3.11 python3; do
    if command -v "$cand" >/dev/null && "$cand" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
      PY="$cand"; break
    fi
  done
fi
if [ -z "$PY" ]; then
  echo "setup: Python 3.11 is required (bpy 5.0.1 is built for it); set PYTHON=/path/to/python3.11" >&2
  exit 1
fi

[ -x .venv/bin/python ] || "$PY" -m venv .venv
REQ="-r requirements.txt"
[ "$DEV" = 1 ] && REQ="-r requirements-dev.txt"
[ "$DEV" = ray ] && REQ="-r requirements.txt -r requirements-ray.txt"
stamp=".venv/.recgs-$(cat requirements*.txt | sha256sum | cut -c1-16)-$DEV"
if [ ! -e "$stamp" ]; then
  echo "setup: installing Python packages ($REQ) into .venv"
  # a failed install stops here (the packages already installed are kept and the next run tries again)
  if ! .venv/bin/python -m pip install -q --disable-pip-version-check $REQ > .venv/pip.log 2>&1; then
    grep -v "is ignored: it is neither a file nor a directory" .venv/pip.log >&2 || true
    echo "setup: pip could not install $REQ (its messages above, all of them in .venv/pip.log)" >&2
    exit 1
  fi
  grep -v "is ignored: it is neither a file nor a directory" .venv/pip.log || true
  .venv/bin/python -c "import bpy, numpy, torch, pycolmap, OpenImageIO" \
    || { echo "setup: the Python packages did not install correctly" >&2; exit 1; }
  touch "$stamp"
fi
# numba's kernels compiled into the per-user cache now (15-40 s once; a second when warm), so the
# first job trains on them from its first step instead of sharing the machine with the compiler
PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" .venv/bin/python -m recgs_addon.core.train.compiling --numba \
  || echo "setup: numba's kernels did not compile; training will run on the slower eager path" >&2
echo "setup: ready (.venv/bin/python)"
