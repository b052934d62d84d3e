"""The ladder of correction models (twinfocus.focus.ladder): each rung against a brute-force sum or an
injected error, the knob's modes, the ``model`` record and its aliases, the refusals."""

import json

import numpy as np
import pytest

from tests.helpers import ROIS, cli, metrics, simulate
from twinfocus.errors import TwinFocusError
from twinfocus.focus.autofocus import AutofocusConfig
from twinfocus.focus.estimators import TWIN_RUNGS, estimator_settings
from twinfocus.focus.ladder import (
    FAST_FIT,
    Problem,
    complex_match,
    heldout_gain,
    heldout_verdict,
)
from twinfocus.focus.pipeline import Bases, Reference
from twinfocus.focus.plan import FocusPlan, build_rungs, climbs_to
from twinfocus.focus.rungs import RUNGS, ReferenceFree, climb
from twinfocus.imaging.grid import ImageGrid
from twinfocus.radar.fmcw import Chirp

M, N = 40, 16
GRID = ImageGrid(-0.02, 0.02, -0.02, 0.02, 0.3, N, N)


@pytest.fixture(scope="module")
def scene():
    """Per-position sub-images S_m of five scatterers (each position sees each with its own
    phase), the scan's basis B_m = exp(-j phi_m) S_m with an injected phase error phi, and the
    template with phase T = sum_m S_m (a physical twin's image, in place)."""
    rng = np.random.default_rng(4)
    sub = 0.01 * (rng.normal(size=(M, N, N)) + 1j * rng.normal(size=(M, N, N)))
    for i, j in [(4, 4), (4, 11), (8, 8), (11, 5), (12, 12)]:
        sub[:, i, j] += np.exp(1j * rng.uniform(-0.1, 0.1, M))
    phi = rng.uniform(-np.pi, np.pi, M)
    basis = (np.exp(-1j * phi)[:, None, None] * sub).astype(np.complex64)
    pos = np.zeros((M, 2, 3))
    pos[:, 0, 0] = np.linspace(-0.04, 0.04, M)
    pos[:, 1, 0] = pos[:, 0, 0] + 0.002
    return dict(basis=basis, template=sub.sum(axis=0).astype(np.complex64), phi=phi, positions=pos)


def _focus(s, template=None, estimator="correlation", **kw):
    template = s["template"] if template is None else template
    has_phase = np.iscomplexobj(template)
    cfg = AutofocusConfig(**{"iterations": 5, **estimator_settings(estimator, has_phase), **kw.pop("cfg", {})})
    bases = Bases(s["basis"], s["basis"], s["positions"], Chirp(), GRID, GRID)
    return FocusPlan.make(config=cfg, **kw).focus_bases(bases, Reference(template))


def _wrapped_error(phase, truth):
    """rms of the wrapped difference after the best constant, radians."""
    d = np.exp(1j * (phase - truth))
    return float(np.sqrt(np.mean(np.angle(d * np.conj(d.mean() / abs(d.mean()))) ** 2)))


