"""The normalizer: one compact JSON line per result for the disk and the modem."""
