"""One evaluation case: a simulated scene, its templates, and the methods run on error draws.

A *scene* (:func:`prepare_scene`) is simulated once: the IF samples on the true positions, the
image of the target formed with the true positions (the truth every metric compares with), the
physical twin (the reference's motion-stage scan, back-projected) and the digital twin (the
scene rendered for the tracking stereo camera, the reference segmented, its point cloud turned
into a simulated template). Each *draw* (:func:`run_draw`) then puts a fresh tracking error on
the positions — the scene's data stay the same, as when the paper injects error draws into one
motion-stage capture — forms the two sub-image bases once and runs every method on them.

Beside the metrics, every draw records the phase errors that explain them (docs/architecture.md section 1):
the oracle phase at the target's and at the reference's centre, the first-order prediction
(4 pi / lambda) (u_ref - u_tgt) . dp of what a perfect reference correction leaves on the target,
and the bound (4 pi / lambda) |u_ref - u_tgt| |dp| on it.
"""

from __future__ import annotations

import hashlib
import time
import zlib
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.evaluation.batched import batchable, paper_estimates
from twinfocus.evaluation.features import hog_similarity
from twinfocus.focus.autofocus import AutofocusConfig, sharpness_autofocus, twin_autofocus
from twinfocus.focus.autofocus import transfer_phase as autofocus_transfer_phase
from twinfocus.focus.estimators import estimator_settings
from twinfocus.imaging import metrics
from twinfocus.imaging.backprojection.numba_backend import backproject, subimage_basis
from twinfocus.imaging.basis import form_image
from twinfocus.imaging.grid import ImageGrid
from twinfocus.motion.tracking_errors import apply_pose_errors, draw_errors
from twinfocus.radar.fmcw import Chirp
from twinfocus.radar.scan import Scan
from twinfocus.scene import Clutter, paper_scene
from twinfocus.simulation.scenario import Scenario, planar_object, simulate_scenario
from twinfocus.simulation.scenario import template_scan as scenario_template_scan
from twinfocus.twins.digital_twin.align import refine_template_shift_by_loss
from twinfocus.twins.digital_twin.camera import StereoCamera
from twinfocus.twins.digital_twin.render import render_scene
from twinfocus.twins.digital_twin.segment import box_from_scene_roi
from twinfocus.twins.digital_twin.template import digital_twin_template
from twinfocus.twins.templates import template_from_scan

METHODS = ("none", "sharpness", "physical", "digital")

#: Twin methods beyond the paper (docs/evaluation.md, "Beyond the paper"): method -> (template,
#: AutofocusConfig overrides, register an amplitude template by the autofocus loss first).
#: "physical" and "digital" are the paper's optimiser (phase ramp removed per EvalSettings); the
#: others are ``twinfocus focus --estimator`` choices (:func:`twinfocus.focus.estimators.estimator_settings`)
#: or those plus one knob.
TWIN_VARIANTS = {
    "physical": ("physical", {}, False),
    "physical-registered": ("physical", estimator_settings("registered", True), False),
    "physical-correlation": ("physical", estimator_settings("correlation", True), False),
    "physical-correlation-refined": ("physical", estimator_settings("correlation-refined", True), False),
    "physical-steep": ("physical", {"loss_steepness": 5.0}, False),
    "digital": ("digital", {}, False),
    "digital-registered": ("digital", {}, True),
    "digital-steep": ("digital", estimator_settings("paper", False), False),
    "digital-projection-only": ("digital", estimator_settings("projection", False), False),
    "digital-projection": ("digital", estimator_settings("projection-refined", False), False),
    "digital-restarts": (
        "digital",
        {**estimator_settings("projection-refined", False), "projection_restarts": 7},
        False,
    ),
    "digital-coarse": ("digital", {**estimator_settings("paper", False), "coarse_iterations": 200}, False),
    "digital-smooth": (
        "digital",
        {**estimator_settings("projection-refined", False), "smoothness_weight": 0.02},
        False,
    ),
}


def needs_reference(method: str) -> bool:
    """Whether ``method`` estimates from the reference region (a twin method)."""
    return method in TWIN_VARIANTS


