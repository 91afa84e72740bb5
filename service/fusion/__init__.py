"""Fusion of the correlated tracks into one system track per target (numerics, no I/O)."""
