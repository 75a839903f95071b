"""9-DoF poses from 2D-3D correspondences: initialisation, Levenberg-Marquardt, support prior, checks."""
