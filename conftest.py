# Workspace-wide pytest setup: per-session ROS domain, LOCALHOST discovery, rclpy fixtures.
pytest_plugins = ["lsu_testing.plugin"]
