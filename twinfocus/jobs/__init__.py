"""Running long work: progress lines, the Dask cluster, where a number was measured.

Beside :mod:`twinfocus.io` at the bottom of the library's layers.
"""
