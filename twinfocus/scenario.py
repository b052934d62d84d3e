"""The paper's evaluation protocol as one call: a handheld scan and a motion-stage template scan.

A :class:`Scenario` fixes the scene (two letters, distance, separation, materials, occluder,
clutter), the trajectory, the motion errors and the impairments (speckle, thermal noise, the
template's placement error). :func:`simulate_scenario` returns the scan of the whole scene on
tracked (erroneous) positions with the truth attached, and the template scan: the reference
alone, placed ``template_offset_m`` off, scanned on accurate positions as a motion stage would.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.grid import ImageGrid
from twinfocus.motion import apply_position_errors, drift_errors, gaussian_errors, vio_errors
from twinfocus.radar import Chirp, mmwcas_virtual_array
from twinfocus.scan import Scan
from twinfocus.scene import Scene, paper_scene, scatterer_spacing_m
from twinfocus.simulate import add_thermal_noise, simulate_if
from twinfocus.trajectory import handheld_zigzag, paper_raster, phase_centres

#: DESIGN.md's regions of interest for the default scene (X0, X1, Y0, Y1, Z).
PAPER_REFERENCE_ROI = (-0.15, 0.0, -0.11, 0.12, 0.6)
PAPER_TARGET_ROI = (0.02, 0.13, -0.11, 0.12, 0.6)


@dataclass
class Scenario:
    """Everything that defines one simulated capture (defaults: the paper with realistic
    impairments: speckle, 10 dB per-sample SNR, 0.5 mm x/y/z jitter, 1 mm template offset)."""

    reference: str = "A"
    target: str = "F"
    distance_m: float = 0.6
    separation_deg: float = 10.0
    height_m: float = 0.127
    target_height_m: float | None = None
    reference_material: str = "metal"
    target_material: str = "metal"
    occluder: str | None = None
    clutter: bool = False
    trajectory: str = "raster"  # "raster" (motion-stage geometry) or "zigzag" (hand sweep)
    error_model: str = "gaussian"  # "gaussian", "drift" or "vio"
    error_sigma_m: tuple = (0.5e-3, 0.5e-3, 0.5e-3)
    snr_db: float | None = 10.0
    speckle: bool = True
    template_offset_m: tuple = (1e-3, 0.0, 0.0)
    spacing_m: float | None = None
    range_step_m: float | None = None
    n_columns: int = 6
    n_rows: int = 130
    seed: int = 0
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)

    def scene(self) -> Scene:
        scene = paper_scene(
            reference=self.reference, target=self.target, distance_m=self.distance_m,
            separation_deg=self.separation_deg, height_m=self.height_m,
            reference_material=self.reference_material, target_material=self.target_material,
            occluder=self.occluder, clutter=self.clutter,
        )
        if self.target_height_m is not None and self.target_height_m != self.height_m:
            bigger = paper_scene(reference=self.reference, target=self.target, distance_m=self.distance_m,
                                 separation_deg=self.separation_deg, height_m=self.target_height_m,
                                 target_material=self.target_material)
            scene.objects[1] = bigger.object("target")
        return scene

    def reference_roi(self) -> tuple:
        """A reference region around the reference letter (DESIGN.md's for the defaults)."""
        return _roi_around(self.scene().object("reference"), self.distance_m, PAPER_REFERENCE_ROI, self)

    def target_roi(self) -> tuple:
        return _roi_around(self.scene().object("target"), self.distance_m, PAPER_TARGET_ROI, self)


def _roi_around(obj, z, default, sc: Scenario) -> tuple:
    if (sc.distance_m, sc.separation_deg, sc.height_m, sc.target_height_m) == (0.6, 10.0, 0.127, None):
        return default
    c = obj.corners_m()
    margin = 0.015
    lo, hi = c[:, :2].min(axis=0) - margin, c[:, :2].max(axis=0) + margin
    return (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]), float(z))


def scenario_positions(sc: Scenario, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(true phase centres (M, K, 3), tracked phase centres (M, K, 3), timestamps_ns (M,))."""
    if sc.trajectory == "raster":
        poses = paper_raster(sc.n_columns, sc.n_rows)
    elif sc.trajectory == "zigzag":
        poses = handheld_zigzag(sc.n_columns, sc.n_rows, rng=rng)
    else:
        raise TwinFocusError(f"unknown trajectory {sc.trajectory!r}; use 'raster' or 'zigzag'")
    true = phase_centres(poses, mmwcas_virtual_array())
    m = true.shape[0]
    if sc.error_model == "gaussian":
        err = gaussian_errors(m, sc.error_sigma_m, rng)
    elif sc.error_model == "drift":
        err = drift_errors(poses.timestamps_ns, sc.error_sigma_m, rng=rng)
    elif sc.error_model == "vio":
        err = vio_errors(poses.timestamps_ns, rng=rng)
    else:
        raise TwinFocusError(f"unknown error model {sc.error_model!r}; use 'gaussian', 'drift' or 'vio'")
    return true, apply_position_errors(true, err), poses.timestamps_ns


def simulate_scenario(sc: Scenario, chirp: Chirp | None = None, progress=None) -> tuple[Scan, Scan]:
    """Simulate the handheld scan of the whole scene and the reference's motion-stage scan.

    Returns (scan, template_scan). ``scan.positions`` are the tracked (erroneous) positions,
    ``scan.positions_true`` the truth; the template scan's positions are exact.
    """
    chirp = chirp or Chirp()
    rng = np.random.default_rng(sc.seed)
    true, tracked, stamps = scenario_positions(sc, rng)
    scene = sc.scene()
    spacing = sc.spacing_m or scatterer_spacing_m(sc.distance_m)
    sim_kw = {} if sc.range_step_m is None else {"range_step_m": sc.range_step_m}
    scene_seed = int(rng.integers(0, 2**31))
    pts, amps = scene.scatterers(spacing, scene_seed, speckle=sc.speckle)
    data = simulate_if(pts, amps, true, chirp, progress=progress, **sim_kw)
    if sc.snr_db is not None:
        data = add_thermal_noise(data, sc.snr_db, rng)
    scan = Scan(data, tracked, chirp, positions_true=true, timestamps_ns=stamps)

    # Template: the same reference object (same scatterers: streams are keyed by object name),
    # moved by the placement error, alone, on the stage's exact positions.
    ref_scene = scene.select("reference", occluders=False)
    ref = ref_scene.objects[0]
    ref_scene.objects[0] = replace(ref, centre_m=np.asarray(ref.centre_m) + np.asarray(sc.template_offset_m, float))
    stage = phase_centres(paper_raster(sc.n_columns, sc.n_rows), mmwcas_virtual_array())
    tpts, tamps = ref_scene.scatterers(spacing, scene_seed, speckle=sc.speckle)
    tdata = simulate_if(tpts, tamps, stage, chirp, **sim_kw)
    if sc.snr_db is not None:
        tdata = add_thermal_noise(tdata, sc.snr_db, rng)
    template_scan = Scan(tdata, stage, chirp, positions_true=stage)
    return scan, template_scan


def scenario_grids(sc: Scenario, size: int = 100) -> tuple[ImageGrid, ImageGrid]:
    return ImageGrid.from_roi(sc.reference_roi(), size), ImageGrid.from_roi(sc.target_roi(), size)
