#!/usr/bin/env bash
# Entry point of the Jetson image: the ROS 2 Jazzy and LEAP-NBV environments, then the command
# (default: ros2 launch leapnbv_bringup leapnbv.launch.py).
set -eo pipefail
# shellcheck disable=SC1091
source /opt/ros/jazzy/setup.bash
# shellcheck disable=SC1091
source /opt/leapnbv/install/setup.bash
for model in yolov8s.onnx smplerx_student.onnx SMPLX_NEUTRAL.npz; do
  [ -e "/opt/leapnbv/models/$model" ] || echo "[leapnbv] note: /opt/leapnbv/models/$model is missing (mount the models folder: docker/jetson/README.md)" >&2
done
exec "$@"
