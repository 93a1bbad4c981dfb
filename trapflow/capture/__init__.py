"""Capture: the node that publishes timestamped stereo pairs, and its wait-or-drop choice."""
