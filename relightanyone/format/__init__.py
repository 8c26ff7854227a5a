"""The normalized dataset format (version 1): schema, shards, reader, PyTorch dataset, validation."""
