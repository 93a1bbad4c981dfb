"""Worker pools: the local and remote pool workers and the one per-pair path (decode, plugin,
result) they share with batch chunks."""