def test_the_phase_rung_is_the_closed_form_and_auto_climbs_no_further_on_a_phase_error(scene):
    s = scene
    out = _focus(s)
    section = out.metrics["model"]
    assert [e["rung"] for e in section["rungs"]] == list(TWIN_RUNGS)
    assert section["kept"] == ["none", "phase"] and section["result"] == "phase" and section["asked"] == "auto"
    # brute force: phi_m = angle sum_p conj(B_m(p)) T(p), the image sum_m exp(j phi_m) B_m
    b = s["basis"].astype(np.complex128)
    want = np.array([np.angle(np.sum(np.conj(b[m]) * s["template"])) for m in range(M)])
    assert np.allclose(np.exp(1j * out.phase_rad), np.exp(1j * want), atol=3e-4)  # complex64 products
    assert np.allclose(out.target, np.einsum("m,mhw->hw", np.exp(1j * want), b), rtol=1e-4, atol=1e-4)
    # and it finds the injected error (up to a constant)
    assert _wrapped_error(out.phase_rad, s["phi"]) < 0.05
    entries = {e["rung"]: e for e in section["rungs"]}
    assert entries["refine"]["why"].startswith("the estimator is closed form") and not entries["refine"]["tried"]
    # registered: nothing misplaced to place, nor to read from the band's halves
    assert entries["placement"]["tried"] and not entries["placement"]["kept"]
    assert "registered" in entries["range_errors"]["why"]
    # the phase leaves nothing unmatched for a drift to take up
    assert entries["tilt"]["why"].startswith("no half-array bases")
    assert entries["drift"]["why"].startswith("not needed")
    phase = entries["phase"]["evidence"]
    assert phase["parameters"] == M
    assert phase["after"]["reference_unmatched"] < 0.01 < phase["before"]["reference_unmatched"]
    # the older entries are aliases of the record
    m = out.metrics
    assert m["phase_ramp"] == entries["placement"]["info"] and m["space_variant"] == entries["drift"]["info"]
    assert m["template_registration"] == entries["phase"]["info"]["registration"]
    assert m["confidence"]["model"] == "phase"
    assert set(out.rung_targets) == {"none", "phase", "placement"}
    assert np.allclose(out.rung_targets["none"], s["basis"].sum(axis=0), atol=1e-5)
    json.dumps(m)  # metrics.json takes all of it


def test_model_none_and_model_phase_are_exactly_those_models(scene):
    s = scene
    none = _focus(s, model="none")
    assert none.metrics["model"]["kept"] == ["none"] and not np.any(none.phase_rad)
    assert np.allclose(none.target, s["basis"].sum(axis=0), atol=1e-5)
    phase = _focus(s, model="phase", estimator="projection", template=np.abs(s["template"]))
    entries = {e["rung"]: e for e in phase.metrics["model"]["rungs"]}
    # the placement is measured but not applied: the estimate goes to the target as it is
    assert entries["placement"]["tried"] and not entries["placement"]["kept"]
    assert phase.metrics["phase_ramp"]["mode"] == "keep"
    assert all(e["why"] == "off" for n, e in entries.items() if n in ("refine", "range_errors"))


def test_fast_stops_at_the_first_trusted_rung(scene):
    """The physical twin's closed form matches the reference within the trust line: fast climbs
    no costly rung above it. An amplitude template with errors over the whole circle: the
    projections' phases have wrapped, below the trust line, so fast runs the optimiser as auto does."""
    s = scene
    fast = _focus(s, model="fast", space_variant="auto")
    f = {e["rung"]: e for e in fast.metrics["model"]["rungs"]}
    assert f["phase"]["kept"] and f["phase"]["evidence"]["after"]["reference_unmatched"] < 0.01
    for rung in ("refine", "drift"):
        assert not f[rung]["tried"] and f[rung]["why"] == "fast: the reference passes the trust line at phase"
    assert f["tilt"]["mode"] == "off"
    np.testing.assert_allclose(fast.target, _focus(s).target)

    amplitude = np.abs(s["template"])
    auto = _focus(s, template=amplitude, estimator="auto")
    fast = _focus(s, template=amplitude, estimator="auto", model="fast")
    a = {e["rung"]: e for e in auto.metrics["model"]["rungs"]}
    f = {e["rung"]: e for e in fast.metrics["model"]["rungs"]}
    check = a["refine"]["info"]["refine_check"]
    assert check["refined"] and a["refine"]["tried"] and auto.metrics["estimator"]["refine_check"] == check
    assert "phases have wrapped" in f["refine"]["below_trust_line"]
    assert f["refine"]["tried"] and f["refine"]["kept"]
    np.testing.assert_allclose(fast.phase_rad, auto.phase_rad)


def test_full_runs_the_optimiser_after_a_closed_form_and_explicit_settings_win(scene):
    s = scene
    full = _focus(s, model="full", space_variant="off", cfg={"iterations": 5})
    entries = {e["rung"]: e for e in full.metrics["model"]["rungs"]}
    assert entries["refine"]["tried"] and entries["refine"]["kept"] and full.loss_history.size == 5
    assert full.metrics["estimator"]["iterations"] == 5
    assert entries["drift"]["why"] == entries["tilt"]["why"] == "off on request"
    assert full.metrics["space_variant"] == {"mode": "off", "used": False, "reason": "off on request"}


