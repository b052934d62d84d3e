"""Autofocus solver node: ``sar/measurement`` + ``twin/template`` -> ``autofocus/result`` and images.

As measurements of a scan arrive, the solver back-projects each onto the reference and the
target regions: one row B_m of the sub-image basis per radar position
(:func:`twinfocus.imaging.backprojection.numba_backend.subimage_basis`, rows are independent), computed in batches of
whatever has arrived while the previous batch ran, and, when the estimator registers a physical
twin's template, the registration's scores of those rows
(:class:`twinfocus.focus.template_match.MatchScores`). So when the scan's ``last`` measurement
arrives, the back-projection is already done and only the optimiser and the metrics remain
(:meth:`twinfocus.focus.plan.FocusPlan.focus_bases`, the steps ``twinfocus focus`` runs after its
back-projections: ``twin``, or the baselines ``sharpness`` / ``none``). A hand-held sweep's drift +
tilt fit runs while the sweep arrives too: the plan's ladder climbed on the rows so far in a
worker thread, each drift fit warm-started from the one before
(:class:`twinfocus.focus.ladder.DriftStarts`), so after the last measurement the fit only refines
from the latest (its held-out fits, which decide whether it is kept, run cold as offline); the
result's timings say ``space_variant`` (after the last frame) and ``space_variant_streamed``. With
``basis:=after_scan`` it instead keeps the samples and runs :meth:`twinfocus.focus.plan.FocusPlan.focus_scan`
on the assembled scan at the end (the same call as ``twinfocus focus``; the benchmark's
baseline).

A digital twin's template comes with the reference's outline (``TwinTemplate.support``); the
solver resamples it with the template and hands it to the focusing steps, so ``estimator: auto``
takes the outline estimator as ``twinfocus focus --digital-twin`` does.

Outputs per scan: :class:`msgs.AutofocusResult` (phase, loss curve, metrics, timings, the
estimator that ran) and
:class:`msgs.Image` on ``image/focused`` named ``target``, ``target_uncorrected``,
``reference``, ``reference_uncorrected``; with ``out_dir`` also ``twinfocus focus``'s files in
``out_dir/<scan_id>/`` (:func:`twinfocus.focus.output_files.write_outputs`); a scan that ended without its
last measurement (its source went quiet, the graph was stopped) goes to
``out_dir/<scan_id>.incomplete/`` with ``complete: false`` and ``incomplete_reason`` in its metrics,
so it never replaces a whole scan's result. Metrics against the truth
are computed when the measurements carry ``positions_true_m`` (simulation). A scan whose
measurements report capture gaps (a DCA1000 stream's lost and zero-filled frames, missing bytes)
has them in its metrics as ``capture``, as ``twinfocus focus`` has a converted capture's.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from msgs import AutofocusResult, Header, Image, SarMeasurement, TwinTemplate, now_ns
from nodes.runtime.bus import query_graph
from nodes.runtime.node import Node, Shutdown, run_node
from nodes.runtime.params import REQUIRED, Param, param_of
from twinfocus.errors import TwinFocusError
from twinfocus.focus.estimators import REFERENCE_FREE_RUNGS
from twinfocus.focus.reference_search import region_from_template_file
from twinfocus.focus.settings import FOCUS_SETTINGS
from twinfocus.imaging.basis import BasisRows
from twinfocus.imaging.depth_search import DEFAULT_HALF_RANGE_M, parse_depth, range_to_search
from twinfocus.imaging.grid import ImageGrid
from twinfocus.io.safe_paths import child_path
from twinfocus.jobs.machine import require_memory
from twinfocus.jobs.progress import remaining_text
from twinfocus.radar.fmcw import Chirp
from twinfocus.radar.scan import Scan
from twinfocus.sensors.capture_to_scan import stream_gaps

if TYPE_CHECKING:  # imported where used: the node starts without the numerics (numba, scipy: 1.0 s
    # against 3.5-4.7 s for `import nodes.solver` at load 25), which a launch's checks import
    from twinfocus.focus.ladder import DriftStarts
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.focus.template_match import MatchScores


#: seconds of focusing work between two progress lines
PROGRESS_EVERY_S = 5.0
#: fewest reference rows a streamed registration step scores at once (see _score_registration)
_REGISTRATION_ROWS = 16
#: a hand-held sweep's drift is fitted while it arrives (:meth:`Solver._stream_drift`) from this
#: many positions on (two knots' spans of the fit's curve), and again, warm-started, whenever
#: this many more have arrived since the fit before began and none is running
DRIFT_STREAM_FIRST = 40
DRIFT_STREAM_EVERY = 20


class _Superseded(Exception):
    """A streamed drift fit stopped: the scan's last measurement came (or the scan ended)."""


@dataclass
class _DriftStream:
    """The drift fits streamed during one scan (:meth:`Solver._stream_drift`): the warm starts
    they leave (``starts``, :class:`twinfocus.focus.ladder.DriftStarts`), the positions the
    latest one began on, and the fits that ran to their end: count, the drift rungs' seconds and
    the whole ladders' seconds (each fit climbs the plan's ladder on the rows so far)."""

    starts: DriftStarts
    rows: int = 0
    fits: int = 0
    fit_s: float = 0.0
    ladder_s: float = 0.0
    start_rows: int = 0  # the positions the fit after the last frame started from (the latest streamed fit's)
    worker: threading.Thread | None = None
    stop: threading.Event = field(default_factory=threading.Event)


@dataclass
class _Scan:
    scan_id: str
    chirp: Chirp
    n_channels: int
    first_wall: float
    pending: list = field(default_factory=list)
    ref_rows: BasisRows = field(default_factory=BasisRows)
    tgt_rows: BasisRows = field(default_factory=BasisRows)
    # the half-array bases (the tilt's), streamed from the first batch when the tilt may be fitted
    half: np.ndarray | None = None  # bool (K,): the half's channels (twinfocus.focus.space_variant.array_half)
    ref_half_rows: BasisRows = field(default_factory=BasisRows)
    tgt_half_rows: BasisRows = field(default_factory=BasisRows)
    half_handed: bool = False  # the streamed half-array rows went to the fit
    positions: list = field(default_factory=list)
    truth: list | None = field(default_factory=list)
    data: list = field(default_factory=list)  # basis:=after_scan, or the truth images after the result
    basis_time_s: float = 0.0
    last_batch_s: float = 0.0  # back-projection of the latest batch (the last one: after the scan)
    batches: int = 0
    last_wall: float | None = None
    n: int = 0
    seen_wall: float = 0.0  # when its latest measurement arrived
    max_index: int = -1
    expected: int | None = None  # positions of the scan: the index of its `last` measurement + 1
    sensor_stamp_ns: int = 0  # header stamp of its latest measurement (the radar frame's)
    scores: MatchScores | None = None  # the template registration's scores over the rows so far
    scores_template: np.ndarray | None = None  # the template they score (a new template starts them again)
    registration_s: float = 0.0
    gaps_before: tuple[int, int, int] = (0, 0, 0)  # the stream's gap counts when the scan began
    gaps: tuple[int, int, int] = (0, 0, 0)  # the stream's gap counts at its latest measurement
    incomplete: str = ""  # why the scan ended without its last measurement (empty: it did not)
    counted_before: tuple[int, int] = (0, 0)  # radar frames, measurements published for the scans before
    drift: _DriftStream | None = None  # the drift fits streamed while the scan arrives (a hand-held sweep's)


