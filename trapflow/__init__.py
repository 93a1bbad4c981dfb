"""trapflow: a runtime for camera traps that think.

Capture publishes stereo pairs, a broker hands them to worker pools with
back-pressure, and a normalizer turns results into compact JSON lines.
"""

__version__ = "0.1.0"
