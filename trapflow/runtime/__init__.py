"""The process base every node runs on: lifecycle and exit codes, the log channel,
signals, sd_notify and rate-limited logging."""
