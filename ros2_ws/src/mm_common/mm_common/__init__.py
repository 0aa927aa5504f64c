"""Shared helpers for the mm nodes: the Jazzy main() pattern, parameter declaration with descriptors, MCAP/rosbag2 schema tools."""
