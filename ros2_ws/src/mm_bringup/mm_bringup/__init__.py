"""Bringup of the mm graph: configs, launch files, the rosbag2-compatible MCAP recorder and player, topic and bag tools, the demo and benchmarks."""
