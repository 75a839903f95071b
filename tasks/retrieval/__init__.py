"""Ranking CAD models for each track: appearance descriptors, whitening, class-label similarity."""
