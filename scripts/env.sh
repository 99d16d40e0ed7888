#!/usr/bin/env bash
# Run a command inside the LEAP-NBV environment: the venv, the colcon install space, the Fast DDS
# profile for large messages and localhost-only discovery.  Usage: scripts/env.sh CMD [ARGS...]
# (or `source scripts/env.sh` in an interactive bash to get the same environment).
_leapnbv_root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
export VIRTUAL_ENV=$_leapnbv_root/.venv
export PATH=$VIRTUAL_ENV/bin:$PATH
export AMENT_PREFIX_PATH=$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}
if [ -f "$_leapnbv_root/ros2_ws/install/local_setup.bash" ]; then
  # shellcheck disable=SC1091
  COLCON_TRACE= source "$_leapnbv_root/ros2_ws/install/local_setup.bash"
fi
export FASTRTPS_DEFAULT_PROFILES_FILE=${FASTRTPS_DEFAULT_PROFILES_FILE:-$_leapnbv_root/src/leapnbv_bringup/config/fastdds_large_messages.xml}
export ROS_AUTOMATIC_DISCOVERY_RANGE=${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}
export RMW_IMPLEMENTATION=${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}
export PYTHONUNBUFFERED=1
if [ "${BASH_SOURCE[0]}" = "$0" ]; then
  exec "$@"
fi
