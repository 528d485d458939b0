"""Landmark-based perception for multi-robot teams (ROS 2 Jazzy)."""
