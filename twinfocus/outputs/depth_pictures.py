"""PNG pictures of where things are: the depth search's sharpness curve and a volume's
maximum-intensity projection and depth map (matplotlib, file-only)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from twinfocus.imaging.depth_search import DepthSearch
from twinfocus.imaging.grid import VolumeGrid
from twinfocus.io.png import pyplot


def depth_search_picture(path, search: DepthSearch, typed_m: float | None = None) -> None:
    """``depth_search.png``: sharpness (sum |I|^4, relative to the best plane) against depth, the
    coarse planes and the fine ones, the depth found and the typed one when there was one.

    path : a file name or a binary file open for writing. Returns nothing."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.4), dpi=110)
    ax.plot(search.coarse_z_m * 100, search.coarse_score, "o-", ms=3, color="0.5", label="coarse planes")
    ax.plot(search.fine_z_m * 100, search.fine_score, "o-", ms=3, color="C1", label="fine planes")
    ax.axvline(search.depth_m * 100, color="C3", lw=1, label=f"found {search.depth_m * 100:.1f} cm")
    if typed_m is not None:
        ax.axvline(typed_m * 100, color="C0", lw=1, ls="--", label=f"typed {typed_m * 100:.1f} cm")
    ax.set_xlabel("depth z (cm)")
    ax.set_ylabel("sharpness (relative)")
    ax.set_title("target depth from the scan")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, format="png")
    plt.close(fig)


def volume_pictures(out_dir: str | Path, mip: np.ndarray, depth: np.ndarray, grid: VolumeGrid) -> list[Path]:
    """``volume_mip.png`` (the maximum-intensity projection along depth, dB) and
    ``volume_depth.png`` (the depth of the brightest voxel, cm, blank where the projection is
    faint) from :func:`twinfocus.imaging.volume.projections`."""
    plt = pyplot()
    p = grid.plane
    extent = (p.x0 * 100, p.x1 * 100, p.y0 * 100, p.y1 * 100)
    out = []
    db = 20 * np.log10(np.maximum(mip / max(float(mip.max()), 1e-30), 1e-6))
    for name, img, kw, label in (
        ("volume_mip.png", db, {"cmap": "inferno", "vmin": -30, "vmax": 0}, "dB"),
        ("volume_depth.png", depth * 100, {"cmap": "viridis", "vmin": grid.z0 * 100, "vmax": grid.z1 * 100}, "z (cm)"),
    ):
        fig, ax = plt.subplots(figsize=(5, 4), dpi=110)
        im = ax.imshow(img, origin="lower", extent=extent, **kw)
        fig.colorbar(im, ax=ax, label=label)
        ax.set_xlabel("x (cm)")
        ax.set_ylabel("y (cm)")
        ax.set_title("maximum over depth" if name == "volume_mip.png" else "depth of the brightest voxel")
        fig.tight_layout()
        fig.savefig(Path(out_dir) / name)
        plt.close(fig)
        out.append(Path(out_dir) / name)
    return out
