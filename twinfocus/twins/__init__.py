"""The twin references: templates from a template scan (the physical twin), the digital twin
from a camera, and the content-addressed cache both are kept in.
"""
