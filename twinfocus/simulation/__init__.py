"""Simulated scans: the IF samples of point scatterers, and the paper's protocol as one call."""