def test_heldout_gain_is_the_match_on_the_judged_pixels_and_the_verdict_needs_every_half():
    rng = np.random.default_rng(0)
    template = rng.normal(size=(8, 8)) + 1j * rng.normal(size=(8, 8))
    judged = np.zeros((8, 8), bool)
    judged[::2] = True
    before = template * np.exp(1j * rng.normal(scale=0.5, size=(8, 8)))
    after = template * np.exp(1j * rng.normal(scale=0.1, size=(8, 8)))
    g = heldout_gain(before, after, template, judged)
    # brute force on the judged rows alone: 1 - Re<T, I> / (|I| |T|)
    t = template[::2].ravel()
    want = [1 - np.vdot(t, x[::2].ravel()).real / np.linalg.norm(x[::2]) / np.linalg.norm(t) for x in (before, after)]
    assert g["unmatched_before"] == pytest.approx(want[0]) and g["unmatched_after"] == pytest.approx(want[1])
    assert g["gain"] == pytest.approx(want[0] - want[1]) and g["gain"] > 0
    # the pixels the fit saw do not count: changing them changes nothing
    after[1::2] = 0
    assert heldout_gain(before, after, template, judged)["gain"] == pytest.approx(g["gain"])
    both = heldout_verdict([{"unmatched_before": 0.1, "unmatched_after": 0.05, "gain": 0.05},
                            {"unmatched_before": 0.1, "unmatched_after": 0.07, "gain": 0.03}])  # fmt: skip
    assert both["kept"] and both["gain"] == pytest.approx(0.04) and both["noise"] == pytest.approx(0.01)
    one = heldout_verdict([{"unmatched_before": 0.1, "unmatched_after": 0.0, "gain": 0.1},
                           {"unmatched_before": 0.1, "unmatched_after": 0.11, "gain": -0.01}])  # fmt: skip
    assert not one["kept"] and one["noise"] > one["gain"] > 0


def test_a_drift_fitted_to_noise_is_not_kept(scene):
    """The error is one phase per position and the rest is noise: the drift, fitted all the same
    (``full``), fits some of the reference's noise, which its held-out halves do not share."""
    s = scene
    out = _focus(s, model="full", cfg={"iterations": 5})
    drift = {e["rung"]: e for e in out.metrics["model"]["rungs"]}["drift"]
    assert drift["tried"] and not drift["kept"] and "drift" not in out.metrics["model"]["kept"]
    held = drift["evidence"]["heldout"]
    assert len(held["folds"]) == 2 and not held["kept"] and held["gain"] <= held["noise"]
    assert drift["why"].startswith("fitted but not kept")
    # on the pixels it was fitted to, the drift matches better: that is the noise it took up
    assert drift["info"]["residual_space_variant"] < drift["info"]["residual_scalar"]


