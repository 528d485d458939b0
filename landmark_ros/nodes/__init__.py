"""Thin rclpy nodes: message -> arrays -> pipeline -> message -> publish."""
