"""The paper's evaluation protocol as one call: a handheld scan and a motion-stage template scan.

A :class:`Scenario` fixes the scene (two letters, distance, separation, materials, occluder,
clutter), the trajectory, the motion errors and the impairments (speckle, thermal noise, the
template's placement error). :func:`simulate_scenario` returns the scan of the whole scene on
tracked (erroneous) positions with the truth attached, and the template scan: the reference
alone, placed ``template_offset_m`` off, scanned on accurate positions as a motion stage would.

Every random draw comes from its own stream of the scenario's seed (:func:`scenario_stream`:
trajectory, scene, radar noise, tracking error, template noise), so the simulated sensors of the
node graph (``nodes/runtime/sim_backends.py``, each in its own process, the radar a block of frames at
a time) draw exactly the scan :func:`simulate_scenario` draws: ``twinfocus launch sim`` and
``twinfocus simulate`` agree for one seed (tests/test_graph_offline.py).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.grid import ImageGrid
from twinfocus.motion.tracking_errors import apply_pose_errors, draw_errors
from twinfocus.motion.trajectory import (
    Poses,
    handheld_zigzag,
    paper_raster,
    phase_centres,
    quat_from_rotvec,
    quat_multiply,
    quat_to_matrix,
)
from twinfocus.radar.array_errors import ArrayErrors, apply_array_errors_to_channels
from twinfocus.radar.board import load_board
from twinfocus.radar.fmcw import Chirp, VirtualArray, mmwcas_virtual_array
from twinfocus.radar.scan import Scan
from twinfocus.scene import PlanarObject, Scene, paper_scene, scatterer_spacing_m, shaped
from twinfocus.simulation.if_simulator import add_thermal_noise, simulate_if

#: the paper's regions of interest (docs/architecture.md section 2) for the default scene (X0, X1, Y0, Y1, Z).
PAPER_REFERENCE_ROI = (-0.15, 0.0, -0.11, 0.12, 0.6)
PAPER_TARGET_ROI = (0.02, 0.13, -0.11, 0.12, 0.6)
#: the paper's image size (pixels per side) and optimiser iterations. launch/paper.yaml and the
#: Makefile's demo take these values (tests/test_launch.py checks the launch file agrees).
PAPER_IMAGE_SIZE = 100
PAPER_ITERATIONS = 300


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
    error_model: str = (
        "gaussian"  # twinfocus.motion.tracking_errors.ERROR_MODELS: "gaussian", "drift", "vio", "hand", "none"
    )
    error_sigma_m: tuple = (0.5e-3, 0.5e-3, 0.5e-3)
    #: correlation time of "drift" and "hand" (seconds) and the array rotation of "hand" (degrees)
    correlation_time_s: float = 2.0
    rotation_sigma_deg: float = 0.15
    snr_db: float | None = 10.0
    speckle: bool = True
    template_offset_m: tuple = (1e-3, 0.0, 0.0)
    spacing_m: float | None = None
    range_step_m: float | None = None
    n_columns: int = 6
    n_rows: int = 130
    seed: int = 0
    extra: dict = field(default_factory=dict)
    # Field-like references: a rough surface (per-scatterer phase uniform in
    # +-reference_roughness_deg, magnitude x (1 +- reference_amplitude_spread)); a non-planar
    # shape (twinfocus.scene.SHAPES: 'plane', 'cylinder' radius m, 'bent' degrees; parameter None:
    # the shape's default); a target further from the aperture than the reference, along its ray.
    reference_roughness_deg: float | None = None
    reference_amplitude_spread: float = 0.3
    reference_shape: str = "plane"
    reference_shape_parameter: float | None = None
    target_depth_offset_m: float = 0.0
    #: board file of the radar's antenna layout (twinfocus.radar.board; None: TI's MMWCAS-RF-EVM)
    board: str | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    def scene(self) -> Scene:
        scene = paper_scene(
            reference=self.reference,
            target=self.target,
            distance_m=self.distance_m,
            separation_deg=self.separation_deg,
            height_m=self.height_m,
            reference_material=self.reference_material,
            target_material=self.target_material,
            occluder=self.occluder,
            clutter=self.clutter,
        )
        if self.target_height_m is not None and self.target_height_m != self.height_m:
            bigger = paper_scene(
                reference=self.reference,
                target=self.target,
                distance_m=self.distance_m,
                separation_deg=self.separation_deg,
                height_m=self.target_height_m,
                target_material=self.target_material,
            )
            scene.objects[1] = bigger.object("target")
        return _field_like(scene, self)

    def reference_roi(self) -> tuple:
        """A reference region around the reference letter (the paper's for the defaults, docs/architecture.md section 2)."""
        return _roi_around(self.scene().object("reference"), self.distance_m, PAPER_REFERENCE_ROI, self)

    def target_roi(self) -> tuple:
        if self.target_depth_offset_m:
            tgt = planar_object(self.scene(), "target")
            # distance_m=-1 only tells _roi_around this is not the paper's geometry (no fixed ROI)
            return _roi_around(tgt, float(tgt.centre_m[2]), None, replace(self, distance_m=-1.0))
        return _roi_around(self.scene().object("target"), self.distance_m, PAPER_TARGET_ROI, self)


def planar_object(scene: Scene, name: str) -> PlanarObject:
    """The paper scene's object ``name``, which paper_scene always builds as a planar mask."""
    obj = scene.object(name)
    assert isinstance(obj, PlanarObject)
    return obj


def _field_like(scene: Scene, sc: Scenario) -> Scene:
    """The Scenario's field-like options applied to the paper scene (twinfocus.scene does the work)."""
    ref = shaped(planar_object(scene, "reference"), sc.reference_shape, sc.reference_shape_parameter)
    if sc.reference_roughness_deg is not None:
        ref = replace(ref, roughness_deg=sc.reference_roughness_deg, amplitude_spread=sc.reference_amplitude_spread)
    scene.objects[0] = ref
    off = float(sc.target_depth_offset_m)
    if off:
        tgt = planar_object(scene, "target")
        c = np.asarray(tgt.centre_m, float)
        if not (np.isfinite(off) and c[2] + off > 0):
            raise TwinFocusError(f"target_depth_offset_m ({off}) must keep the target in front of the aperture")
        scene.objects[1] = replace(tgt, centre_m=c * (c[2] + off) / c[2])  # along its ray: same angle
    return scene


def _roi_around(obj, z, default, sc: Scenario) -> tuple:
    if (sc.distance_m, sc.separation_deg, sc.height_m, sc.target_height_m) == (0.6, 10.0, 0.127, None):
        return default
    c = obj.corners_m()
    margin = 0.015
    lo, hi = c[:, :2].min(axis=0) - margin, c[:, :2].max(axis=0) + margin
    return (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]), float(z))


