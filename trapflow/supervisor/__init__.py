"""The supervisor: its pure supervision core (state, actions, pool control, ladder)
beside its process shell, control server, sensors, report, ledger and summary."""
