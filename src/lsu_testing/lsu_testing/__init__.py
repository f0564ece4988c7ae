"""The pytest plugin (per-session ROS domain, graph fixtures) and simulated bags for tests and benchmarks."""
