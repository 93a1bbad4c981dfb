"""Power: the energy model and the CPU metering it is fed by."""
