"""Events: stereo pairs kept around a configured result, in event folders."""