def needs_digital_twin(method: str) -> bool:
    return method in TWIN_VARIANTS and TWIN_VARIANTS[method][0] == "digital"


#: Margin (metres) around an object's extent for the "object" regions of interest: about what
#: the paper's regions leave around the default letters (a tight 15 mm frame starves the digital
#: twin, docs/evaluation.md).
OBJECT_ROI_MARGIN_M = 0.04


@dataclass
class EvalScenario(Scenario):
    """:class:`~twinfocus.simulation.scenario.Scenario` plus the reference's own distance (the paper's NLoS
    set-up puts the reference at 76 cm and the target at 60 cm) and a denser room.

    clutter_near_m : with ``clutter``, the room's clutter fills a box from this far in front of
        the letters' plane to 60 cm behind it (2,000 weak scatterers of amplitude 0.1, 40 strong
        ones of 0.5) instead of :meth:`~twinfocus.scene.Clutter.room`'s, which starts 5 cm behind
        and so lies outside the range cell of the image plane.
    """

    reference_distance_m: float | None = None
    clutter_near_m: float | None = None

    def scene(self):
        scene = super().scene()
        if self.clutter and self.clutter_near_m is not None:
            d = max(self.distance_m, self.reference_distance_m or 0.0)
            scene.clutter = Clutter(
                np.array([-0.4, -0.3, min(self.distance_m, self.reference_distance_m or 9.9) - self.clutter_near_m]),
                np.array([0.4, 0.3, d + 0.6]),
                n_points=2000,
                amplitude=0.1,
                n_strong=40,
                strong_amplitude=0.5,
            )
        if self.reference_distance_m is not None:
            moved = paper_scene(
                reference=self.reference,
                target=self.target,
                distance_m=self.distance_m,
                separation_deg=self.separation_deg,
                height_m=self.height_m,
                reference_distance_m=self.reference_distance_m,
                reference_material=self.reference_material,
            )
            scene.objects[[o.name for o in scene.objects].index("reference")] = moved.object("reference")
        return scene


@dataclass
class EvalSettings:
    """Sizes and optimiser settings every case of a run shares (defaults: the paper's)."""

    size: int = 100
    iterations: int = 300
    basis_dtype: str = "float16"
    precision: str = "float32"
    n_columns: int = 6
    n_rows: int = 130
    spacing_m: float | None = None
    device: str = "cpu"
    #: the estimate's linear phase ramp before the transfer, as ``twinfocus focus --phase-ramp``
    phase_ramp: str = "auto"

    def autofocus_config(self, **overrides) -> AutofocusConfig:
        kw: dict[str, Any] = dict(
            iterations=self.iterations, basis_dtype=self.basis_dtype, precision=self.precision, device=self.device
        )
        kw.update(overrides)
        return AutofocusConfig(**kw)

    def bp_options(self) -> dict:
        if self.device.startswith("cuda"):
            return {"backend": "torch", "device": self.device, "precision": self.precision}
        return {"precision": self.precision}

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class SceneCase:
    """A simulated scene ready for error draws.

    scan : data on the true positions (``positions_true``); its ``positions`` are not used.
    truth_target : complex64 (H, W) target image formed with the true positions.
    templates : {"physical:<room>": complex64 (H, W) (the motion-stage image, phase kept),
        "digital": float32 (H, W) amplitude or None when the digital twin failed
        (``notes["digital_error"]`` says why)}.
    centres : {"reference", "target", "target_far"}: (3,) scene points (object centres, and the
        target corner farthest from the reference).
    """

    scenario: Scenario
    scan: Scan
    ref_grid: ImageGrid
    tgt_grid: ImageGrid
    truth_target: np.ndarray
    templates: dict
    centres: dict
    timings_s: dict = field(default_factory=dict)
    notes: dict = field(default_factory=dict)