#: Purposes of the scenario's random streams (:func:`scenario_stream`).
TRAJECTORY_STREAM, SCENE_STREAM, RADAR_NOISE_STREAM, TRACKING_STREAM, TEMPLATE_NOISE_STREAM = 1, 2, 3, 4, 5

#: The thermal noise level is set from the clean signal's power at every this-many-th position,
#: so that a sensor simulating a block of frames at a time knows it before the scan is complete.
NOISE_POWER_STRIDE = 10


def scenario_stream(sc: Scenario, purpose: int) -> np.random.Generator:
    """Independent random stream ``purpose`` (one of the ``*_STREAM`` constants) of the seed."""
    return np.random.default_rng([int(sc.seed), int(purpose)])


def scenario_poses(sc: Scenario, frame_period_s: float = 0.1, t0_ns: int = 0) -> Poses:
    """The true radar poses, one per radar frame (stamps ``t0_ns`` + k ``frame_period_s``)."""
    if sc.trajectory == "raster":
        return paper_raster(sc.n_columns, sc.n_rows, frame_period_s=frame_period_s, t0_ns=t0_ns)
    if sc.trajectory == "zigzag":
        return handheld_zigzag(
            sc.n_columns,
            sc.n_rows,
            frame_period_s=frame_period_s,
            rng=scenario_stream(sc, TRAJECTORY_STREAM),
            t0_ns=t0_ns,
        )
    raise TwinFocusError(f"unknown trajectory {sc.trajectory!r}; use 'raster' or 'zigzag'")