@pytest.mark.slow  # 3 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_a_real_drift_is_kept():
    """A hand's drift and rotation on a small simulated scan (2 x 20 positions, 20 x 20 pixels):
    the drift, fitted on half the reference's blocks, matches the other half better; kept, the
    reference is nearer its image on the true positions than with one phase per position."""
    from twinfocus.imaging.backprojection.numba_backend import backproject, subimage_basis
    from twinfocus.imaging.metrics import image_ssim
    from twinfocus.simulation.scenario import Scenario, scenario_grids, simulate_scenario
    from twinfocus.twins.templates import template_from_scan

    sc = Scenario(reference="H", target="S", separation_deg=16.3, snr_db=15, error_model="hand",
                  error_sigma_m=(0.8e-3,) * 3, n_columns=2, n_rows=20, seed=1)  # fmt: skip
    scan, tpl = simulate_scenario(sc)
    rg, tg = scenario_grids(sc, 20)
    template = template_from_scan(tpl, rg, keep_phase=True)
    rb, tb = (subimage_basis(scan.data, scan.positions, scan.chirp, g) for g in (rg, tg))
    cfg = AutofocusConfig(**estimator_settings("correlation", True))
    outs = {model: FocusPlan.make(config=cfg, model=model).focus_bases(
        Bases(rb, tb, scan.positions, scan.chirp, rg, tg),
        Reference(template=template),
    )
            for model in ("phase", "auto", "fast")}  # fmt: skip
    drift = {e["rung"]: e for e in outs["auto"].metrics["model"]["rungs"]}["drift"]
    assert drift["kept"] and outs["auto"].metrics["model"]["result"] == "drift"
    held = drift["evidence"]["heldout"]
    assert all(f["gain"] > 0 for f in held["folds"]) and held["gain"] > held["noise"]
    truth = backproject(scan.data, scan.positions_true, scan.chirp, rg)
    assert complex_match(outs["auto"].reference, truth) > complex_match(outs["phase"].reference, truth)
    assert image_ssim(outs["auto"].reference, truth) > image_ssim(outs["phase"].reference, truth)
    # fast: one phase per position leaves the reference below the trust line, so the drift is
    # climbed as a quick fit (ladder.FAST_FIT) and kept on one held-out half's evidence
    fast = {e["rung"]: e for e in outs["fast"].metrics["model"]["rungs"]}["drift"]
    assert "template" in fast["below_trust_line"] and fast["kept"]
    assert fast["info"]["iterations"] == FAST_FIT["iterations"]
    assert fast["info"]["refine_iterations"] <= FAST_FIT["refine_iterations"] < drift["info"]["refine_iterations"]
    assert len(fast["evidence"]["heldout"]["folds"]) == 1 and fast["info"]["heldout_fit"].startswith("one half")
    assert complex_match(outs["fast"].reference, truth) > complex_match(outs["phase"].reference, truth)


def test_climbs_to_says_which_costly_rungs_a_setting_can_reach():
    """What the CLI (torch's import) and the solver (the half-array bases) ask before the climb:
    fast never reaches the tilt, a rung's name nothing above it, --space-variant wins over
    --model for the drift and the tilt, and a model the twin's ladder refuses reaches nothing."""
    assert climbs_to("drift", "auto") and climbs_to("tilt", "auto") and climbs_to("tilt", "full")
    assert climbs_to("drift", "fast") and not climbs_to("tilt", "fast")
    assert climbs_to("drift", "drift") and not climbs_to("tilt", "drift")
    assert not climbs_to("drift", "phase") and not climbs_to("drift", "none")
    assert not climbs_to("drift", "auto", "off") and not climbs_to("tilt", "full", "off")
    assert climbs_to("tilt", "fast", "on") and climbs_to("drift", "phase", "on")
    assert not climbs_to("drift", "sharpness") and not climbs_to("drift", "everything")


def test_refusals_name_the_problem(scene):
    s = scene
    with pytest.raises(TwinFocusError, match="model must be one of"):
        build_rungs("everything")
    with pytest.raises(TwinFocusError, match="needs a template with phase"):
        _focus(s, template=np.abs(s["template"]), estimator="projection", model="drift")
    with pytest.raises(TwinFocusError, match="need --method"):
        _focus(s, model="sharpness")
    with pytest.raises(TwinFocusError, match="needs a template"):
        build_rungs("drift", method="sharpness")
    with pytest.raises(TwinFocusError, match="--model range_errors: no upper-band basis"):
        _focus(s, template=np.abs(s["template"]), estimator="projection", model="range_errors")


def test_a_new_rung_is_one_class_and_one_registry_line(scene, monkeypatch):
    """A reference-free estimator added to the registry (one class, one line: docs/architecture.md)
    becomes a ladder of its own: none, it, the placement; here the injected error itself, so the
    image is its brute-force sum."""
    s = scene

    class Oracle(ReferenceFree):
        name, adds = "oracle", "the injected phases"

        def estimate(self, problem):
            return s["phi"], {"source": "injected"}, np.zeros(0)

    monkeypatch.setitem(RUNGS, "oracle", Oracle)
    rungs = build_rungs("auto", method="oracle", phase_ramp="keep")
    assert [r.name for r in rungs] == ["none", "oracle", "placement"]
    problem = Problem(s["basis"], s["basis"], s["positions"], Chirp(), GRID, GRID, AutofocusConfig())
    model, section = climb(problem, rungs)
    assert section["kept"] == ["none", "oracle"] and section["rungs"][1]["info"] == {"source": "injected"}
    want = np.einsum("m,mhw->hw", np.exp(1j * s["phi"]), s["basis"].astype(np.complex128))
    assert np.allclose(model.apply(problem, "target"), want, rtol=1e-4, atol=1e-4)