def object_roi(sc: Scenario, name: str, margin_m: float = OBJECT_ROI_MARGIN_M) -> tuple:
    """(X0, X1, Y0, Y1, Z) around object ``name`` ("reference" or "target") of the scenario's
    scene: its extent plus ``margin_m``, on the plane of its centre, but never past the middle of
    the gap between the two objects (the reference lies on -x, the target on +x), so neither
    region takes in the other object."""
    scene = sc.scene()
    ext = {}
    for n in ("reference", "target"):
        c = planar_object(scene, n).corners_m()
        ext[n] = (c[:, :2].min(axis=0), c[:, :2].max(axis=0))
    lo, hi = ext[name][0] - margin_m, ext[name][1] + margin_m
    middle = (ext["reference"][1][0] + ext["target"][0][0]) / 2.0
    if name == "reference":
        hi[0] = min(hi[0], middle)
    else:
        lo[0] = max(lo[0], middle)
    return (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]), float(planar_object(scene, name).centre_m[2]))


def case_grids(sc: Scenario, size: int, roi: str, margin_m: float = OBJECT_ROI_MARGIN_M) -> tuple[ImageGrid, ImageGrid]:
    """Reference and target grids: ``roi="paper"`` the scenario's own regions (the paper's, architecture.md s. 2, for the
    default scene), ``"object"`` each object's extent plus ``margin_m`` (:func:`object_roi`)."""
    if roi == "paper":
        return ImageGrid.from_roi(sc.reference_roi(), size), ImageGrid.from_roi(sc.target_roi(), size)
    if roi == "object":
        return (
            ImageGrid.from_roi(object_roi(sc, "reference", margin_m), size),
            ImageGrid.from_roi(object_roi(sc, "target", margin_m), size),
        )
    raise TwinFocusError(f"roi must be 'paper' or 'object', got {roi!r}")


def digital_twin_points(sc: Scenario, ref_roi, seed: int) -> tuple[np.ndarray, dict]:
    """The digital twin's view of the reference: render the scene for the ZED 2i-like camera
    co-located with the radar, segment the reference inside its region of interest projected into
    the picture, and extract its point cloud (:mod:`twinfocus.twins.digital_twin`).

    Returns (float64 (N, 3) scene-frame points, {stage: seconds}).
    """
    from twinfocus.twins.digital_twin.pipeline import reference_from_stereo  # lazy: open3d (+4.3 s at import)

    cam = StereoCamera.zed2i()
    t = time.perf_counter()
    pictures = render_scene(sc.scene(), cam, seed=seed)
    info = {"render": time.perf_counter() - t}
    twin = reference_from_stereo(pictures.left, pictures.right, cam, box_from_scene_roi(ref_roi, cam))
    info.update(twin.timings_s)
    info["points"] = int(twin.points_m.shape[0])
    return twin.points_m, info


def digital_twin_for(
    sc: Scenario,
    scan_positions: np.ndarray,
    chirp: Chirp,
    ref_grid: ImageGrid,
    seed: int,
    method: str = "psf",
    coherent: bool = True,
    **bp,
) -> tuple[np.ndarray, dict]:
    """The digital twin's template on ``ref_grid``: :func:`digital_twin_points`, then its SAR
    amplitude simulated (:func:`twinfocus.twins.digital_twin.template.digital_twin_template`).

    Returns (float32 (H, W) template, {stage: seconds, "points": N}).
    """

    points, info = digital_twin_points(sc, ref_grid.roi, seed)
    t = time.perf_counter()
    tpl = digital_twin_template(points, scan_positions, chirp, ref_grid, method=method, coherent=coherent, **bp)
    info["template_simulation"] = time.perf_counter() - t
    return tpl, info


def _far_corner(sc: Scenario, reference_centre: np.ndarray) -> np.ndarray:
    c = planar_object(sc.scene(), "target").corners_m()
    return c[int(np.argmax(np.linalg.norm(c[:, :2] - reference_centre[:2], axis=1)))]


def _data_key(scan: Scan) -> str:
    data = np.ascontiguousarray(scan.data).view(np.uint8)
    return hashlib.blake2b(data, digest_size=16).hexdigest()  # type: ignore[arg-type]  # numpy's stubs give arrays __buffer__ only on Python >= 3.12


