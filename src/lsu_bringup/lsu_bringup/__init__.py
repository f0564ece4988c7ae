"""The scan_coordinator node, launch files and the lsu command (launch, run, graph introspection, doctor, bags)."""
