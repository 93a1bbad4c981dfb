"""The motion gate: a cheap change detector per pair (motion), the pure decision core that
feeds or withholds pairs per gated pool (policy), and the energy estimate (energy)."""
