"""Bags (rosbags typestore, reader, writer, player, recorder), message introspection and the lsu bag commands; no rclpy at import."""