def test_rungs_are_plain_estimators_that_climb_any_number_of_times(scene):
    """Nothing is written on a rung while it is climbed (its settings are its constructor's), so the
    plan's rungs, built once, give the same record and phase on a second climb, and a climb on
    another problem in between changes neither."""
    s = scene
    # 5 optimiser steps on the refine rung: the closed form's settings say 0, which the rung reads
    # as "the default 300" (three climbs of those were 18 s CPU of this test)
    cfg = AutofocusConfig(**{**estimator_settings("correlation", True), "iterations": 5})
    rungs = build_rungs("full", space_variant="off")
    settings = [dict(vars(r)) for r in rungs]

    def problem(basis):
        return Problem(basis, basis, s["positions"], Chirp(), GRID, GRID, cfg, s["template"])

    def record(section):
        return [{k: v for k, v in e.items() if k != "time_s"} for e in section["rungs"]]

    first, section = climb(problem(s["basis"]), rungs)
    other = s["basis"] * np.exp(1j * np.linspace(0, 3, M)).astype(np.complex64)[:, None, None]
    climb(problem(other), rungs)  # another scan's errors in between
    again, section_again = climb(problem(s["basis"]), rungs)
    assert [dict(vars(r)) for r in rungs] == settings
    assert json.dumps(record(section), default=float) == json.dumps(record(section_again), default=float)
    assert np.array_equal(first.phase_rad, again.phase_rad)


@pytest.mark.slow
def test_focus_model_knob_end_to_end(tmp_path):
    d = simulate(tmp_path / "sim", "--columns 2 --rows 24 --seed 5")
    common = ("focus", d / "scan.npz", *ROIS, "--size 32 --quiet --template-scan", d / "tpl.npz")
    assert cli(*common, "--out", tmp_path / "fast", "--model fast --pictures all") == 0
    m = metrics(tmp_path / "fast")
    assert m["model"]["asked"] == "fast"
    rungs = {e["rung"]: e for e in m["model"]["rungs"]}
    # the costly rungs only below the trust line (here 0.015 of the reference unmatched by one
    # phase per position: the drift is fitted), the closed form's estimator no optimiser, no tilt
    for name in ("refine", "drift"):
        assert "below_trust_line" in rungs[name] or rungs[name]["why"].startswith("fast: the reference passes")
    assert rungs["drift"]["tried"] == ("below_trust_line" in rungs["drift"])
    assert not rungs["refine"]["tried"] and rungs["tilt"]["mode"] == "off" and not rungs["tilt"]["tried"]
    assert (tmp_path / "fast" / "model_ladder.png").is_file()
    assert cli(*common, "--out", tmp_path / "none", "--model none") == 0
    m = metrics(tmp_path / "none")
    assert m["model"]["kept"] == ["none"]
    assert m["target_ssim_corrected"] == pytest.approx(m["target_ssim_uncorrected"], abs=1e-6)


