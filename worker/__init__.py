"""Computation for maxfs-ps: the exact Max-FS solver, its references, and tile tasks.

Nothing in this package speaks HTTP; ``service`` builds on it.
"""
