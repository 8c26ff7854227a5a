"""Training: rows to batches, sampling, losses, checkpoints, memory estimate, colour warm-up, one trainer per stage, finished runs."""