def test_the_half_array_bases_are_a_stage_of_their_own_in_the_timings():
    """``timings_s``: the tilt's back-projection of half the channels as ``half_array_bases``, the
    kept drift or tilt rung's time less it as ``space_variant``, the estimate's rungs summed as
    ``autofocus``; a rung not kept gives no ``space_variant``."""
    from twinfocus.focus.ladder import rung_timings

    def section(tilt_kept: bool) -> dict:
        return {"rungs": [
            {"rung": "none", "tried": True, "kept": True, "time_s": 0.01},
            {"rung": "phase", "tried": True, "kept": True, "time_s": 0.2},
            {"rung": "refine", "tried": True, "kept": False, "time_s": 1.5},
            {"rung": "placement", "tried": True, "kept": False, "time_s": 0.05},
            {"rung": "drift", "tried": False, "kept": False, "time_s": 0.0, "info": {"used": False}},
            {"rung": "tilt", "tried": True, "kept": tilt_kept, "time_s": 6.5,
             "info": {"half_array_bases_s": 1.25}},
        ]}  # fmt: skip

    kept = rung_timings(section(True))
    assert kept["half_array_bases"] == 1.25 and abs(kept["space_variant"] - 5.25) < 1e-12
    assert abs(kept["autofocus"] - 1.7) < 1e-12
    dropped = rung_timings(section(False))
    assert dropped["half_array_bases"] == 1.25 and "space_variant" not in dropped


def test_a_grid_of_every_kth_pixel_is_the_slice_of_the_whole_grids_images():
    """``ImageGrid.every``: the same points as the whole grid's ``[::rows, ::columns]``, so the
    sub-image basis formed on it is that slice of the whole one (a brute-force back-projection of
    each); a stride that leaves fewer than 2 pixels, or one that is not a whole number, is refused."""
    from twinfocus.imaging.backprojection.numba_backend import subimage_basis
    from twinfocus.simulation.scenario import Scenario, scenario_grids, simulate_scenario

    sc = Scenario(n_columns=2, n_rows=6, seed=2)
    scan, _ = simulate_scenario(sc)
    grid, _ = scenario_grids(sc, (21, 17))
    for ky, kx in ((2, 2), (3, 1), (1, 4)):
        sub = grid.every(ky, kx)
        assert np.allclose(sub.x_m, grid.x_m[::kx]) and np.allclose(sub.y_m, grid.y_m[::ky]) and sub.z == grid.z
        whole = subimage_basis(scan.data, scan.positions, scan.chirp, grid)
        # float32 carrier phases referred to each grid's own range window: 5e-5 of the peak seen
        np.testing.assert_allclose(subimage_basis(scan.data, scan.positions, scan.chirp, sub), whole[:, ::ky, ::kx],
                                   rtol=0, atol=2e-4 * np.abs(whole).max())  # fmt: skip
    assert grid.every(1, 1) == grid
    with pytest.raises(TwinFocusError, match="leave 1 x 17: too few"):
        grid.every(21, 1)
    with pytest.raises(TwinFocusError, match="positive whole numbers"):
        grid.every(0, 2)
    with pytest.raises(TwinFocusError, match="positive whole numbers"):
        grid.every(1.5, 2)


def test_fast_forms_a_physical_twins_reference_at_its_resolution_and_nothing_else():
    """``fast_reference``: for ``--model fast`` with a template with phase, each axis keeps every
    k-th pixel, k the most pixels that fit in ``FAST_REFERENCE_CELL_SHARE`` of a resolution cell
    lambda R / (2 L), at least ``FAST_REFERENCE_MIN_SIDE`` pixels a side; any other model, an
    amplitude template or an outline (a digital twin's) keeps every pixel."""
    from twinfocus.focus.ladder import FAST_REFERENCE_CELL_SHARE, FAST_REFERENCE_MIN_SIDE, fast_reference

    chirp = Chirp()
    lam = chirp.wavelength_m
    pos = np.zeros((2, 2, 3))  # the aperture: 0.4 m across x, 0.1 m across y, centred under the region
    pos[:, :, 0] = [[-0.2, -0.2], [0.2, 0.2]]
    pos[:, :, 1] = [[-0.05, 0.05], [-0.05, 0.05]]
    grid = ImageGrid(-0.05, 0.05, -0.05, 0.05, 0.6, 100, 100)  # 1.01 mm pixels at R = 0.6 m
    pitch = 0.1 / 99
    cell_x, cell_y = lam * 0.6 / (2 * 0.4), lam * 0.6 / (2 * 0.1)  # 2.9 mm and 11.7 mm
    want_x = int(FAST_REFERENCE_CELL_SHARE * cell_x / pitch)
    assert want_x == 2  # 0.8 x 2.9 mm holds two 1.01 mm pixels
    # across y a cell holds 9 pixels, but every 9th leaves 12 a side: the stride stops at 6 (17 a side)
    assert int(FAST_REFERENCE_CELL_SHARE * cell_y / pitch) == 9 and 99 // 6 + 1 >= FAST_REFERENCE_MIN_SIDE > 99 // 7 + 1
    tpl = (np.arange(100 * 100).reshape(100, 100) * (1 + 1j)).astype(np.complex64)
    g, t, strides = fast_reference("fast", tpl, None, pos, grid, lam)
    assert strides == (6, want_x) and g == grid.every(6, want_x)
    np.testing.assert_array_equal(t, tpl[::6, ::want_x])
    for model, template, support in (("auto", tpl, None), ("full", tpl, None), ("drift", tpl, None),
                                     ("fast", np.abs(tpl), None), ("fast", tpl, np.ones(tpl.shape, bool)),
                                     ("fast", None, None)):  # fmt: skip
        g, t, strides = fast_reference(model, template, support, pos, grid, lam)
        assert strides == (1, 1) and g is grid and t is template
    # a region whose pixels are already a cell apart keeps them all
    coarse = ImageGrid(-0.05, 0.05, -0.05, 0.05, 0.6, 20, 20)
    assert fast_reference("fast", tpl[:20, :20], None, pos, coarse, lam)[2] == (1, 1)


