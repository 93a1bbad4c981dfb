"""Measurement with the stereo rig: range, position and length of what a box holds; the
board check that tells whether a calibration still measures right.
"""
