#!/usr/bin/env bash
# Source ROS 2 Jazzy and the mm workspace, then run the given command (ros2 run/launch/bag ...).
set -e
source /opt/ros/jazzy/setup.bash
source /mm/ros2_ws/install/setup.bash
exec "$@"
