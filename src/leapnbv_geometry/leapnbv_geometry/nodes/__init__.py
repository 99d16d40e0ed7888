"""ROS 2 nodes of the geometry stage (thin wrappers around the cores)."""
