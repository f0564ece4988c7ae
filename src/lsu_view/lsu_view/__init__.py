"""Live view of the LSU graph in Foxglove (the foxglove_bridge node and `lsu view`)."""