def prepare_scene(
    sc: Scenario,
    settings: EvalSettings,
    roi: str,
    template_envs=("open",),
    digital: bool = True,
    template_cache: dict | None = None,
    progress=None,
    roi_margin_m: float = OBJECT_ROI_MARGIN_M,
) -> SceneCase:
    """Simulate ``sc`` once and build what every draw on it needs.

    template_envs : which physical templates to build: ``"open"`` (the reference alone on the
        stage) and/or ``"cluttered"`` (on the stage in the scene's cluttered room).
    template_cache : dict shared across scenes; a reference whose motion-stage scan is
        bit-identical to one seen before reuses its physical templates (one twin per reference
        object, amortised over the targets scanned with it, as in the paper); a digital twin is
        reused only by the same scene (its camera sees the target too).
    """
    bp = settings.bp_options()
    timings: dict[str, float] = {}
    t = time.perf_counter()
    scan, template_scan = simulate_scenario(sc, progress=progress)
    assert scan.positions_true is not None  # a simulated scan knows where its positions really were
    timings["simulate"] = time.perf_counter() - t
    ref_grid, tgt_grid = case_grids(sc, settings.size, roi, roi_margin_m)
    t = time.perf_counter()
    truth = backproject(scan.data, scan.positions_true, scan.chirp, tgt_grid, **bp)
    timings["truth_image"] = time.perf_counter() - t

    cache = template_cache if template_cache is not None else {}
    key = (_data_key(template_scan), ref_grid.roi, ref_grid.shape)
    templates: dict = {}
    notes: dict = {}
    for env in template_envs:
        if (key, env) not in cache:
            t = time.perf_counter()
            if env == "open":
                stage = template_scan
            elif env == "cluttered":
                stage = scenario_template_scan(replace(sc, clutter=True), with_clutter=True)
            else:
                raise TwinFocusError(f"template environment must be 'open' or 'cluttered', got {env!r}")
            cache[(key, env)] = template_from_scan(stage, ref_grid, keep_phase=True, **bp)
            timings[f"template_{env}"] = time.perf_counter() - t
        templates[f"physical:{env}"] = cache[(key, env)]
    if digital:
        # The camera sees the whole scene (the target too), so the digital twin is the scene's own:
        # keyed by the scene, a run gives the same twins whichever scenes came before it.
        digital_key = (repr(sc), ref_grid.roi, ref_grid.shape, "digital")
        if digital_key not in cache:
            try:
                tpl, info = digital_twin_for(sc, scan.positions_true, scan.chirp, ref_grid, seed=sc.seed, **bp)
                cache[digital_key] = (tpl, info, None)
            except TwinFocusError as exc:  # a failed twin is a result, not a crash
                cache[digital_key] = (None, {}, str(exc))
        tpl, info, err = cache[digital_key]
        templates["digital"] = tpl
        notes["digital_timings_s"] = info
        if err:
            notes["digital_error"] = err
    ref_centre = np.asarray(planar_object(sc.scene(), "reference").centre_m, float)
    centres = {
        "reference": ref_centre,
        "target": np.asarray(planar_object(sc.scene(), "target").centre_m, float),
        "target_far": _far_corner(sc, ref_centre),
    }
    return SceneCase(sc, scan, ref_grid, tgt_grid, truth, templates, centres, timings, notes)


def draw_position_errors(sc: Scenario, timestamps_ns: np.ndarray, seed) -> tuple[np.ndarray, np.ndarray]:
    """One tracking-error realisation for the scenario's error model and sigma: (translation (M, 3)
    metres, rotation (M, 3) radians), :func:`twinfocus.motion.tracking_errors.draw_errors`.

    The same ``seed`` gives the same underlying normal draws whatever the sigma, so a sweep over
    sigma compares like with like (common random numbers).
    """
    return draw_errors(
        sc.error_model,
        timestamps_ns,
        sc.error_sigma_m,
        np.random.default_rng(seed),
        sc.correlation_time_s,
        np.radians(sc.rotation_sigma_deg),
    )


def draw_seed(*parts) -> int:
    """A stable integer seed from strings and numbers (crc32 of their text)."""
    return zlib.crc32("|".join(str(p) for p in parts).encode())


