"""Associating detections into tracks (clique partitioning) and the relations people state between tracks."""
