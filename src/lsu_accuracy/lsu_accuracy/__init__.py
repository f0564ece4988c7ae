"""The accuracy study: extraction, matching, meshing and smoothing against renderer ground truth or recorded board bags (lsu accuracy)."""
