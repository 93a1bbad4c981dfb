"""The broker: its pure decision core (state, policy, remote workers) beside its process
shell, its tap and its remote-worker socket."""