@pytest.mark.slow
def test_fast_on_a_reference_at_its_resolution_focuses_as_on_every_pixel(monkeypatch):
    """``twinfocus focus --model fast`` (``focus_scan``) on a hand's drift with a fine reference
    grid: the reference is formed on every other pixel (its outputs on that grid, the strides in
    the ``model`` record), and the target reaches what fast gives on every pixel, against the image
    on the true positions."""
    import twinfocus.focus.ladder as ladder
    from twinfocus.focus.pipeline import Reference
    from twinfocus.focus.plan import FocusPlan
    from twinfocus.imaging.backprojection.numba_backend import backproject
    from twinfocus.imaging.metrics import image_ssim
    from twinfocus.simulation.scenario import Scenario, scenario_grids, simulate_scenario
    from twinfocus.twins.templates import template_from_scan

    sc = Scenario(reference="H", target="S", separation_deg=16.3, snr_db=15, error_model="hand",
                  error_sigma_m=(0.8e-3,) * 3, n_columns=2, n_rows=24, seed=3)  # fmt: skip
    scan, tpl_scan = simulate_scenario(sc)
    rg, tg = scenario_grids(sc, 40)
    template = template_from_scan(tpl_scan, rg, keep_phase=True)
    truth = backproject(scan.data, scan.positions_true, scan.chirp, tg)
    cfg = AutofocusConfig(**estimator_settings("auto", True, model="fast"))
    strided = FocusPlan.make(config=cfg, model="fast").focus_scan(scan, rg, tg, Reference(template=template))
    ky, kx = strided.metrics["model"]["reference_strides"]
    assert ky > 1 and kx > 1 and strided.reference_grid == rg.every(ky, kx)
    assert strided.reference.shape == strided.reference_grid.shape and strided.target.shape == tg.shape
    monkeypatch.setattr(ladder, "FAST_REFERENCE_CELL_SHARE", 0.0)  # every pixel
    whole = FocusPlan.make(config=cfg, model="fast").focus_scan(scan, rg, tg, Reference(template=template))
    assert whole.metrics["model"]["reference_strides"] == [1, 1] and whole.reference.shape == rg.shape
    assert strided.metrics["model"]["kept"] == whole.metrics["model"]["kept"]
    uncorrected = image_ssim(whole.target_uncorrected, truth)
    a, b = image_ssim(strided.target, truth), image_ssim(whole.target, truth)
    # the strided reference must not focus worse than every pixel (it may focus better: the drift fit
    # on every pixel also skips every other row, docs/performance_field_fits.md)
    assert b > uncorrected + 0.05 and a > b - 0.02, (uncorrected, a, b)
