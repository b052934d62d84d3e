"""The radar: the FMCW chirp and its range compression, the MIMO array from a board file, what the
array gets wrong as hardware, its channel calibration, and the scan it records.
"""
