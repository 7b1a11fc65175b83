# Source this file (bash) to use gpis_grasp_ros from the repository:
#     source scripts/env.sh
# It activates .venv, sources the colcon workspace (install/setup.bash), puts the package's
# executables (gpis-grasp, the nodes) on PATH and keeps DDS traffic on this machine unless you
# chose otherwise (ROS_AUTOMATIC_DISCOVERY_RANGE / ROS_DOMAIN_ID are only set when unset).
_gpis_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
if [ ! -x "$_gpis_root/.venv/bin/python" ] || [ ! -f "$_gpis_root/install/setup.bash" ]; then
  echo "gpis_grasp_ros is not set up yet: run 'make setup' (or 'bash scripts/setup.sh') first" >&2
  return 1 2>/dev/null || exit 1
fi
# shellcheck disable=SC1091
. "$_gpis_root/.venv/bin/activate"
# colcon's setup scripts read unset variables; relax nounset while sourcing them.
case $- in *u*) _gpis_nounset=1; set +u ;; *) _gpis_nounset=0 ;; esac
# shellcheck disable=SC1091
. "$_gpis_root/install/setup.bash"
[ "$_gpis_nounset" = 1 ] && set -u
export PATH="$_gpis_root/install/gpis_grasp_ros/lib/gpis_grasp_ros:$PATH"
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$((40 + $$ % 60))}"
unset _gpis_root _gpis_nounset
