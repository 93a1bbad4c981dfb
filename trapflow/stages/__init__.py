"""The per-pair pipeline stages: capture, workers (local and remote), the normalizer and
its result JSON, events."""
