"""Minimisers: the coarse search, Levenberg-Marquardt and Adam; the normal refinement's Schur-complement system."""
