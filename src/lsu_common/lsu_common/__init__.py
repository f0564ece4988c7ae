"""Helpers every LSU package shares, one owner each.

- `lsu_common.node`: the console-script ``main()`` runner of a node.
- `lsu_common.params`: table-driven parameter declaration (descriptors, ranges, read-only,
  on-set check and post-set apply callbacks).
- `lsu_common.qos`: the named QoS profiles of the graph contract.
- `lsu_common.stamps`: integer-nanosecond stamp conversions.
- `lsu_common.images`: the one sensor_msgs/Image encoder and decoder.
- `lsu_common.diagnostics`: one ``/diagnostics`` status message.

Importing this package imports no rclpy; the modules that need it import it themselves.
"""
