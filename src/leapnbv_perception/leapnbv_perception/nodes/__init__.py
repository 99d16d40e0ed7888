"""ROS 2 nodes of the perception stage (thin wrappers around the cores)."""