def phase_transfer_terms(
    true_m: np.ndarray, tracked_m: np.ndarray, ref_point: np.ndarray, tgt_point: np.ndarray, wavelength_m: float
) -> dict:
    """First-order phase-transfer error of docs/architecture.md section 1, r.m.s. over radar positions (rad).

    true_m, tracked_m : (M, K, 3) phase centres. Per position m (channels averaged): dp_m the
    position error, u the unit line of sight to each point. Returns ``first_order``
    = rms (4 pi / lambda) (u_ref - u_tgt) . dp and ``bound`` = rms (4 pi / lambda) |u_ref - u_tgt| |dp|
    (:func:`twinfocus.imaging.metrics.transfer_bound_rad` per unit error, times each position's |dp|).
    """
    p = np.asarray(true_m, float).mean(axis=1)
    dp = np.asarray(tracked_m, float).mean(axis=1) - p
    u_r = ref_point - p
    u_r /= np.linalg.norm(u_r, axis=1, keepdims=True)
    u_t = tgt_point - p
    u_t /= np.linalg.norm(u_t, axis=1, keepdims=True)
    first = 4.0 * np.pi / wavelength_m * np.einsum("mi,mi->m", u_r - u_t, dp)
    bound = metrics.transfer_bound_rad(true_m, ref_point, tgt_point, wavelength_m, 1.0) * np.linalg.norm(dp, axis=1)
    return {"first_order": float(np.sqrt(np.mean(first**2))), "bound": float(np.sqrt(np.mean(bound**2)))}


def transfer_phase(
    phase_rad: np.ndarray, tracked_m: np.ndarray, mode: str = "auto", registered: bool = False, range_m: float = 0.6
) -> np.ndarray:
    """The phase applied to the target, as ``twinfocus focus`` applies it
    (:func:`twinfocus.focus.autofocus.transfer_phase` on the tracked aperture, the reference ``range_m``
    away; the chirp's wavelength)."""
    aperture = np.asarray(tracked_m, float).mean(axis=1)
    return autofocus_transfer_phase(
        phase_rad, aperture[:, :2], range_m - float(aperture[:, 2].mean()), Chirp().wavelength_m, mode, registered
    )[0]


@dataclass
class DrawBases:
    """One draw's sub-image bases (complex64 (M, H, W); ``reference`` None when no twin method
    runs), its oracle phases (M,) and the fields every method's record shares."""

    reference: np.ndarray | None
    target: np.ndarray
    oracle_target: np.ndarray
    oracle_reference: np.ndarray
    shared: dict
    tracked_m: np.ndarray


def draw_shared(
    case: SceneCase, tracked_m: np.ndarray, settings: EvalSettings, need_reference: bool = True
) -> DrawBases:
    """Bases of one error draw and what explains its results (all phases in radians, r.m.s. over
    radar positions after removing the best constant):

    phase_rms_uncorrected : the target's oracle phase (the error to undo);
    transfer_floor_rad : reference oracle vs target oracle: the error a perfect reference
        estimate leaves on the target's centre (``_far``: on its corner farthest from the reference);
    transfer_first_order_rad / transfer_bound_rad : the first-order prediction of it (docs/architecture.md section 1) and the bound;
    ssim_oracle_target / ssim_oracle_transfer : target SSIM with the target's / the reference's
        oracle phase (the ceiling of any per-position correction / of any reference method).
    """
    scan, chirp = case.scan, case.scan.chirp
    bp = settings.bp_options()
    cfg = settings.autofocus_config()
    centre, steep = cfg.threshold_centre, cfg.threshold_steepness
    t = time.perf_counter()
    ref_basis = subimage_basis(scan.data, tracked_m, chirp, case.ref_grid, **bp) if need_reference else None
    tgt_basis = subimage_basis(scan.data, tracked_m, chirp, case.tgt_grid, **bp)
    basis_s = time.perf_counter() - t

    true = scan.positions_true
    assert true is not None  # a simulated scan knows where its positions really were
    oracle_t = metrics.oracle_phase(true, tracked_m, case.centres["target"], chirp)
    oracle_r = metrics.oracle_phase(true, tracked_m, case.centres["reference"], chirp)
    oracle_far = metrics.oracle_phase(true, tracked_m, case.centres["target_far"], chirp)
    lam = chirp.wavelength_m
    centre_terms = phase_transfer_terms(true, tracked_m, case.centres["reference"], case.centres["target"], lam)
    far_terms = phase_transfer_terms(true, tracked_m, case.centres["reference"], case.centres["target_far"], lam)
    shared = {
        "basis_s": basis_s,
        "phase_rms_uncorrected": metrics.phase_error_rms(np.zeros(scan.n_positions), oracle_t),
        "transfer_floor_rad": metrics.phase_error_rms(oracle_r, oracle_t),
        "transfer_floor_far_rad": metrics.phase_error_rms(oracle_r, oracle_far),
        "transfer_first_order_rad": centre_terms["first_order"],
        "transfer_bound_rad": centre_terms["bound"],
        "transfer_first_order_far_rad": far_terms["first_order"],
        "transfer_bound_far_rad": far_terms["bound"],
        "ssim_oracle_target": metrics.image_ssim(form_image(tgt_basis, oracle_t), case.truth_target, centre, steep),
        "ssim_oracle_transfer": metrics.image_ssim(form_image(tgt_basis, oracle_r), case.truth_target, centre, steep),
    }
    return DrawBases(ref_basis, tgt_basis, oracle_t, oracle_r, shared, tracked_m)


