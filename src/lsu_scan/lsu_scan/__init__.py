"""The scan_coordinator node (stop-snap scans through the /lsu/scan action), its scan plan and laser guard, and LsuScanner, the Python API."""
