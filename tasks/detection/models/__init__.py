"""Pretrained models: reproducible fetch + conversion, and their pre/post-processing."""