def scenario_array(sc: Scenario) -> VirtualArray:
    """The virtual array of the scenario's board (TI's MMWCAS-RF-EVM unless ``sc.board`` names a file)."""
    return mmwcas_virtual_array(None if sc.board is None else load_board(sc.board))


def scenario_positions(
    sc: Scenario, rng: np.random.Generator | None = None, frame_period_s: float = 0.1, t0_ns: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(true phase centres (M, K, 3), tracked phase centres (M, K, 3), timestamps_ns (M,)).

    rng : the tracking error's draws (default: the scenario's tracking stream)."""
    poses = scenario_poses(sc, frame_period_s, t0_ns)
    true = phase_centres(poses, scenario_array(sc))
    shift, turn = scenario_pose_errors(sc, poses.timestamps_ns, rng)
    return true, apply_pose_errors(true, shift, turn), poses.timestamps_ns


def scenario_pose_errors(
    sc: Scenario, timestamps_ns: np.ndarray, rng: np.random.Generator | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The scenario's tracking error per radar pose: (translation float64 (M, 3) metres, rotation
    vector float64 (M, 3) radians; zeros but for "hand"), :func:`twinfocus.motion.tracking_errors.draw_errors` on
    ``rng`` (default: the scenario's tracking stream)."""
    return draw_errors(
        sc.error_model,
        timestamps_ns,
        sc.error_sigma_m,
        scenario_stream(sc, TRACKING_STREAM) if rng is None else rng,
        sc.correlation_time_s,
        np.radians(sc.rotation_sigma_deg),
    )


def scenario_tracked_poses(sc: Scenario, frame_period_s: float = 0.1, t0_ns: int = 0) -> tuple[Poses, Poses]:
    """(true poses, tracked poses), one per radar frame: the tracked pose is the rigid pose whose
    phase centres (:func:`twinfocus.motion.trajectory.phase_centres`) are :func:`scenario_positions`'
    tracked ones, what a tracker reports: the translation error, and the rotation error turning
    the orientation about the array's channel centre.

    :func:`twinfocus.motion.tracking_errors.apply_pose_errors` turns the channels to first order (r x arm); this
    pose turns them exactly, so its phase centres differ from :func:`scenario_positions`' by
    |r|^2 |arm| / 2 at most: 0.4 um for the hand's 0.15 degrees on the 83 mm array, 1e-3 rad of
    phase at 77 GHz. Without a rotation error the two are the same numbers."""
    poses = scenario_poses(sc, frame_period_s, t0_ns)
    shift, turn = scenario_pose_errors(sc, poses.timestamps_ns)
    position = poses.position_m + shift
    quat = poses.quat_xyzw
    if np.any(turn):
        # the turn about the channel centre cbar: centre + R' (offset - cbar) with R' = Q R
        quat = quat_multiply(quat_from_rotvec(turn), poses.quat_xyzw)
        cbar = np.asarray(scenario_array(sc).offsets_m, np.float64).mean(axis=0)
        position = position + np.einsum("mij,j->mi", quat_to_matrix(poses.quat_xyzw) - quat_to_matrix(quat), cbar)
    return poses, Poses(poses.timestamps_ns, position, quat)


def scenario_scene_seed(sc: Scenario) -> int:
    """The seed of the scene's scatterers (speckle, clutter) for this scenario."""
    return int(scenario_stream(sc, SCENE_STREAM).integers(0, 2**31))