def template_key(method: str, template_env: str = "open") -> str:
    """The key of :attr:`SceneCase.templates` that twin method ``method`` estimates from."""
    return f"physical:{template_env}" if TWIN_VARIANTS[method][0] == "physical" else "digital"


def runs_paper_optimiser(method: str, cfg: AutofocusConfig) -> bool:
    """Whether twin method ``method`` under ``cfg`` is the paper's optimiser on its template as it
    is, so that :func:`paper_twin_estimates` can run it beside the others on the same basis."""
    if method not in TWIN_VARIANTS:
        return False
    _, overrides, register_by_loss = TWIN_VARIANTS[method]
    return not overrides and not register_by_loss and batchable(cfg) and cfg.basis_dtype == "float16"


def paper_twin_estimates(case: SceneCase, bases: DrawBases, keys, cfg: AutofocusConfig) -> dict:
    """The paper's optimiser on the reference basis of one draw from every template of ``keys``
    (keys of :attr:`SceneCase.templates`, :func:`template_key`) at once
    (:func:`twinfocus.evaluation.batched.paper_estimates`).

    Returns {key: (float64 (M,) phase radians, seconds: the batch's wall time over its estimates)
    or the TwinFocusError its method reports}; ``evaluate_methods(estimates=...)`` takes it.
    """
    out: dict = {}
    run = []
    for key in dict.fromkeys(keys):
        tpl = case.templates.get(key)
        if tpl is None:
            out[key] = TwinFocusError(case.notes.get("digital_error", f"no {key} template"))
        elif bases.reference is None:
            out[key] = TwinFocusError("the reference basis was not formed for this draw")
        else:
            run.append(key)
    if run:
        assert bases.reference is not None  # checked per key above
        phases, seconds = paper_estimates(bases.reference, [case.templates[k] for k in run], cfg)
        for key, phase in zip(run, phases):
            out[key] = phase if isinstance(phase, TwinFocusError) else (phase, seconds / len(run))
    return out


def estimate_phase(
    method: str, case: SceneCase, bases: DrawBases, cfg: AutofocusConfig, template_env: str = "open"
) -> tuple[np.ndarray, float]:
    """Phase (M,) radians of one method and its optimiser time (s). Raises TwinFocusError when the
    method cannot run (no digital twin)."""
    if method == "none":
        return np.zeros(bases.target.shape[0]), 0.0
    if method == "sharpness":
        res = sharpness_autofocus(bases.target, cfg)
        return res.phase_rad, res.time_s
    if method in TWIN_VARIANTS:
        _, overrides, register_by_loss = TWIN_VARIANTS[method]
        key = template_key(method, template_env)
        tpl = case.templates.get(key)
        if tpl is None:
            raise TwinFocusError(case.notes.get("digital_error", f"no {key} template"))
        if bases.reference is None:
            raise TwinFocusError("the reference basis was not formed for this draw")
        t = time.perf_counter()
        if register_by_loss:
            tpl, _, _ = refine_template_shift_by_loss(bases.reference, np.abs(tpl), cfg)
        res = twin_autofocus(bases.reference, tpl, replace(cfg, **overrides))
        return res.phase_rad, time.perf_counter() - t
    raise TwinFocusError(f"unknown method {method!r}; use one of {', '.join(METHODS)}")


