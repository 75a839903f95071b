"""The dataset that comes out: objects per clip, official and Scan2CAD exports, statistics."""