class Solver(Node):
    """Twin-reference autofocus of each scan."""

    NAME = "solver"
    RENAMED_PARAMS = {"tracking_error_m": "tracking_error_mm, in millimetres (0.5e-3 m is 0.5), as twinfocus focus"}
    PARAMS = {
        **Node.PARAMS,
        "reference_roi": Param(
            [],
            "reference region X0 X1 Y0 Y1 Z, metres; empty: the region the template on twin/template was made on",
            type="floats",
        ),
        "target_roi": Param(
            REQUIRED,
            "target region X0 X1 Y0 Y1 [Z | Z0 Z1], metres: with Z focused there; with a range Z0 Z1, or "
            f"without a depth (the reference's +- {DEFAULT_HALF_RANGE_M} m), the depth where its corrected image "
            "is sharpest is searched for (the result's target_depth.depth_m)",
            type="floats",
        ),
        "refine_depth": Param(0.0, "with a typed Z: search Z +- this many metres for the target's depth (0: trust Z)"),
        "volume": Param(
            [],
            "Z0 Z1 DZ, metres: also form the corrected volume over both regions' x/y box, size x size pixels, and "
            "publish its maximum-intensity projection on image/focused as volume_mip (empty: none)",
            type="floats",
        ),
        "method": Param(
            "twin",
            "twin (needs twin/template), a reference-free autofocus (sharpness, entropy, pga) or none",
            choices=("twin",) + REFERENCE_FREE_RUNGS + ("none",),
        ),
        # the settings of `twinfocus focus`, same names and defaults (twinfocus/focus/settings.py)
        **{s.name: param_of(s) for s in FOCUS_SETTINGS},
        "basis": Param(
            "stream",
            "stream: basis built as measurements arrive; after_scan: all at the end",
            choices=("stream", "after_scan"),
        ),
        "truth_metrics": Param(True, "compute SSIM against the truth when measurements carry it"),
        "template_wait_s": Param(30.0, "how long a finished scan waits for a template before it is dropped"),
        "scan_timeout_s": Param(
            10.0,
            "a scan whose measurements stopped this long ago without its last one (an "
            "incomplete log, a stopped radar) is focused with what arrived",
        ),
        "min_positions": Param(2, "an ended scan with fewer positions than this is dropped with a message"),
        "out_dir": Param("", "write twinfocus focus's files to OUT_DIR/<scan_id>/ (empty: do not write)", type="str"),
        "pictures": Param(True, "with out_dir, also write the PNG pictures"),
        "exit_after_scans": Param(0, "end the node after this many focused scans (0: never)"),
        "warm_up": Param(
            True,
            "run the optimiser and back-projection once on a toy problem at start-up, so the "
            "first scan does not pay their one-off set-up (seconds of imports and JIT loading)",
        ),
    }

    def __init__(self, **kw):
        super().__init__(**kw)
        from twinfocus.focus.autofocus import AutofocusConfig  # lazy: scipy.fft (+0.8 s at import)

        p = self.params
        if len(p["reference_roi"]) not in (0, 5):
            raise TwinFocusError(
                f"node {self.name!r}: parameter 'reference_roi' needs 5 numbers X0 X1 Y0 Y1 Z (or none), "
                f"got {p['reference_roi']}"
            )
        if len(p["target_roi"]) not in (4, 5, 6):
            raise TwinFocusError(
                f"node {self.name!r}: parameter 'target_roi' needs X0 X1 Y0 Y1 and optionally Z or Z0 Z1, "
                f"got {p['target_roi']}"
            )
        if p["volume"] and len(p["volume"]) != 3:
            raise TwinFocusError(f"node {self.name!r}: parameter 'volume' needs Z0 Z1 DZ, got {p['volume']}")
        # None until a template brings its region when none is typed
        self.ref_grid = ImageGrid.from_roi(p["reference_roi"], p["size"]) if p["reference_roi"] else None
        self.target_box = tuple(float(v) for v in p["target_roi"][:4])
        ImageGrid.from_roi((*self.target_box, 1.0), 2)  # checks the box
        depth = p["target_roi"][4:]
        self.typed_depth: float | tuple[float, float] | None = (
            parse_depth(f"{depth[0]}:{depth[1]}") if len(depth) == 2 else parse_depth(str(depth[0])) if depth else None
        )
        if not p["refine_depth"] >= 0:
            raise TwinFocusError(
                f"node {self.name!r}: parameter 'refine_depth' must be >= 0 metres, got {p['refine_depth']}"
            )
        # the typed plane, or None when the target's depth is searched for at the scan's end
        self.tgt_grid = (
            ImageGrid.from_roi((*self.target_box, self.typed_depth), p["size"])
            if isinstance(self.typed_depth, float) and not p["refine_depth"]
            else None
        )
        # a region or depth found at the end needs the samples there: the scan is focused whole
        self.whole_scan = p["basis"] == "after_scan" or self.ref_grid is None or self.tgt_grid is None
        self._check_volume_memory()
        self.cfg = AutofocusConfig.from_settings(p)  # the device resolved as twinfocus focus resolves it
        self.tracking_error_m = p["tracking_error_mm"] * 1e-3
        device = self.cfg.device
        self.bp = {"oversample": p["oversample"], "precision": p["precision"]}
        if device != "cpu":
            self.bp.update(backend="torch", device=device)
        from twinfocus.focus.plan import FocusPlan  # lazy: numba, scipy.fft (+2.1 s at import)

        # the focusing policy, made once from the parameters (twinfocus/focus/plan.py)
        self.plan = FocusPlan.from_settings(
            {**p, "device": device}, p["method"], bp_options=self.bp, progress_factory=lambda label: self._progress
        )
        self.template: np.ndarray | None = None
        self.support: np.ndarray | None = None  # the reference's outline on ref_grid (a digital twin's)
        self.twin_info: dict | None = None  # a digital twin's conditioning (on_template)
        self.template_info = ""
        self.scan: _Scan | None = None
        self.waiting: list[_Scan] = []  # finished scans waiting for a template
        self.done = 0
        self.failed = 0  # scans dropped (not focused)
        self.short: list[str] = []  # scans focused without every position: what each lacked
        self._template_msg: TwinTemplate | None = None  # the template in use, as received
        self._radar_frames_before = 0  # radar frames published for the scans before the current one
        self._paired_before = 0  # measurements published (paired) for the scans before the current one
        self._flush_scheduled = False
        self.stream_gaps = (0, 0, 0)  # the latest measurement's capture gap counts (since the stream began)
        self.result_pub = self.create_publisher("autofocus/result")
        self.image_pub = self.create_publisher("image/focused")
        self.create_subscription("sar/measurement", self.on_measurement)
        self.create_subscription("twin/template", self.on_template)
        if p["warm_up"]:
            self.log("warming up the optimiser and the back-projection (one-off, seconds on a busy machine)")
            t = time.perf_counter()
            self._warm_up()
            self.log(f"warmed up in {time.perf_counter() - t:.1f} s; joining the graph")
        self._said_at = self._step_t0 = 0.0  # when the latest progress line went out; the step began

    def on_start(self) -> None:
        self.create_timer(min(1.0, max(0.05, self.params["scan_timeout_s"] / 4)), self._check_stale)

    def _check_stale(self) -> None:
        s = self.scan
        if s is not None and time.monotonic() - s.seen_wall > self.params["scan_timeout_s"]:
            s.incomplete = f"no measurement for {self.params['scan_timeout_s']:g} s and no last one"
            self.log(f"scan {s.scan_id!r}: {s.incomplete} ({s.n} received); focusing what arrived")
            self._end_scan()

    def _volume_grid(self, ref_grid):
        """The volume's grid over both regions' x/y box (``twinfocus focus --volume``'s), or None
        without ``volume``; ``ref_grid`` None: the target's box stands in for the reference's."""
        from twinfocus.imaging.volume import volume_grid  # lazy: numba (+2.1 s at import)

        if not self.params["volume"]:
            return None
        b = self.target_box
        r = ref_grid.roi if ref_grid is not None else (*b, 1.0)
        size = self.params["size"]
        plane = ImageGrid(min(b[0], r[0]), max(b[1], r[1]), min(b[2], r[2]), max(b[3], r[3]), 1.0, size, size)
        return volume_grid(plane, *self.params["volume"])

    def _check_volume_memory(self) -> None:
        """A volume that cannot fit is refused when the node starts, not after a scan."""
        from twinfocus.imaging.volume import volume_cost  # lazy: numba (+2.1 s at import)

        grid = self._volume_grid(self.ref_grid)
        if grid is not None:
            require_memory(
                volume_cost(grid, 1, 1)["memory_bytes"],
                f"node {self.name!r}: volume ({' x '.join(map(str, grid.shape))} voxels)",
                "choose a smaller size or fewer planes",
                None,
            )

    def _plan(self) -> FocusPlan:
        """The focus plan for the template at hand (:meth:`twinfocus.focus.plan.FocusPlan.for_reference`:
        the estimator resolved as ``twinfocus focus`` resolves it)."""
        return self.plan.for_reference(self.template if self.params["method"] == "twin" else None, self.support)

    def _config(self, chirp):
        """The AutofocusConfig for the template at hand: the plan's (:meth:`_plan`)."""
        return self._plan().config

    def _warm_up(self) -> None:
        from twinfocus.focus.autofocus import AutofocusConfig, twin_autofocus  # lazy: scipy.fft (+0.8 s at import)
        from twinfocus.imaging.backprojection.numba_backend import subimage_basis  # lazy: numba (+2.1 s at import)

        rng = np.random.default_rng(0)
        chirp = Chirp(n_samples=8)
        grid = ImageGrid(-0.01, 0.01, -0.01, 0.01, 0.3, 4, 4)
        data = (rng.standard_normal((2, 2, 8)) + 1j * rng.standard_normal((2, 2, 8))).astype(np.complex64)
        pos = np.zeros((2, 2, 3))
        pos[:, 1, 0] = 1e-3
        basis = subimage_basis(data, pos, chirp, grid, **self.bp)
        cfg = AutofocusConfig(**{**self.cfg.to_dict(), "iterations": 2})
        twin_autofocus(basis, rng.random((4, 4)), cfg)
        self._warm_up_drift(basis, pos, grid, chirp.wavelength_m)

    def _warm_up_drift(self, basis: np.ndarray, pos: np.ndarray, grid, wavelength_m: float) -> None:
        """The drift + tilt fit once on the toy problem of :meth:`_warm_up`, when the ladder may
        climb to it: a hand-held scan's first fit then does not pay loading the fit's numba kernels
        after its last frame. basis : complex (2, 4, 4) on ``grid``; pos : (2, K, 3) metres."""
        from twinfocus.focus.plan import climbs_to  # lazy: numba, scipy.fft (+2.1 s at import)

        if self.params["method"] != "twin" or not climbs_to(
            "drift", self.params["model"], self.params["space_variant"]
        ):
            return
        from twinfocus.focus.space_variant import (  # lazy: numba, scipy.sparse (+2.1 s at import)
            DriftFitSettings,
            fit_smooth_drift,
        )

        template = np.asarray(basis.sum(axis=0))
        fit_smooth_drift(
            basis,
            template,
            np.zeros(basis.shape[0]),
            pos.mean(axis=1),
            grid,
            wavelength_m,
            DriftFitSettings(iterations=2, refine_iterations=2),
            half_basis=basis,
            device=self.cfg.device,
        )

    # -- template -----------------------------------------------------------------------------
    def on_template(self, msg: TwinTemplate) -> None:
        from twinfocus.twins.templates import resample_support, resample_template  # lazy: numba (+2.1 s at import)

        if self._same_template(msg):  # the same template again (sent for a node that started later)
            return
        if not self.params["reference_roi"]:
            roi, _ = region_from_template_file(msg.x_m, msg.y_m, msg.z_m)
            self.ref_grid = ImageGrid.from_roi(roi, self.params["size"])
        assert self.ref_grid is not None
        try:
            template = resample_template(msg.image, msg.x_m, msg.y_m, msg.z_m, self.ref_grid, phase_rad=msg.phase_rad)
        except TwinFocusError as exc:
            self.log(f"ignored a {msg.kind} template from {msg.source or '?'}: {exc}")
            return
        support = None
        if msg.support is not None:
            try:
                support = resample_support(msg.support, msg.x_m, msg.y_m, self.ref_grid)
            except TwinFocusError as exc:
                # the template alone still focuses the scans: auto then takes what it takes without an outline
                self.log(f"ignored the outline of the {msg.kind} template from {msg.source or '?'}: {exc}")
                support = None
        self.template, self.support = template, support
        self._template_msg = msg
        # what the confidence report needs of a digital twin's conditioning (metrics.json ``digital_twin``)
        self.twin_info = (
            {"surface": msg.surface, "curved": bool(msg.curved), "curvature_m": float(msg.curvature_m)}
            if msg.kind == "digital" and msg.surface
            else None
        )
        self.template_info = f"{msg.kind} twin from {msg.source or '?'}" + (
            " with its outline" if support is not None else ""
        )
        self.log(f"template received: {self.template_info}")
        for s in list(self.waiting):
            self.waiting.remove(s)
            self._finish(s)

    def _same_template(self, msg: TwinTemplate) -> bool:
        """Whether ``msg`` repeats the template in use, field for field (the sequence number
        aside): the latched topic sends it again when another subscriber starts later, and
        handling it again would only redo the work."""
        import dataclasses

        old = self._template_msg
        if old is None:
            return False
        for f in dataclasses.fields(msg):
            a, b = getattr(old, f.name), getattr(msg, f.name)
            if f.name == "header":
                if (a.stamp_ns, a.frame_id) != (b.stamp_ns, b.frame_id):
                    return False
            elif isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
                if a is None or b is None or not np.array_equal(a, b):
                    return False
            elif a != b:
                return False
        return True

    # -- measurements -------------------------------------------------------------------------
    def on_measurement(self, m: SarMeasurement) -> None:
        chirp = m.chirp()
        s = self.scan
        if s is not None and s.scan_id != m.scan_id:
            s.incomplete = f"scan {m.scan_id!r} began before its last measurement"
            self.log(f"scan {s.scan_id!r} ended without its last measurement ({s.n} received); focusing what arrived")
            self._end_scan()
            s = None
        if s is None:
            s = self.scan = _Scan(m.scan_id, chirp, m.data.shape[0], time.monotonic(), gaps_before=self.stream_gaps)
            s.counted_before = (self._radar_frames_before, self._paired_before)
            s.truth = [] if self.params["truth_metrics"] else None
            self.log(f"scan {m.scan_id!r} started")
        if chirp != s.chirp or m.data.shape[0] != s.n_channels:
            self.log(
                f"dropped measurement {m.index} of scan {m.scan_id!r}: its chirp or channel count differs from the scan's first"
            )
            return
        s.pending.append(m)
        s.n += 1
        s.gaps = self.stream_gaps = (int(m.frames_lost), int(m.frames_zero_filled), int(m.bytes_lost))
        s.seen_wall = time.monotonic()
        s.max_index = max(s.max_index, int(m.index))
        s.sensor_stamp_ns = int(m.header.stamp_ns)
        if m.last:
            s.expected = int(m.index) + 1
        if s.truth is not None and m.positions_true_m is None:
            s.truth = None
        if m.last:
            s.last_wall = time.monotonic()
            if s.drift is not None:  # the streamed fit stops now, not after the last batch's back-projection
                s.drift.stop.set()
            self._flush()
            self._end_scan()
        elif not self._flush_scheduled:
            # Runs after the loop has read what is already queued: one batch per pass.
            self._flush_scheduled = True
            self.call_later(0, self._flush)

    def _flush(self) -> None:
        from twinfocus.imaging.backprojection.numba_backend import subimage_basis  # lazy: numba (+2.1 s at import)

        self._flush_scheduled = False
        s = self.scan
        if s is None or not s.pending:
            return
        batch, s.pending = s.pending, []
        data = np.stack([m.data for m in batch])
        pos = np.stack([m.positions_m for m in batch])
        s.positions.append(pos)
        if s.truth is not None:
            s.truth.append(np.stack([m.positions_true_m for m in batch]))
        if self.whole_scan or s.truth is not None or self.params["space_variant"] != "off" or self.params["volume"]:
            # whole scan: focused at the end; truth: its images are formed only after the
            # result is out, so they neither slow the stream nor delay the image; the
            # space-variant fit: the half-array bases, back-projected only when the fit runs;
            # the volume: formed with the scan's phase once it is known
            s.data.append(data)
        if self.whole_scan:
            return
        assert self.ref_grid is not None and self.tgt_grid is not None
        t = time.perf_counter()
        s.ref_rows.append(subimage_basis(data, pos, s.chirp, self.ref_grid, **self.bp))
        s.tgt_rows.append(subimage_basis(data, pos, s.chirp, self.tgt_grid, **self.bp))
        if self._half_streamed(s, pos):
            assert s.half is not None
            s.ref_half_rows.append(subimage_basis(data[:, s.half], pos[:, s.half], s.chirp, self.ref_grid, **self.bp))
            s.tgt_half_rows.append(subimage_basis(data[:, s.half], pos[:, s.half], s.chirp, self.tgt_grid, **self.bp))
        s.last_batch_s = time.perf_counter() - t
        s.basis_time_s += s.last_batch_s
        s.batches += 1
        self._score_registration(s)
        if not s.last_wall:  # the last measurement's batch: the fit after it runs at once
            self._stream_drift(s)
        self.heartbeat_if_due()

    def _stream_drift(self, s: _Scan) -> None:
        """Starts a drift fit on the rows so far in a worker thread when the plan may fit the
        drift (a template with phase, the space-variant correction not off), none is running and
        ``DRIFT_STREAM_EVERY`` positions came since the latest began (``DRIFT_STREAM_FIRST`` for
        the first): the plan's ladder climbed on the streamed bases, each drift fit warm-started
        from the one before (:data:`twinfocus.focus.ladder.STREAMED_FIT` steps), so that after the
        last frame the fit only refines from there (:data:`twinfocus.focus.ladder.WARM_FIT`) and
        a hand-held scan's image does not wait for a whole fit (bus.json ``live_hand_sweep``). The
        measurements keep being read and back-projected on the node's thread meanwhile (the
        fit's numba pass releases the GIL)."""
        n = s.ref_rows.n
        d = s.drift
        if d is not None and (d.worker is not None and d.worker.is_alive() or n < d.rows + DRIFT_STREAM_EVERY):
            return
        if n < DRIFT_STREAM_FIRST or not self._drift_streams(s):
            return
        from twinfocus.focus.ladder import STREAMED_FIT, DriftStarts  # lazy: numba, scipy.fft (+2.1 s at import)
        from twinfocus.focus.pipeline import Bases, Reference  # lazy: numba, scipy.fft (+2.1 s at import)

        if d is None:
            d = s.drift = _DriftStream(DriftStarts(warm=dict(STREAMED_FIT)))
        assert self.ref_grid is not None and self.tgt_grid is not None
        # views of the rows so far: the rows after them are appended past them (BasisRows)
        halves = (s.ref_half_rows.array()[:n], s.tgt_half_rows.array()[:n]) if s.ref_half_rows.n >= n else None
        bases = Bases(s.ref_rows.array()[:n], s.tgt_rows.array()[:n], np.concatenate(s.positions)[:n], s.chirp,
                      self.ref_grid, self.tgt_grid, half_bases=None if halves is None else lambda: halves,
                      drift_starts=d.starts)  # fmt: skip
        reference = Reference(self.template, self.support, self.twin_info)
        stop = d.stop

        def check(*_args) -> None:  # the fit's progress: stop at its next step once superseded
            if stop.is_set():
                raise _Superseded

        # the space-variant rungs "on": a streamed fit is there for its end state, and its held-out
        # fits (a third of its time) would only judge a part of the aperture the last fit judges whole
        plan = dataclasses.replace(self._plan().varied(space_variant="on"), progress_factory=lambda label: check)
        d.rows = n
        d.worker = threading.Thread(target=self._drift_worker, args=(d, plan, bases, reference), daemon=True)
        d.worker.start()

    def _drift_streams(self, s: _Scan) -> bool:
        """Whether the scan's drift is fitted as it arrives: the plan climbs to the drift (or the
        tilt, whose half-array rows are then streamed) for a template with phase, on the streamed
        bases at their own resolution (not ``--model fast``'s coarser reference)."""
        plan = self.plan
        if self.whole_scan or self.params["method"] != "twin" or self.template is None or plan.model == "fast":
            return False
        if not np.iscomplexobj(self.template) or not (plan.climbs("drift") or plan.climbs("tilt")):
            return False
        return (not plan.needs.half_bases or s.half is not None) and _parallel_kernels_thread_safe()

    def _drift_worker(self, d: _DriftStream, plan, bases, reference) -> None:
        """One streamed fit (on the worker thread): the plan's ladder on the rows so far, its
        drift fits leaving their warm starts in ``d.starts``; an error or a stop leaves the starts
        of the fits that ended (an error is logged in one line: the fit after the scan runs
        whatever it was)."""
        t = time.perf_counter()
        try:
            out = plan.focus_bases(bases, reference)
        except _Superseded:
            return
        except Exception as exc:  # noqa: BLE001 - a partial scan the ladder refuses: the fit after the scan says why
            self.log(f"streamed drift fit on {d.rows} positions stopped: {type(exc).__name__}: {exc}")
            return
        d.fits += 1
        d.ladder_s += time.perf_counter() - t
        d.fit_s += sum(
            e["time_s"] for e in out.metrics["model"]["rungs"] if e["rung"] in ("drift", "tilt") and e["tried"]
        )

    def _stop_drift(self, s: _Scan) -> DriftStarts | None:
        """The streamed drift fit stopped (at its next step) and waited for; the scan's warm
        starts for the fit after its last frame, None when no streamed fit left one."""
        from twinfocus.focus.ladder import WARM_FIT  # lazy: numba, scipy.fft (+2.1 s at import)

        d = s.drift
        if d is None:
            return None
        d.stop.set()
        if d.worker is not None:
            d.worker.join()
        d.start_rows = max((st.rows for st in d.starts.states.values()), default=0)
        if not d.starts.states:
            return None
        # the fit after the last frame records its own end in a copy: the scan's record says what it started from
        return dataclasses.replace(d.starts, states=dict(d.starts.states), warm=dict(WARM_FIT))

    def _half_streamed(self, s: _Scan, pos: np.ndarray) -> bool:
        """Whether this batch's half-array rows are streamed: from the scan's first batch, when the
        ladder may fit the tilt (a template with phase, the space-variant correction not off, a
        --model that climbs to the tilt). Their back-projection is then paid while the scan
        arrives, not after its last frame (1.3 s at 780 positions x 100 x 100 on the 2-core
        machine); a scan whose drift is not fitted paid it for nothing."""
        from twinfocus.focus.space_variant import array_half  # lazy: numba, scipy.sparse (+2.1 s at import)

        if s.batches == 0 and s.half is None:
            tilt_possible = (
                self.params["method"] == "twin"
                and self.template is not None
                and np.iscomplexobj(self.template)
                and self.plan.needs.half_bases
            )
            if tilt_possible:
                try:
                    s.half = array_half(pos)
                except TwinFocusError:  # one channel, or none spread: no tilt to see
                    pass
        return s.half is not None

    def _half_bases(self, s: _Scan, positions: np.ndarray):
        """``focus_bases``'s ``half_bases``: the streamed rows when they cover the scan and its
        channels split as the first batch's did (the whole scan's :func:`array_half`, as
        ``twinfocus focus`` takes it); else back-projected from the samples when the fit asks."""
        from twinfocus.focus.pipeline import half_array_bases  # lazy: numba, scipy.fft (+2.1 s at import)
        from twinfocus.focus.space_variant import array_half  # lazy: numba, scipy.sparse (+2.1 s at import)

        assert self.ref_grid is not None and self.tgt_grid is not None, "the streamed path has both regions"

        if s.half is not None and s.ref_half_rows.n == positions.shape[0]:
            try:
                same = bool(np.array_equal(array_half(positions), s.half))
            except TwinFocusError:
                same = False
            if same:
                s.half_handed = True
                return lambda: (s.ref_half_rows.array(), s.tgt_half_rows.array())
        if not s.data:
            return None
        return half_array_bases(
            lambda: np.concatenate(s.data),
            positions,
            s.chirp,
            self.ref_grid,
            self.tgt_grid,
            self.bp,
            lambda label: self._progress,
        )

    def _score_registration(self, s: _Scan, final: bool = False) -> None:
        """Adds the reference rows not scored yet to the template registration's scores
        (:class:`twinfocus.focus.template_match.MatchScores`), when the estimator registers the
        template: at the scan's end (``final``) they are the whole basis's, and the
        registration's FFTs (0.15-0.7 s at the paper's size on the 2-core VM) are no longer paid
        after the last measurement. Rows are scored _REGISTRATION_ROWS at a time at least until
        the end: one FFT call per radar frame cost 2.5x as much per row (0.57 ms against 0.23).
        A new template starts the scores again from the rows kept."""
        from twinfocus.focus.template_match import MatchScores  # lazy: scipy.fft (+0.8 s at import)

        t = time.perf_counter()
        if s.scores is None or s.scores_template is not self.template:
            s.scores = None
            if self.params["method"] != "twin" or self.template is None:
                return
            try:
                cfg = self._config(s.chirp)
                if cfg.template_registration != "correlation":
                    return
                s.scores = MatchScores(self.template, cfg.registration_max_shift_px)
            except TwinFocusError:  # an unusable template or estimator: the scan's end says why
                return
            s.scores_template = self.template
        rows = s.ref_rows.array()[s.scores.n_positions :]
        if rows.shape[0] >= (1 if final else _REGISTRATION_ROWS):
            s.scores.add(rows)
        s.registration_s += time.perf_counter() - t

    def _end_scan(self) -> None:
        s, self.scan = self.scan, None
        if s is None:
            return
        self._flush()
        if s.drift is not None:  # a scan dropped or waiting for a template: its streamed fit ends here
            s.drift.stop.set()
        self._count_positions(s)
        if s.last_wall is None:  # ended without its last measurement: from the latest that came
            s.last_wall = s.seen_wall or time.monotonic()
        if s.n < max(1, int(self.params["min_positions"])):
            self._drop(s, f"{s.n} position(s) arrived, fewer than min_positions {self.params['min_positions']}")
            return
        if self.params["method"] == "twin" and self.template is None:
            self.log(
                f"scan {s.scan_id!r} complete ({s.n} positions); waiting up to {self.params['template_wait_s']:g} s for a template"
            )
            self.waiting.append(s)
            self.call_later(self.params["template_wait_s"], functools.partial(self._give_up, s))
            return
        self._finish(s)

    def _give_up(self, s: _Scan) -> None:
        if s in self.waiting:
            self.waiting.remove(s)
            self._drop(s, f"no template arrived on twin/template within {self.params['template_wait_s']:g} s")

    def _drop(self, s: _Scan, reason: str) -> None:
        """The scan is not focused: say why in one line and in a result with ``dropped`` set, so
        whoever waits for the scan's result (the visualizer's ``exit_after_results``) ends."""
        self.log(f"dropped scan {s.scan_id!r}: {reason}")
        self.status_message = f"dropped scan {s.scan_id!r}: {reason}"
        self.result_pub.publish(
            AutofocusResult(
                header=Header(stamp_ns=now_ns(), frame_id="scene"),
                scan_id=s.scan_id,
                method=self.params["method"],
                phase_rad=np.zeros(0),
                loss_history=np.zeros(0),
                metrics={"n_positions": float(s.n)},
                dropped=reason,
            )
        )
        self._count_done(failed=True)

    # -- focusing -----------------------------------------------------------------------------
    def _finish(self, s: _Scan) -> None:
        t_start = self._said_at = time.monotonic()
        positions = np.concatenate(s.positions)
        truth = np.concatenate(s.truth) if s.truth else None
        tgt_basis = None
        try:
            if self.whole_scan:
                out = self._focus_whole(Scan(np.concatenate(s.data), positions, s.chirp, positions_true=truth))
            else:
                out, tgt_basis = self._focus_bases(s, positions)
            volume = self._volume(s, positions, out) if self.params["volume"] else None
        except TwinFocusError as exc:
            self._drop(s, f"could not focus it: {exc}")
            return
        stopping = bool(s.incomplete) and self._stop is not None
        if stopping:  # counted now that the graph around the solver has stopped
            s.expected = self._expected_at_stop(s)
        expected = s.expected if s.expected is not None else s.max_index + 1
        out.metrics["n_positions_expected"] = int(max(expected, s.n))
        out.metrics["n_positions_missing"] = int(max(0, expected - s.n))
        out.metrics["complete"] = not s.incomplete
        if s.incomplete:
            out.metrics["incomplete_reason"] = s.incomplete
        if expected > s.n:
            why = "never reached the solver before it stopped" if stopping else "never arrived"
            self.log(
                f"scan {s.scan_id!r}: {expected - s.n} of its {expected} positions {why}; focused the {s.n} that did"
            )
        gaps = _scan_gaps(s.gaps_before, s.gaps)
        if any(gaps):
            out.metrics["capture"] = stream_gaps(*gaps)
        timing = {k: float(v) for k, v in out.timings_s.items()}
        if not self.whole_scan:
            timing["basis_streamed"] = s.basis_time_s
            timing["basis_last_batch"] = s.last_batch_s
            if s.scores is not None:
                timing["registration_streamed"] = s.registration_s
            out.metrics["basis_batches"] = s.batches
        assert s.last_wall is not None, "set by the scan's last measurement"
        timing["last_measurement_to_result"] = time.monotonic() - s.last_wall
        timing["after_last_measurement_work"] = time.monotonic() - t_start
        latency = time.monotonic() - s.last_wall
        pending = tgt_basis is not None and truth is not None
        self._publish(s, out, timing, latency, pending, volume)
        if pending:
            assert tgt_basis is not None and truth is not None
            t = time.perf_counter()
            self._truth_metrics(s, out, tgt_basis, positions, truth)
            timing["truth_metrics_after_result"] = time.perf_counter() - t
            self._publish_result(s, out, timing, latency, False)
            self._log_focused(s, out, timing)
        if self.params["out_dir"]:
            from twinfocus.focus.output_files import write_outputs  # lazy: numba, scipy.fft (+2.1 s at import)

            out.metrics["timings_s"] = timing
            # a scan that did not end never replaces the result of one that did
            name = s.scan_id + (".incomplete" if s.incomplete else "")
            try:  # a scan id comes from the bus: it names a folder only inside out_dir
                folder = child_path(self.params["out_dir"], name, what="scan id")
            except TwinFocusError as exc:
                self.log(f"not written: {exc}")
            else:
                d = write_outputs(folder, out, pictures=self.params["pictures"])
                self.log(f"wrote {d}/")
        if s.incomplete or expected > s.n:
            lack = f"{expected - s.n} of {expected} positions missing" if expected > s.n else f"{s.n} positions focused"
            self.short.append(
                f"scan {s.scan_id!r}: {lack}" + (f", its end never arrived ({s.incomplete})" if s.incomplete else "")
            )
        self._count_done()

    def _focus_whole(self, scan):
        """The plan's focus of the assembled scan (:meth:`twinfocus.focus.plan.FocusPlan.focus_target`),
        as ``twinfocus focus`` runs it: the target's depth searched first when it is not typed."""
        from twinfocus.focus.pipeline import Reference  # lazy: numba, scipy.fft (+2.1 s at import)
        from twinfocus.focus.plan import Target  # lazy: numba, scipy.fft (+2.1 s at import)

        if self.ref_grid is None:
            raise TwinFocusError("no reference region: none typed and no template yet")
        depth_range = range_to_search(self.typed_depth, self.params["refine_depth"] or None, self.ref_grid.z)
        typed = self.typed_depth if isinstance(self.typed_depth, float) else None
        target = Target(self.target_box, typed, depth_range, self.params["size"])
        reference = Reference(self.template, self.support, self.twin_info)
        out, search = self._plan().focus_target(scan, self.ref_grid, reference, target)
        if search is not None:
            assert depth_range is not None
            self.log(f"target depth {search.depth_m:.4f} m (searched {depth_range[0]:.3f} to {depth_range[1]:.3f} m)")
        if not self.params["reference_roi"]:
            out.metrics["reference_search"] = {"source": "template on twin/template", "roi": list(self.ref_grid.roi)}
        return out

    def _volume(self, s: _Scan, positions: np.ndarray, out):
        """The corrected volume (:func:`twinfocus.imaging.volume.corrected_image` with the scan's phase) and
        its grid; its figures in ``out.metrics["volume"]``."""
        from twinfocus.imaging.volume import corrected_image  # lazy: numba (+2.1 s at import)

        grid = self._volume_grid(self.ref_grid)  # the region typed or found, as twinfocus focus takes it
        t = time.perf_counter()
        vol = corrected_image(
            np.concatenate(s.data), positions, s.chirp, grid, out.phase_rad, progress=self._progress, **self.bp
        )
        p = grid.plane
        out.metrics["volume"] = {
            "roi": [p.x0, p.x1, p.y0, p.y1],
            "z_m": [grid.z0, grid.z1],
            "shape": list(grid.shape),
            "seconds": time.perf_counter() - t,
        }
        out.timings_s["volume"] = out.metrics["volume"]["seconds"]
        return vol, grid

    def _progress(self, done: int = 0, total: int = 0, *extra) -> None:
        """The focusing steps' progress: heartbeats, and a line when focusing has gone on for a
        while without one (no silent stretch of more than a few seconds), with what is left of the
        current step at its pace so far."""
        self.heartbeat_if_due()
        now = time.monotonic()
        if done <= 1:
            self._step_t0 = now
        elif now - self._said_at >= PROGRESS_EVERY_S and done < total:
            self._said_at = now
            left = (now - self._step_t0) * (total - done) / done
            self.log(f"focusing: {done} of {total} of the current step, about {remaining_text(left)} left")

    def _focus_bases(self, s: _Scan, positions: np.ndarray):
        """The plan's focus of the streamed bases (:meth:`twinfocus.focus.plan.FocusPlan.focus_bases`,
        what ``twinfocus focus`` runs after its back-projections; tests/test_graph.py checks the
        phase), without the truth: :meth:`_truth_metrics` adds it once the image is out. Returns the
        outputs and the target basis (the oracle-phase image needs it)."""
        from threadpoolctl import threadpool_limits

        from twinfocus.focus.pipeline import (  # lazy: numba, scipy.fft (+2.1 s at import)
            Bases,
            Reference,
            upper_band_basis,
        )

        assert self.ref_grid is not None and self.tgt_grid is not None, "the streamed path has both regions"
        plan = self._plan()
        tgt_basis = s.tgt_rows.array()
        self._score_registration(s, final=True)  # the rows left (all of them if the template came after the scan)
        scores = s.scores.scores() if s.scores is not None else None
        # --model fast: the reference at its resolution, as twinfocus focus forms it (the streamed
        # rows' slice: the same pixels; the registration is scored again on them)
        ref_grid, reference, (ky, kx) = plan.reference_for(
            Reference(self.template, self.support, self.twin_info), positions, self.ref_grid, s.chirp.wavelength_m
        )
        ref_basis = s.ref_rows.array()[:, ::ky, ::kx]
        whole_halves = self._half_bases(s, positions) if plan.needs.half_bases else None
        half_bases = whole_halves
        if (ky, kx) != (1, 1):
            scores = None
            if whole_halves is not None:

                def half_bases():
                    ref_half, tgt_half = whole_halves()
                    return ref_half[:, ::ky, ::kx], tgt_half

        upper_band = None
        if s.data and plan.needs.upper_band:
            samples = lambda: np.concatenate(s.data)  # noqa: E731
            upper_band = upper_band_basis(samples, positions, s.chirp, ref_grid, self.bp, plan.progress_factory)
        starts = self._stop_drift(s) if (ky, kx) == (1, 1) else None
        bases = Bases(ref_basis, tgt_basis, positions, s.chirp, ref_grid, self.tgt_grid, scores, half_bases, upper_band,
                      starts)  # fmt: skip
        t = time.perf_counter()
        # The BLAS work of these steps (SSIM filters, form_image, small fits on 100 x 100 images)
        # is too small to gain from threads, and OpenBLAS's spinning threads fight numba's and the
        # other nodes' for a few cores: one 100 x 100 SSIM took 60 ms instead of 1 ms on the loaded
        # 2-core VM, a second of the latency after a scan (docs/performance.md). Only here: the
        # back-projection keeps the BLAS set-up of `twinfocus focus` (with one BLAS thread for the
        # whole node, the live uncorrected image differed from focus's by 4e-5 of its maximum
        # under load, above tests/test_graph_offline.py's 1e-5).
        with threadpool_limits(1, user_api="blas"):
            out = plan.focus_bases(bases, reference)
        out.timings_s["focus_bases"] = time.perf_counter() - t  # autofocus and the rest of the steps
        out.metrics["model"]["reference_strides"] = [ky, kx]
        if s.half_handed:
            out.metrics["half_array_bases"] = "streamed"
        if s.drift is not None:
            d = s.drift
            out.timings_s["space_variant_streamed"] = d.fit_s
            out.metrics["space_variant_streamed"] = {
                "fits": d.fits,
                "warm_start_positions": d.start_rows,
                "fit_s": round(d.fit_s, 3),
                "ladder_s": round(d.ladder_s, 3),
                "used": starts is not None,
            }
        return out, tgt_basis

    def _truth_metrics(self, s: _Scan, out, tgt_basis: np.ndarray, positions: np.ndarray, truth: np.ndarray) -> None:
        """:func:`twinfocus.focus.pipeline.add_truth_metrics` (what ``focus_bases`` adds when handed the
        truth), on images formed from the kept samples at the true positions, as
        :meth:`twinfocus.focus.plan.FocusPlan.focus_scan` forms them."""
        from twinfocus.focus.pipeline import add_truth_metrics  # lazy: numba, scipy.fft (+2.1 s at import)
        from twinfocus.imaging.backprojection.numba_backend import backproject  # lazy: numba (+2.1 s at import)

        data = np.concatenate(s.data)
        s.data = []
        out.target_truth = backproject(data, truth, s.chirp, self.tgt_grid, progress=self._progress, **self.bp)
        self.heartbeat_if_due()
        out.reference_truth = backproject(data, truth, s.chirp, out.reference_grid, progress=self._progress, **self.bp)
        add_truth_metrics(
            out,
            tgt_basis,
            positions,
            s.chirp,
            out.target_truth,
            out.reference_truth,
            truth,
            self.cfg.threshold_centre,
            self.cfg.threshold_steepness,
        )

    def _publish_result(self, s: _Scan, out, timing: dict, latency: float, pending: bool) -> None:
        numeric = {
            k: float(v)
            for k, v in out.metrics.items()
            if isinstance(v, (int, float, np.floating, np.integer)) and not isinstance(v, bool)
        }
        # the message's metrics are flat: metrics.json's capture entry as capture.frames_lost ...
        numeric.update({f"capture.{k}": float(v) for k, v in out.metrics.get("capture", {}).items()})
        # the depth found for the target (metrics.json target_depth) as target_depth.depth_m, the
        # drift fits streamed during the sweep as space_variant_streamed.fits ...
        numeric.update(
            {
                f"{section}.{k}": float(v)
                for section in ("target_depth", "space_variant_streamed")
                for k, v in out.metrics.get(section, {}).items()
                if isinstance(v, (int, float)) and not isinstance(v, bool)
            }
        )
        self.result_pub.publish(
            AutofocusResult(
                header=Header(stamp_ns=now_ns(), frame_id="scene"),
                scan_id=s.scan_id,
                method=out.method,
                phase_rad=np.asarray(out.phase_rad, np.float64),
                loss_history=np.asarray(out.loss_history, np.float64),
                metrics=numeric,
                timing_s=dict(timing),
                latency_s=latency,
                metrics_pending=pending,
                # still the template the scan was focused with: on_template waits for this callback to end
                estimator=self._plan().estimator_that_ran(out.metrics) if out.method == "twin" else "",
            )
        )

    def _publish(self, s: _Scan, out, timing: dict, latency: float, pending: bool, volume=None) -> None:
        """The images (the volume's maximum-intensity projection at the depth of its brightest
        voxel; the target last: a viewer waiting for it has the rest), then the result."""
        stamp = now_ns()
        images = [
            ("target_uncorrected", out.target_uncorrected, out.target_grid),
            ("reference_uncorrected", out.reference_uncorrected, out.reference_grid),
            ("reference", out.reference, out.reference_grid),
        ]
        if volume is not None:
            from twinfocus.imaging.volume import projections  # lazy: numba (+2.1 s at import)

            vol, vgrid = volume
            mip, _ = projections(vol, vgrid)
            peak_z = float(vgrid.z_m[np.unravel_index(int(np.argmax(np.abs(vol))), vol.shape)[0]])
            images.append(("volume_mip", mip, dataclasses.replace(vgrid.plane, z=peak_z)))
        images.append(("target", out.target, out.target_grid))  # last: a viewer waiting for it has the rest
        for name, img, grid in images:
            self.image_pub.publish(
                Image(
                    header=Header(stamp_ns=stamp, frame_id="scene"),
                    name=name,
                    scan_id=s.scan_id,
                    image=img,
                    x_m=grid.x_m,
                    y_m=grid.y_m,
                    z_m=grid.z,
                )
            )
        self._publish_result(s, out, timing, latency, pending)
        if not pending:
            self._log_focused(s, out, timing)
        self.status_message = f"focused {self.done + 1} scan(s)"

    def _log_focused(self, s: _Scan, out, timing: dict) -> None:
        ssim = out.metrics.get("target_ssim_corrected")
        tag = (
            f", target SSIM {out.metrics.get('target_ssim_uncorrected', float('nan')):.3f} -> {ssim:.3f}"
            if ssim is not None
            else ""
        )
        self.log(
            f"focused scan {s.scan_id!r}: {out.phase_rad.size} positions, {out.method}{tag}, "
            f"{timing['last_measurement_to_result']:.2f} s after its last measurement"
        )

    def _count_done(self, failed: bool = False) -> None:
        self.done += 1
        self.failed += int(failed)
        n = int(self.params["exit_after_scans"])
        if n and self.done >= n:
            if self.failed:
                self.request_shutdown(f"{self.failed} of {self.done} scan(s) dropped: {self.status_message}", 1)
            elif self.short:
                # the work is unfinished: a replay of a cut or damaged log is not a clean run
                self.request_shutdown(
                    f"{len(self.short)} of {self.done} scan(s) focused without every position: {'; '.join(self.short)}",
                    1,
                )
            else:
                self.request_shutdown(f"{self.done} scan(s) done")

    def _count_positions(self, s: _Scan) -> None:
        """At a scan's end: the positions it should have had (``s.expected``; for a scan without
        its last measurement, the radar frames published for it), and those frames counted off
        before the next scan."""
        if s.expected is None:
            s.expected = max(s.max_index + 1, self._radar_frames(s))
        self._radar_frames_before += max(s.expected, s.n)
        self._paired_before += max(s.expected, s.n)

    def _radar_frames(self, s: _Scan) -> int:
        """Radar frames published for the scan so far, by the radar drivers' heartbeats (0 where no
        node publishes radar/frame, as in a replay of measurements): what an unfinished scan should
        have had, had every frame reached the solver."""
        total = sum(st.published.get("radar/frame", 0) for st in self.read_heartbeats().values())
        return max(0, total - self._radar_frames_before)

    def _expected_at_stop(self, s: _Scan, wait_s: float = 3.0) -> int:
        """The positions a scan cut short by the solver's own stop should have had: the
        measurements the other nodes published for it (the synchronizer's pairs), by their
        final heartbeats at the broker (waiting up to ``wait_s`` for them to end: the graph
        stops around the solver, and a publisher that ends later paired more); where a publisher
        sent no final heartbeat (killed, hung) its count may be short, and the radar frames
        published for the scan count too."""
        deadline = time.monotonic() + wait_s
        while True:
            graph = query_graph(self.broker, self.ctx)
            pubs = [g for n, g in graph.items() if n != self.name and (g.get("published") or {}).get("sar/measurement")]
            final = all(g.get("state") in ("stopped", "error") for g in pubs)
            if final or time.monotonic() >= deadline or not all(_alive(int(g.get("pid") or 0)) for g in pubs):
                break
            self.heartbeat_if_due()
            time.sleep(0.1)
        if not graph or not pubs:  # no broker answer, or no publisher heard from: the old count
            return int(s.expected if s.expected is not None else s.max_index + 1)
        radar_before, paired_before = s.counted_before
        paired = sum(int(g["published"]["sar/measurement"]) for g in pubs) - paired_before
        radar = 0
        if not final:
            radar = sum(int((g.get("published") or {}).get("radar/frame", 0)) for g in graph.values()) - radar_before
        return max(s.max_index + 1, s.n, paired, radar)

    def on_shutdown(self) -> None:
        """A graph stopped mid-scan (a node hung, Ctrl-C) still gets the scan's image from what
        arrived, marked incomplete (metrics.json ``complete: false``, ``n_positions_missing``)."""
        s = self.scan
        if s is None or s.n < max(1, int(self.params["min_positions"])) or self.launcher_gone():
            return
        if self.params["method"] == "twin" and self.template is None:
            return
        s.incomplete = f"the graph stopped ({self._stop.reason if self._stop else 'stop'}) before its last measurement"
        self.log(f"scan {s.scan_id!r}: {s.incomplete}; focusing the {s.n} position(s) that arrived")
        try:
            self._flush()
            self._count_positions(s)
            s.truth = None  # the graph is stopping: the image and its own metrics, not the simulation's truth
            self.scan = None
            s.last_wall = s.last_wall or s.seen_wall or time.monotonic()
            self._finish(s)
        except Shutdown:  # the launcher died meanwhile: nothing can be delivered
            pass


def _parallel_kernels_thread_safe() -> bool:
    """Whether numba's parallel kernels may run on two threads at once (the streamed drift fit
    beside the back-projection): omp and tbb yes; workqueue, numba's fallback without either
    library, no (it aborts the process), and then the drift is fitted after the scan alone."""
    import numba

    try:
        return numba.threading_layer() != "workqueue"
    except ValueError:  # no parallel kernel ran yet: the layer the priority list would take
        return numba.config.THREADING_LAYER != "workqueue"


def _alive(pid: int) -> bool:
    """Whether process ``pid`` still exists (a node on this machine; 0: unknown, taken as alive)."""
    import os

    if pid <= 0:
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    return True


def _scan_gaps(before: tuple[int, int, int], now: tuple[int, int, int]) -> tuple[int, int, int]:
    """A scan's capture gaps from the stream's counts (since the stream began) when it began and
    at its latest measurement; counts that went down mean the stream started again: all of them."""
    if any(n < b for n, b in zip(now, before)):
        return now
    lost, zero_filled, nbytes = (n - b for n, b in zip(now, before))
    return lost, zero_filled, nbytes


def main(argv: list[str] | None = None) -> int:
    return run_node(Solver, argv)


if __name__ == "__main__":
    sys.exit(main())
