"""Sub-pixel laser line extraction (thesis detector and sub-pixel detectors) and the laser_extractor node."""
