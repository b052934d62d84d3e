"""PNG files through matplotlib on its file-only Agg back-end, loaded on first use."""

from __future__ import annotations


def pyplot():
    """matplotlib.pyplot on the file-only Agg back-end, imported on first use (0.6 s)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
