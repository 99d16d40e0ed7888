"""Reading and writing rosbag2 MCAP bags of the graph's topics (no ROS runtime needed)."""
