"""The ladder of correction models (twinfocus.ladder): each rung against a brute-force sum or an
injected error, the knob's modes, the ``model`` record and its aliases, the refusals."""
import json

import numpy as np
import pytest

from twinfocus.autofocus import AutofocusConfig
from twinfocus.errors import TwinFocusError
from twinfocus.estimators import TWIN_RUNGS, estimator_settings
from twinfocus.grid import ImageGrid
from twinfocus.ladder import (
    REFERENCE_FREE,
    SPACE_VARIANT_MIN_GAIN,
    Problem,
    SmoothDrift,
    build_ladder,
    climb,
)
from twinfocus.pipeline import focus_bases
from twinfocus.radar import Chirp

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
    return focus_bases(s["basis"], s["basis"], s["positions"], Chirp(), GRID, GRID, template=template, config=cfg, **kw)


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


def test_fast_leaves_the_optimiser_out_where_auto_runs_it(scene):
    """An amplitude template and errors over the whole circle: the projections' phases have
    wrapped, so auto's rule runs the optimiser; fast stops at the closed form."""
    s = scene
    amplitude = np.abs(s["template"])
    auto = _focus(s, template=amplitude, estimator="auto")
    fast = _focus(s, template=amplitude, estimator="auto", model="fast")
    a = {e["rung"]: e for e in auto.metrics["model"]["rungs"]}
    f = {e["rung"]: e for e in fast.metrics["model"]["rungs"]}
    check = a["refine"]["info"]["refine_check"]
    assert a["refine"]["tried"] == check["refined"]
    assert auto.metrics["estimator"]["refine_check"] == check
    assert not f["refine"]["tried"] and f["refine"]["mode"] == "off"
    assert fast.metrics["estimator"]["iterations"] == 0
    # what fast kept is the closed form auto started from
    assert np.allclose(fast.rung_targets["phase"], auto.rung_targets["phase"])


def test_full_runs_the_optimiser_after_a_closed_form_and_explicit_settings_win(scene):
    s = scene
    full = _focus(s, model="full", space_variant="off", cfg={"iterations": 5})
    entries = {e["rung"]: e for e in full.metrics["model"]["rungs"]}
    assert entries["refine"]["tried"] and entries["refine"]["kept"] and full.loss_history.size == 5
    assert full.metrics["estimator"]["iterations"] == 5
    assert entries["drift"]["why"] == entries["tilt"]["why"] == "off on request"
    assert full.metrics["space_variant"] == {"mode": "off", "used": False, "reason": "off on request"}


def test_the_drift_is_kept_only_when_it_takes_away_enough_of_the_unmatched_reference():
    rung = SmoothDrift("auto")
    for after, kept in ((0.018, False), (0.02 * (1 - SPACE_VARIANT_MIN_GAIN) - 1e-4, True)):
        rung.info_.update(residual_scalar=0.02, residual_space_variant=after)
        assert rung.keep(None, None, None)[0] is kept  # type: ignore[arg-type]
    forced = SmoothDrift("on")
    forced.info_.update(residual_scalar=0.02, residual_space_variant=0.019)
    assert forced.keep(None, None, None) == (True, "on request")  # type: ignore[arg-type]


def test_refusals_name_the_problem(scene):
    s = scene
    with pytest.raises(TwinFocusError, match="model must be one of"):
        build_ladder("everything")
    with pytest.raises(TwinFocusError, match="needs a template with phase"):
        _focus(s, template=np.abs(s["template"]), estimator="projection", model="drift")
    with pytest.raises(TwinFocusError, match="need --method"):
        _focus(s, model="sharpness")
    with pytest.raises(TwinFocusError, match="needs a template"):
        build_ladder("drift", method="sharpness")
    with pytest.raises(TwinFocusError, match="--model range_errors: no upper-band basis"):
        _focus(s, template=np.abs(s["template"]), estimator="projection", model="range_errors")


def test_a_reference_free_rung_plugs_in_by_name(scene, monkeypatch):
    """A reference-free estimator added to the table becomes a ladder of its own: none, it, the
    placement; here the injected error itself, so the image is its brute-force sum."""
    s = scene

    def oracle(basis, config, progress, problem):
        return s["phi"], {"source": "injected"}, np.zeros(0)

    monkeypatch.setitem(REFERENCE_FREE, "oracle", (oracle, "the injected phases"))
    rungs = build_ladder("auto", method="oracle", phase_ramp="keep")
    assert [r.name for r in rungs] == ["none", "oracle", "placement"]
    problem = Problem(s["basis"], s["basis"], s["positions"], Chirp(), GRID, GRID, AutofocusConfig())
    model, section = climb(problem, rungs)
    assert section["kept"] == ["none", "oracle"] and section["rungs"][1]["info"] == {"source": "injected"}
    want = np.einsum("m,mhw->hw", np.exp(1j * s["phi"]), s["basis"].astype(np.complex128))
    assert np.allclose(model.apply(problem, "target"), want, rtol=1e-4, atol=1e-4)


@pytest.mark.slow
def test_focus_model_knob_end_to_end(tmp_path):
    from twinfocus.cli import main

    d = tmp_path / "sim"
    assert main(["simulate", "--out", str(d / "scan.npz"), "--template-out", str(d / "tpl.npz"), "--columns", "2",
                 "--rows", "24", "--quiet", "--seed", "5"]) == 0
    common = ["focus", str(d / "scan.npz"), "--reference-roi", "-0.15", "0.0", "-0.11", "0.12", "0.6",
              "--target-roi", "0.02", "0.13", "-0.11", "0.12", "0.6", "--size", "32", "--quiet",
              "--template-scan", str(d / "tpl.npz")]
    assert main([*common, "--out", str(tmp_path / "fast"), "--model", "fast", "--pictures", "all"]) == 0
    m = json.loads((tmp_path / "fast" / "metrics.json").read_text())
    assert m["model"]["asked"] == "fast"
    assert not any(e["tried"] for e in m["model"]["rungs"] if e["rung"] in ("refine", "drift", "tilt"))
    assert (tmp_path / "fast" / "model_ladder.png").is_file()
    assert main([*common, "--out", str(tmp_path / "none"), "--model", "none"]) == 0
    m = json.loads((tmp_path / "none" / "metrics.json").read_text())
    assert m["model"]["kept"] == ["none"]
    assert m["target_ssim_corrected"] == pytest.approx(m["target_ssim_uncorrected"], abs=1e-6)
