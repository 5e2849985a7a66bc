#!/usr/bin/env bash
# Build the ROS 2 interface packages into the venv: semcal_interfaces (the Calibrate action) and, where
# tf2_msgs is missing (ROS 2 from PyPI wheels has none), a tf2_msgs with TFMessage for /tf_static.
#
# Called by .ci/setup-env.sh after the pip install, with $VENV set. The packages are installed into
# the venv prefix itself (lib/, lib/python3.X/site-packages, share/ament_index), so running the nodes
# needs no sourcing and no extra environment variables. Idempotent: a stamp keyed on the sources and
# the pinned build wheels makes a second run take well under a second.
# Facts this relies on: ../shared/notes/ros2-from-pypi.md (undeclared build wheels, hard-coded include
# paths in the wheels' CMake exports, AMENT_PREFIX_PATH at build time).
set -euo pipefail
cd "$(dirname "$0")/../.."
VENV=$(cd "${VENV:-.venv}" && pwd)
PY="$VENV/bin/python"
STAMP="$VENV/.semcal-interfaces.stamp"
WORK="$VENV/var/semcal-interfaces"   # colcon build/install/log trees (kept for fast rebuilds)

sources=(requirements-build.txt .ci/setup.d/10-interfaces.sh)
while IFS= read -r f; do sources+=("$f"); done < <(find semcal_interfaces -type f | LC_ALL=C sort)
key=$(cat "${sources[@]}" | sha256sum | cut -d' ' -f1)

have_interfaces() {
  "$PY" -c 'from semcal_interfaces.action import Calibrate; from tf2_msgs.msg import TFMessage' \
    >/dev/null 2>&1
}

if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$key" ] && have_interfaces; then
  echo "interfaces: semcal_interfaces and tf2_msgs up to date"
  exit 0
fi

# Python.h is needed by the generated Python extensions (Debian's python3.11 lacks it without -dev).
py_include=$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
if [ ! -f "$py_include/Python.h" ]; then
  sudo=""; [ "$(id -u)" -eq 0 ] || sudo="sudo"
  echo "interfaces: installing python3-dev (Python.h missing in $py_include)"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq python3-dev >/dev/null
fi

echo "interfaces: installing build-time wheels (requirements-build.txt)"
"$PY" -m pip install -q -r requirements-build.txt 2>&1 | grep -v '^WARNING: Location' || true

# The wheels' exported CMake targets name include directories of the machine that built them;
# point every such non-existent Python / numpy include directory at this venv's.
"$PY" - "$VENV" <<'EOF'
import pathlib, re, sys, sysconfig
import numpy

venv = pathlib.Path(sys.argv[1])
py_inc, np_inc = sysconfig.get_paths()["include"], numpy.get_include()
prop = re.compile(r'(INTERFACE_INCLUDE_DIRECTORIES ")([^"]*)(")')

def fix(path: str) -> str:
    if pathlib.Path(path).exists() or "${" in path:
        return path
    if re.search(r"include/python3\.\d+$", path):
        return py_inc
    if re.search(r"numpy/(_core|core)/include$", path):
        return np_inc
    return path

changed = 0
for cmake in (venv / "share").glob("*/cmake/*.cmake"):
    text = cmake.read_text()
    new = prop.sub(lambda m: m[1] + ";".join(fix(p) for p in m[2].split(";")) + m[3], text)
    if new != text:
        cmake.write_text(new)
        changed += 1
print(f"interfaces: fixed include paths in {changed} CMake file(s)")
EOF

paths=(semcal_interfaces)
packages=(semcal_interfaces)
fallback_tf2=0
if ! "$PY" -c 'import tf2_msgs.msg' >/dev/null 2>&1 \
    || [ -f "$VENV/share/tf2_msgs/semcal_fallback" ]; then
  fallback_tf2=1
  paths+=(semcal_interfaces/fallback/tf2_msgs)
  packages+=(tf2_msgs)
fi

echo "interfaces: building ${packages[*]} with colcon"
mkdir -p "$WORK"
start=$SECONDS
# The venv prefix must be on AMENT_PREFIX_PATH (else "No 'rosidl_typesupport_c' found").
export AMENT_PREFIX_PATH="$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export CMAKE_PREFIX_PATH="$VENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
export PATH="$VENV/bin:$PATH"
if ! "$VENV/bin/colcon" --log-base "$WORK/log" build \
      --base-paths "${paths[@]}" --packages-select "${packages[@]}" \
      --build-base "$WORK/build" --install-base "$WORK/install" \
      --event-handlers console_cohesion- console_stderr+ status- summary+ \
      --cmake-args -DPython3_EXECUTABLE="$PY" -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release \
      > "$WORK/colcon.out" 2>&1; then
  cat "$WORK/colcon.out"
  echo "interfaces: colcon build failed; logs in $WORK/log" >&2
  exit 1
fi
for pkg in "${packages[@]}"; do
  cmake --install "$WORK/build/$pkg" --prefix "$VENV" > "$WORK/install-$pkg.out"
done
[ "$fallback_tf2" -eq 0 ] || echo "built by semcal_ros .ci/setup.d/10-interfaces.sh" \
  > "$VENV/share/tf2_msgs/semcal_fallback"

if ! have_interfaces; then
  echo "interfaces: built, but 'from semcal_interfaces.action import Calibrate' fails:" >&2
  "$PY" -c 'from semcal_interfaces.action import Calibrate; from tf2_msgs.msg import TFMessage' >&2
  exit 1
fi
echo "$key" > "$STAMP"
echo "interfaces: installed ${packages[*]} into $VENV in $((SECONDS - start)) s"
