#!/usr/bin/env bash
# Create .venv with every dependency pinned in requirements.txt, installing the Debian packages
# the wheels need when they are absent. Idempotent: `make` calls it when .venv is missing or stale.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3.11}
command -v "$PYTHON" >/dev/null || PYTHON=python3

apt_install() {
  local sudo=""
  [ "$(id -u)" -eq 0 ] || sudo="sudo"
  echo "setup: installing Debian packages: $*"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "$@" >/dev/null
}

# Open3D links libusb-1.0; the venv module needs python3-venv on a minimal Debian.
missing=()
ldconfig -p | grep -q 'libusb-1.0.so.0' || missing+=(libusb-1.0-0)
"$PYTHON" -c 'import ensurepip' 2>/dev/null || missing+=(python3-venv)
command -v cmake >/dev/null || missing+=(cmake)
command -v g++ >/dev/null || missing+=(g++)
[ ${#missing[@]} -eq 0 ] || apt_install "${missing[@]}"

if [ ! -x "$VENV/bin/python" ]; then
  echo "setup: creating $VENV"
  "$PYTHON" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install -q --upgrade "pip>=24" 2>&1 | grep -v '^WARNING: Location' || true
echo "setup: installing pinned requirements (first time: ~2 minutes)"
"$VENV/bin/python" -m pip install -q -r requirements.txt 2>&1 | grep -v '^WARNING: Location' || true
"$VENV/bin/python" -m pip install -q --no-deps -e . 2>&1 | grep -v '^WARNING: Location' || true
# Fail loudly if anything is missing rather than at the first test.
"$VENV/bin/python" -c 'import numpy, scipy, numba, open3d, onnxruntime, cv2, rosbags, plyfile, rclpy, semcal_ros'
for hook in .ci/setup.d/*.sh; do
  [ -e "$hook" ] || continue
  echo "setup: $hook"
  VENV="$VENV" bash "$hook"
done
echo "setup: done"
