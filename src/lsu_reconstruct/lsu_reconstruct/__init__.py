"""Stereo model, epipolar matching, triangulation, PointCloud2 codec and the stereo_matcher node."""
