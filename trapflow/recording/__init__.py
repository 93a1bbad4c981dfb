"""Recordings: the MCAP recorder and its ROS 2 / Foxglove message builders."""
