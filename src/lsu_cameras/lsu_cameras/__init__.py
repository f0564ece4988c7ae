"""Stereo camera sources (v4l2, image folders, simulated rig), stereo calibration and the stereo_camera node."""
