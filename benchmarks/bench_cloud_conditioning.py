"""Cloud conditioning benchmark (twinfocus.twins.digital_twin.condition): what it makes of camera clouds.

For each reference shape (plane, cylinder, bent plate) and each camera of the field-like scenes
(A: 0.5 mm z / 0.2 mm x, y; B: 1 mm z / 0.3 mm; C: 1.6 mm z / 0.3 mm; each with a quarter of the
surface missing in patches and 3 % outliers; plus a worst case: 2 mm on every axis, 40 % holes,
5 % outliers), ``draws`` clouds: the surface model chosen, the measured noise, the model's depth
error against the true surface (mean |dz|, mm; the raw cloud's beside it), the outline's IoU
against the true outline on the 100 x 100 reference grid, and the time. Then clouds of 10^3 ..
10^6 points: time and peak memory of the conditioning. Writes ``cloud_conditioning.json`` to the
output folder and ``docs/figures/cloud_conditioning.png`` (camera cloud -> outline -> template).

Run: ``python -m benchmarks.bench_cloud_conditioning --out benchmarks/results [--draws 5]``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time
import warnings
from pathlib import Path

import numpy as np

CAMERAS = {
    "A": ((0.2e-3, 0.2e-3, 0.5e-3), 0.25, 0.03),
    "B": ((0.3e-3, 0.3e-3, 1.0e-3), 0.25, 0.03),
    "C": ((0.3e-3, 0.3e-3, 1.6e-3), 0.25, 0.03),
    "worst": ((2e-3, 2e-3, 2e-3), 0.40, 0.05),
}


def _depth_error(points, exact):
    from scipy.interpolate import griddata

    return float(np.mean(np.abs(points[:, 2] - griddata(exact[:, :2], exact[:, 2], points[:, :2], method="nearest"))))


def main(
    out_dir: str | os.PathLike = "benchmarks/results",
    draws: int = 5,
    figure: str | None = "docs/figures/cloud_conditioning.png",
) -> dict:
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.simulation.scenario import Scenario
    from twinfocus.twins.digital_twin.camera_cloud import camera_cloud
    from twinfocus.twins.digital_twin.condition import condition_cloud, support_on_grid

    warnings.simplefilter("ignore")
    rows = []
    for shape in ("plane", "cylinder", "bent"):
        sc = Scenario(reference_shape=shape)
        grid = ImageGrid.from_roi(sc.reference_roi(), 100)
        exact = sc.scene().object("reference").surface_points(0.5e-3)
        truth = support_on_grid(exact, grid)
        for cam, (noise, holes, outliers) in CAMERAS.items():
            res = []
            for d in range(draws):
                cloud = camera_cloud(exact[::4], noise, holes, outliers, 0.0, rng=d)
                t0 = time.perf_counter()
                r = condition_cloud(cloud, grid)
                dt = time.perf_counter() - t0
                s = support_on_grid(r.points_m, grid)
                res.append(
                    (
                        r.surface,
                        r.info["noise_sd_m"] * 1e3,
                        _depth_error(r.points_m, exact) * 1e3,
                        _depth_error(cloud, exact) * 1e3,
                        (s & truth).sum() / (s | truth).sum(),
                        dt,
                    )
                )
            surfaces = [x[0] for x in res]
            a = np.array([x[1:] for x in res], float)
            row = {
                "shape": shape,
                "camera": cam,
                "surfaces": {k: surfaces.count(k) for k in set(surfaces)},
                **{
                    f"{k}_mean": round(float(a[:, i].mean()), 3)
                    for i, k in enumerate(("noise_mm", "model_dz_mm", "raw_dz_mm", "outline_iou", "seconds"))
                },
                **{
                    f"{k}_sd": round(float(a[:, i].std()), 3)
                    for i, k in enumerate(("noise_mm", "model_dz_mm", "raw_dz_mm", "outline_iou", "seconds"))
                },
            }
            rows.append(row)
            print(json.dumps(row))

    sc = Scenario()
    grid = ImageGrid.from_roi(sc.reference_roi(), 100)
    exact = sc.scene().object("reference").surface_points(0.5e-3)
    sizes = []
    for n in (1_000, 10_000, 100_000, 1_000_000):
        rng = np.random.default_rng(n)
        cloud = exact[rng.integers(0, exact.shape[0], n)] + rng.normal(size=(n, 3)) * 1e-3
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        t0 = time.perf_counter()
        r = condition_cloud(cloud, grid)
        dt = time.perf_counter() - t0
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        sizes.append(
            {
                "points": n,
                "seconds": round(dt, 3),
                "peak_rss_growth_mb": round((peak - before) / 1024, 1),
                "peak_rss_mb": round(peak / 1024, 1),
                "surface": r.surface,
            }
        )
        print(json.dumps(sizes[-1]))

    doc = {
        "draws": draws,
        "cameras": {
            k: {"noise_sd_m": v[0], "hole_fraction": v[1], "outlier_fraction": v[2]} for k, v in CAMERAS.items()
        },
        "scenes": rows,
        "sizes": sizes,
    }
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "cloud_conditioning.json").write_text(json.dumps(doc, indent=2) + "\n")
    if figure:
        _figure(Path(figure))
    return doc


def _figure(path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.motion.trajectory import paper_raster, phase_centres
    from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array
    from twinfocus.simulation.scenario import Scenario
    from twinfocus.twins.digital_twin.camera_cloud import camera_cloud
    from twinfocus.twins.digital_twin.condition import digital_twin_reference, support_on_grid

    pos = phase_centres(paper_raster(6, 65, row_pitch_m=0.004), mmwcas_virtual_array())
    fig, ax = plt.subplots(3, 4, figsize=(13, 9.5))
    for i, shape in enumerate(("plane", "cylinder", "bent")):
        sc = Scenario(reference_shape=shape)
        grid = ImageGrid.from_roi(sc.reference_roi(), 100)
        exact = sc.scene().object("reference").surface_points(0.5e-3)
        cloud = camera_cloud(exact[::4], (0.3e-3, 0.3e-3, 1e-3), 0.25, 0.03, 2e-3, rng=1)
        ref = digital_twin_reference(cloud, pos, Chirp(), grid)
        ext = [grid.x0 * 100, grid.x1 * 100, grid.y1 * 100, grid.y0 * 100]
        a = ax[i, 0]
        sel = np.abs(cloud[:, 2] - np.median(cloud[:, 2])) < 0.03
        s = a.scatter(cloud[sel, 0] * 100, cloud[sel, 1] * 100, c=(cloud[sel, 2] - 0.6) * 1e3, s=1, cmap="viridis")
        a.set_xlim(ext[0], ext[1])
        a.set_ylim(ext[2], ext[3])
        a.set_aspect("equal")
        fig.colorbar(s, ax=a, label="z - 0.6 m (mm)")
        a.set_title(f"{shape}: camera cloud (1 mm z noise,\n25 % holes, 3 % outliers, 2 mm offset)", fontsize=9)
        a = ax[i, 1]
        s = a.scatter(
            ref.cloud.points_m[:, 0] * 100,
            ref.cloud.points_m[:, 1] * 100,
            c=(ref.cloud.points_m[:, 2] - 0.6) * 1e3,
            s=1,
            cmap="viridis",
        )
        a.set_xlim(ext[0], ext[1])
        a.set_ylim(ext[2], ext[3])
        a.set_aspect("equal")
        fig.colorbar(s, ax=a, label="z - 0.6 m (mm)")
        a.set_title(f"conditioned: '{ref.surface}' model", fontsize=9)
        truth = support_on_grid(exact, grid)
        rgb = np.zeros(grid.shape + (3,))
        rgb[..., 1] = truth
        rgb[..., 0] = ref.support
        ax[i, 2].imshow(rgb, extent=ext)
        ax[i, 2].set_title("support mask (red) vs true outline (green);\nyellow: both", fontsize=9)
        ax[i, 3].imshow(ref.template, extent=ext, cmap="gray")
        ax[i, 3].set_title("template on the reference grid", fontsize=9)
        for a in ax[i]:
            a.set_xlabel("x (cm)")
            a.set_ylabel("y (cm)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="benchmarks/results")
    p.add_argument("--draws", type=int, default=5)
    a = p.parse_args()
    main(a.out, a.draws)