def evaluate_methods(
    case: SceneCase,
    bases: DrawBases,
    methods,
    settings: EvalSettings,
    template_env: str = "open",
    config_overrides: dict | None = None,
    keep_images: bool = False,
    estimates: dict | None = None,
) -> list[dict]:
    """Every method on one draw: one record each with method, status ("ok" or "failed: ..."),
    ssim and hog (target vs truth), phase error r.m.s. against the target's and the reference's
    oracle phases (rad) and autofocus_s; unless ``settings.phase_ramp`` is "keep", also
    ssim_as_estimated (the phase transferred with its ramp, as the source paper does); with
    ``keep_images`` also "image": the target's display image (float32 (H, W), what SSIM is taken on).

    estimates : :func:`paper_twin_estimates` of this draw; a twin method that runs the paper's
        optimiser (:func:`runs_paper_optimiser`) takes its template's entry instead of running."""
    cfg = settings.autofocus_config(**(config_overrides or {}))
    records = []
    for method in methods:
        rec = {"method": method, "status": "ok", "ssim": None, "hog": None, "autofocus_s": 0.0}
        try:
            key = template_key(method, template_env) if method in TWIN_VARIANTS else None
            if estimates is not None and key in estimates and runs_paper_optimiser(method, cfg):
                got = estimates[key]
                if isinstance(got, TwinFocusError):
                    raise got
                phase, rec["autofocus_s"] = got
            else:
                phase, rec["autofocus_s"] = estimate_phase(method, case, bases, cfg, template_env)
        except TwinFocusError as exc:
            rec["status"] = f"failed: {exc}"
            records.append(rec)
            continue
        if method != "none":
            if settings.phase_ramp != "keep":
                # The source paper transfers the phase as estimated: keep its score too.
                rec["ssim_as_estimated"] = metrics.image_ssim(
                    form_image(bases.target, phase), case.truth_target, cfg.threshold_centre, cfg.threshold_steepness
                )
            registered = TWIN_VARIANTS.get(method, (None, {}, False))[1].get("template_registration", "none") != "none"
            phase = transfer_phase(phase, bases.tracked_m, settings.phase_ramp, registered, case.ref_grid.z)
        image = form_image(bases.target, phase)
        rec["ssim"] = metrics.image_ssim(image, case.truth_target, cfg.threshold_centre, cfg.threshold_steepness)
        rec["hog"] = hog_similarity(image, case.truth_target, cfg.threshold_centre, cfg.threshold_steepness)
        rec["phase_rms_vs_target_oracle"] = metrics.phase_error_rms(phase, bases.oracle_target)
        rec["phase_rms_vs_reference_oracle"] = metrics.phase_error_rms(phase, bases.oracle_reference)
        if keep_images:
            rec["image"] = metrics.display_image(image, cfg.threshold_centre, cfg.threshold_steepness).astype(
                np.float32
            )
        records.append(rec)
    return records


def tracked_positions(scan: Scan, error_scenario: Scenario, seed) -> np.ndarray:
    """The scan's true phase centres plus one draw of ``error_scenario``'s tracking error (its
    ``error_model`` and ``error_sigma_m``): (M, K, 3) metres."""
    stamps = (
        scan.timestamps_ns
        if scan.timestamps_ns is not None
        else np.arange(scan.n_positions, dtype=np.int64) * 100_000_000
    )
    assert scan.positions_true is not None  # a simulated scan knows where its positions really were
    return apply_pose_errors(scan.positions_true, *draw_position_errors(error_scenario, stamps, seed))
