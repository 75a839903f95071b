"""Finding objects in frames: the ONNX detectors and the appearance embedder."""
