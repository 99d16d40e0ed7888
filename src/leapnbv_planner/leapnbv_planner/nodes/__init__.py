"""ROS 2 node of the planner stage (a thin wrapper around the cores)."""