def scenario_scatterers(
    sc: Scenario, reference_only: bool = False, with_clutter: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Scatterers (P, 3) metres and complex amplitudes (P,) of the whole scene, or of the reference
    alone moved by the template placement error (the same scatterers: streams are keyed by object),
    in the scene's room clutter with ``with_clutter``."""
    scene = sc.scene()
    if reference_only:
        scene = scene.select("reference", occluders=False, clutter=with_clutter)
        ref = scene.objects[0]
        scene.objects[0] = replace(ref, centre_m=np.asarray(ref.centre_m) + np.asarray(sc.template_offset_m, float))
    spacing = sc.spacing_m or scatterer_spacing_m(sc.distance_m)
    return scene.scatterers(spacing, scenario_scene_seed(sc), speckle=sc.speckle)


def simulator_options(sc: Scenario) -> dict:
    """Keywords of :func:`twinfocus.simulation.if_simulator.simulate_if` the scenario sets."""
    return {} if sc.range_step_m is None else {"range_step_m": sc.range_step_m}


def scenario_noise_power(n_positions: int, samples_at) -> float:
    """Mean clean-signal power the scan's SNR refers to: over every :data:`NOISE_POWER_STRIDE`-th
    of the ``n_positions`` radar positions. samples_at : ``indices -> complex IF samples``
    (len(indices), K, N) of those positions."""
    x = np.asarray(samples_at(np.arange(0, int(n_positions), NOISE_POWER_STRIDE)))
    return float(np.mean(np.abs(x.astype(np.complex128)) ** 2))


def template_scan(
    sc: Scenario, chirp: Chirp | None = None, with_clutter: bool = False, array_errors: ArrayErrors | None = None
) -> Scan:
    """The reference alone on the motion stage's raster (exact positions): the physical twin's
    capture; ``with_clutter``: in the scene's cluttered room (the evaluation's swapped rooms);
    ``array_errors``: through that imperfect array (:func:`simulate_scenario`)."""
    chirp = chirp or Chirp()
    stage = phase_centres(paper_raster(sc.n_columns, sc.n_rows), scenario_array(sc))
    pts, amps = scenario_scatterers(sc, reference_only=True, with_clutter=with_clutter)
    data = simulate_if(pts, amps, stage, chirp, **simulator_options(sc), **_pattern(array_errors))
    if sc.snr_db is not None:
        data = add_thermal_noise(data, sc.snr_db, scenario_stream(sc, TEMPLATE_NOISE_STREAM))
    return Scan(_through(data, chirp, array_errors, sc), stage, chirp, positions_true=stage)


def simulate_scenario(
    sc: Scenario, chirp: Chirp | None = None, progress=None, array_errors: ArrayErrors | None = None
) -> tuple[Scan, Scan]:
    """Simulate the handheld scan of the whole scene and the reference's motion-stage scan.

    Returns (scan, template_scan). ``scan.positions`` are the tracked (erroneous) positions,
    ``scan.positions_true`` the truth; the template scan's positions are exact. ``array_errors``
    (:mod:`twinfocus.radar.array_errors`; None: the perfect array): both scans through that imperfect
    array, the beam pattern on every scatterer, the channel errors, leakage, DC offset and I/Q
    imbalance on the channels (the same draws of scene, tracking and noise as the perfect array).
    """
    chirp = chirp or Chirp()
    true, tracked, stamps = scenario_positions(sc)
    pts, amps = scenario_scatterers(sc)
    data = simulate_if(pts, amps, true, chirp, progress=progress, **simulator_options(sc), **_pattern(array_errors))
    if sc.snr_db is not None:
        power = scenario_noise_power(data.shape[0], lambda idx: data[idx])
        data = add_thermal_noise(data, sc.snr_db, scenario_stream(sc, RADAR_NOISE_STREAM), signal_power=power)
    scan = Scan(_through(data, chirp, array_errors, sc), tracked, chirp, positions_true=true, timestamps_ns=stamps)
    return scan, template_scan(sc, chirp, array_errors=array_errors)


def _pattern(array_errors: ArrayErrors | None) -> dict:
    return {"pattern_exponent": array_errors.pattern_exponent} if array_errors and array_errors.pattern_exponent else {}


def _through(data: np.ndarray, chirp: Chirp, array_errors: ArrayErrors | None, sc: Scenario) -> np.ndarray:
    if array_errors is None:
        return data
    return apply_array_errors_to_channels(data, chirp, array_errors, mmwcas_virtual_array(), sc.distance_m)


def scenario_grids(sc: Scenario, size: int = PAPER_IMAGE_SIZE) -> tuple[ImageGrid, ImageGrid]:
    return ImageGrid.from_roi(sc.reference_roi(), size), ImageGrid.from_roi(sc.target_roi(), size)
