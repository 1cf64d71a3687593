"""On-disk formats: the Zarr job store, job records, and input dataset folders.

Only this package knows the layout; ``worker`` and ``service`` go through it.
"""
