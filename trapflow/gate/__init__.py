"""The motion gate: a cheap change detector per pair (motion), the pure decision core that
feeds or withholds pairs per gated pool (policy), what the normalizer tells it of tracks and
a moving rig (hint), capture's duty cycling (duty), and the energy estimate (energy)."""
