"""The process base every node runs on: lifecycle and exit codes, the log channel,
signals, sd_notify, rate-limited logging and the plugin registry."""
