"""Reading clips: camera files (given or from SfM), the world's up, ingest and frame extraction."""
