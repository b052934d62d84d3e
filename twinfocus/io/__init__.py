"""Files: atomic writes, paths from data made safe, checksums, the PNG back-end.

The lowest layer of the library: it imports nothing of TwinFocus but :mod:`twinfocus.errors`.
"""
