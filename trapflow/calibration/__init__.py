"""Stereo calibration: the camera model, calibration files in and out, rectification,
checkerboard calibration."""
