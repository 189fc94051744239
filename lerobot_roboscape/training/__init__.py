"""What every trainer shares: the supervised loop on Accelerate, the checkpoint layout, and the records a run keeps
beside its checkpoints (history, videos)."""
