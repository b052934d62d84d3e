"""Images from a scan: grids, back-projection, the sub-image basis, volumes, depth search,
image-quality metrics and the torch device they run on.
"""
