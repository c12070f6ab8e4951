"""Bags and logs: reading and writing rosbag2 / ROS 1 bags, importing column logs, inspecting a bag."""
