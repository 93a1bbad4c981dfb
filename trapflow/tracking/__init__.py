"""Observations from detections: tracks across pairs, interval counts (visits, MaxN, dwell),
and MOTChallenge text files. Pure cores: callers pass capture times in."""
