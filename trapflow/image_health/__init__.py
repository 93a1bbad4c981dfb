"""Image health: a fouled port or turbid water, told from an empty sea (docs/image-health.md).

measure.py: a few statistics of one small grey copy of a left image (pure, ~1 ms).
watch.py: the baseline, the medians and the flags with their hold and hysteresis (pure: the
caller passes the times). trapflow.capture.node runs them on one pair every few seconds.
"""
