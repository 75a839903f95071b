"""The CAD library: sources, canonical ingest, symmetry, classes, rendered views and their descriptors."""
