"""Evaluation (``twinfocus bench paper``): the second metric against scikit-image, the first-order
transfer terms against closed forms and exact phases, the experiment definitions, the report's
aggregation, and the quick benchmark end to end (physical twin beats no correction; files written)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from twinfocus.cli import main as cli_main
from twinfocus.errors import TwinFocusError
from twinfocus.evaluation.aggregate import crossing, method_stats, pareto_front, stops_helping
from twinfocus.evaluation.cases import (
    EvalScenario,
    draw_position_errors,
    phase_transfer_terms,
    transfer_phase,
)
from twinfocus.evaluation.experiments import BASELINE_LETTERS, paper_experiments
from twinfocus.evaluation.features import hog_descriptor, hog_similarity
from twinfocus.evaluation.trade import central_rows
from twinfocus.imaging import metrics
from twinfocus.motion.trajectory import paper_raster, phase_centres
from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array
from twinfocus.simulation.scenario import simulate_scenario

# --- second metric ---------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(100, 100), (32, 32), (37, 53)])
def test_hog_matches_scikit_image(shape):
    hog = pytest.importorskip("skimage.feature").hog
    img = np.random.default_rng(shape[0]).random(shape)
    ref = hog(
        img, orientations=9, pixels_per_cell=(8, 8), cells_per_block=(2, 2), block_norm="L2-Hys", feature_vector=True
    )
    ours = hog_descriptor(img)
    assert ours.shape == ref.shape
    np.testing.assert_allclose(ours, ref, atol=1e-6)


def test_hog_similarity_orders_images():
    yy, xx = np.mgrid[0:64, 0:64]
    truth = ((np.abs(xx - 20) < 3) & (yy > 10) & (yy < 54)).astype(float)  # a vertical stroke
    assert hog_similarity(truth, truth) == pytest.approx(1.0)
    rotated = truth.T  # the same stroke, horizontal: different edge orientations
    blurred = np.fft.ifft2(
        np.fft.fft2(truth) * np.exp(-((np.fft.fftfreq(64)[:, None] ** 2 + np.fft.fftfreq(64)[None] ** 2) * 40))
    ).real
    s_rot, s_blur = hog_similarity(rotated, truth), hog_similarity(blurred, truth)
    assert s_blur > s_rot
    assert 0.0 <= s_rot < 0.9
    with pytest.raises(TwinFocusError):
        hog_descriptor(np.zeros((10, 10)))


# --- first-order transfer terms --------------------------------------------------------------------


def test_transfer_terms_closed_form():
    lam = 3.9e-3
    true = np.zeros((1, 1, 3))
    d = 0.4e-3
    tracked = true + np.array([d, 0.0, 0.0])
    x, z = 0.05, 0.6
    r = np.hypot(x, z)
    out = phase_transfer_terms(true, tracked, np.array([-x, 0, z]), np.array([x, 0, z]), lam)
    # u_ref - u_tgt = (-2x/R, 0, 0): first order = bound = (4 pi / lambda) 2 x / R d
    expect = 4 * np.pi / lam * 2 * x / r * d
    assert out["first_order"] == pytest.approx(expect, rel=1e-12)
    assert out["bound"] == pytest.approx(expect, rel=1e-12)
    # A range-only error on boresight-symmetric points: first order (u_r - u_t) . dp = 0, bound > 0.
    out = phase_transfer_terms(true, true + np.array([0, 0, d]), np.array([-x, 0, z]), np.array([x, 0, z]), lam)
    assert out["first_order"] == pytest.approx(0.0, abs=1e-12)
    assert out["bound"] > 0


def test_first_order_prediction_matches_exact_transfer():
    """Small errors: the measured transfer floor (exact oracle phases) equals the first-order
    prediction and never exceeds the bound."""
    chirp = Chirp()
    true = phase_centres(paper_raster(6, 20), mmwcas_virtual_array())
    err, _ = draw_position_errors(EvalScenario(error_sigma_m=(0.1e-3,) * 3), paper_raster(6, 20).timestamps_ns, 3)
    tracked = true + err[:, None, :]
    ref, tgt = np.array([-0.05, 0.0, 0.6]), np.array([0.06, 0.01, 0.6])
    floor = metrics.phase_error_rms(
        metrics.oracle_phase(true, tracked, ref, chirp), metrics.oracle_phase(true, tracked, tgt, chirp)
    )
    terms = phase_transfer_terms(true, tracked, ref, tgt, chirp.wavelength_m)
    assert floor == pytest.approx(terms["first_order"], rel=0.05)
    assert terms["first_order"] <= terms["bound"]


def test_error_draws_scale_with_sigma_and_ramp_removal_keeps_focus_part():
    stamps = paper_raster(6, 10).timestamps_ns
    a, _ = draw_position_errors(EvalScenario(error_sigma_m=(0.5e-3,) * 3), stamps, 11)
    b, _ = draw_position_errors(EvalScenario(error_sigma_m=(2e-3,) * 3), stamps, 11)
    np.testing.assert_allclose(b, 4 * a)  # common random numbers across a sigma sweep
    v, turn = draw_position_errors(EvalScenario(error_model="vio"), stamps, 1)
    assert v.shape == (60, 3) and np.isfinite(v).all() and not turn.any()
    h, turn = draw_position_errors(EvalScenario(error_model="hand"), stamps, 1)
    assert h.shape == turn.shape == (60, 3) and turn.any()
    # A pure ramp is removed entirely; a ramp on top of a random phase leaves the random part.
    pos = phase_centres(paper_raster(6, 10), mmwcas_virtual_array())
    xy = pos.mean(axis=1)[:, :2]
    ramp = 0.3 + 40.0 * xy[:, 0] - 25.0 * xy[:, 1]
    assert metrics.phase_error_rms(transfer_phase(ramp, pos, "remove"), np.zeros(60)) < 1e-6
    bumps = np.random.default_rng(0).normal(0, 0.5, 60)
    assert (
        metrics.phase_error_rms(transfer_phase(bumps + ramp, pos, "remove"), transfer_phase(bumps, pos, "remove"))
        < 1e-6
    )
    np.testing.assert_array_equal(transfer_phase(bumps + ramp, pos, "keep"), bumps + ramp)
    # 40 rad/m at 0.6 m moves the image by 7 mm: more than a misplaced template, so auto keeps it
    np.testing.assert_array_equal(transfer_phase(bumps + ramp, pos, "auto"), bumps + ramp)


# --- scenes -----------------------------------------------------------------------------------------


def test_the_cluttered_rooms_template_scan_is_the_scenarios_plus_the_room():
    from twinfocus.simulation.scenario import template_scan

    sc = EvalScenario(reference="C", target="X", n_rows=3, n_columns=2, spacing_m=6e-3, snr_db=None, clutter=True)
    _, template = simulate_scenario(sc)
    open_room = template_scan(sc, with_clutter=False)
    np.testing.assert_array_equal(open_room.data, template.data)
    np.testing.assert_array_equal(open_room.positions, template.positions)
    room = template_scan(sc, with_clutter=True)
    assert np.abs(room.data - template.data).max() > 1e-3 * np.abs(template.data).max()


def test_eval_scenario_reference_distance():
    sc = EvalScenario(reference="M", target="K", reference_distance_m=0.76, occluder="paper", height_m=0.1016)
    scene = sc.scene()
    assert scene.object("reference").centre_m[2] == pytest.approx(0.76)
    assert scene.object("target").centre_m[2] == pytest.approx(0.6)
    assert len(scene.occluders) == 1
    plain = EvalScenario(reference="M", target="K").scene()
    assert plain.object("reference").centre_m[2] == pytest.approx(0.6)


def test_central_rows_keeps_the_middle_of_every_column():
    pos = phase_centres(paper_raster(6, 130), mmwcas_virtual_array())
    for n, expect in ((200, 198), (400, 402), (600, 600), (780, 780)):
        idx = central_rows(pos, n)
        assert idx.size == expect
        y = pos[idx, :, 1].mean(axis=1)
        assert np.abs(y).max() <= (expect // 6) * 1e-3 + 1e-9  # rows 2 mm apart, symmetric about 0
        assert (
            np.bincount(
                np.round(pos[idx, 0, 0] * 1e3).astype(int) - np.round(pos[idx, 0, 0] * 1e3).astype(int).min()
            ).max()
            <= expect // 6 + 1
        )


# --- experiment definitions and report aggregation --------------------------------------------------


def test_paper_experiment_definitions():
    exps = {e.name: e for e in paper_experiments()}
    pairs = exps["baseline"].conditions[0].pairs
    assert len(pairs) == 30 and len(set(pairs)) == 30
    for letter in BASELINE_LETTERS:
        assert sum(r == letter for r, _ in pairs) == 5 and sum(t == letter for _, t in pairs) == 5
    sig = [c.x for c in exps["tracking_error"].conditions if c.in_paper]
    assert min(sig) == 0.5 and max(sig) == 2.0
    assert [c.x for c in exps["separation"].conditions if c.in_paper] == [10, 15, 20]
    assert [c.x for c in exps["distance"].conditions] == [40, 60, 80]
    assert {c.x for c in exps["material"].conditions} == {"metal", "wood", "plastic"}
    assert {c.x for c in exps["nlos"].conditions} == {"polyester", "paper", "plastic"}
    assert all(e.draws == 3 for e in paper_experiments(draws=3))
    quick = paper_experiments(quick=True)
    assert [e.name for e in quick] == ["baseline", "tracking_error"]
    with pytest.raises(TwinFocusError, match="unknown experiment"):
        paper_experiments(only=["baseline", "bogus"])
    with pytest.raises(TwinFocusError):
        paper_experiments(draws=0)


def _rec(cond, pair, draw, method, ssim):
    return {"condition": cond, "pair": pair, "draw": draw, "method": method, "ssim": ssim, "hog": 0.5, "status": "ok"}


def test_method_stats_is_the_ratio_of_paired_means():
    rec = [
        _rec("c", "A>B", 0, "none", 0.5),
        _rec("c", "A>B", 1, "none", 0.7),
        _rec("c", "A>B", 0, "physical", 0.8),
        _rec("c", "A>B", 1, "physical", 0.9),
        {**_rec("c", "A>B", 0, "digital", None), "status": "failed: no twin"},
        _rec("c", "A>B", 1, "digital", 0.84),
    ]
    st = method_stats(rec, "c")
    assert st["none"]["mean"] == pytest.approx(0.6)
    assert st["none"]["sd"] == pytest.approx(0.1)  # population sd of 0.5 and 0.7, as every table shows
    assert st["physical"]["improvement_pct"] == pytest.approx((0.85 / 0.6 - 1) * 100)
    assert st["physical"]["gain"] == pytest.approx(0.25)
    # digital: only draw 1 ran, paired with none's draw 1
    assert st["digital"]["failed"] == 1 and st["digital"]["n"] == 1
    assert st["digital"]["improvement_pct"] == pytest.approx((0.84 / 0.7 - 1) * 100)


def test_pareto_front_against_brute_force():
    pts = [(float(t), float(s)) for t, s in np.random.default_rng(5).random((40, 2))]
    front = set(pareto_front(pts))
    for i, (t, s) in enumerate(pts):
        dominated = any((t2 <= t and s2 >= s) and (t2 < t or s2 > s) for j, (t2, s2) in enumerate(pts) if j != i)
        assert (i in front) == (not dominated)


def test_stops_helping_and_crossing():
    rows = [
        {"x": x, "label": str(x), "stats": {"physical": {"gain": g}}}
        for x, g in ((1, 0.2), (2, 0.05), (3, 0.004), (4, -0.1))
    ]
    assert stops_helping(rows, "physical")["x"] == 3
    assert stops_helping(rows, "digital")["x"] is None
    assert crossing([0, 1, 2], [0.2, 0.6, 1.4], 1.0) == pytest.approx(1.5)
    assert crossing([0, 1], [0.1, 0.2], 1.0) is None


# --- the quick benchmark end to end ---------------------------------------------------------------


def test_cli_rejects_bad_arguments_before_any_work(tmp_path, capsys):
    assert cli_main(["bench", "paper", "--quick", "--only", "bogus", "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "unknown experiment" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "r").exists()
    with pytest.raises(SystemExit) as exc:  # refused while the options are read
        cli_main(["bench", "paper", "--quick", "--draws", "0", "--out", str(tmp_path / "r")])
    assert exc.value.code == 2 and "--draws" in capsys.readouterr().err


@pytest.mark.slow
def test_quick_benchmark_end_to_end(tmp_path):
    out = tmp_path / "bench"
    assert cli_main(["bench", "paper", "--quick", "--quiet", "--out", str(out)]) == 0
    for f in (
        "report.md",
        "summary.json",
        "baseline.png",
        "baseline_pairs.png",
        "baseline_examples.png",
        "tracking_error.png",
        "limits_tracking_error.png",
        "pareto.png",
        "raw/baseline.json",
        "raw/tracking_error.json",
        "raw/trade.json",
        "raw/run.json",
    ):
        assert (out / f).is_file() and (out / f).stat().st_size > 0, f
    base = json.loads((out / "raw" / "baseline.json").read_text())["records"]
    ssim = {
        m: np.mean([r["ssim"] for r in base if r["method"] == m and r["status"] == "ok"]) for m in ("none", "physical")
    }
    assert ssim["physical"] > ssim["none"]
    report = (out / "report.md").read_text()
    assert "| physical twin | 0.85 | +41.7 %" in report  # the paper's number beside ours
    assert "Table 1 of the paper" in report and "## Limits" in report
    # a row of more than one sample: mean ± sd of its records
    vals = [r["ssim"] for r in base if r["method"] == "physical" and r["status"] == "ok"]
    row = next(line for line in report.splitlines() if line.startswith("| physical twin |"))
    assert len(vals) > 1 and f"| {np.mean(vals):.3f} ± {np.std(vals):.3f} |" in row
    for png in out.glob("*.png"):
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # A second call keeps finished experiments and rewrites the report.
    lines = []
    from twinfocus.evaluation.runner import run_paper

    md = run_paper(out, quick=True, only=["baseline"], resume=True, log=lines.append)
    assert any("kept from an earlier run" in ln for ln in lines)
    assert md.is_file()
    # The report alone, written elsewhere: its figure links resolve from where it lies.
    elsewhere = tmp_path / "docs" / "results.md"
    assert cli_main(["bench", "paper", "--report-only", "--out", str(out), "--markdown", str(elsewhere)]) == 0
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", elsewhere.read_text())
    assert len(links) >= 5 and all((elsewhere.parent / link).is_file() for link in links)
    assert cli_main(["bench", "paper", "--report-only", "--out", str(tmp_path / "nothing")]) == 2


@pytest.mark.slow  # 5 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_object_regions_frame_each_letter_without_the_other():
    from twinfocus.evaluation.cases import object_roi

    for kw in ({"distance_m": 0.4}, {}, {"separation_deg": 40.0}):
        sc = EvalScenario(reference="K", target="P", **kw)
        scene = sc.scene()
        ref_c, tgt_c = scene.object("reference").corners_m(), scene.object("target").corners_m()
        r, t = object_roi(sc, "reference"), object_roi(sc, "target")
        assert r[0] < ref_c[:, 0].min() and r[1] > ref_c[:, 0].max() and r[1] <= tgt_c[:, 0].min()
        assert t[0] < tgt_c[:, 0].min() and t[1] > tgt_c[:, 0].max() and t[0] >= ref_c[:, 0].max()
        assert r[2] == pytest.approx(ref_c[:, 1].min() - 0.04) and r[4] == pytest.approx(sc.distance_m)


def test_report_adds_the_field_conditions_from_the_benchmarks_figures(tmp_path):
    from twinfocus.evaluation.report import _section_field

    lines: list = []
    _section_field(tmp_path, lines)
    assert lines == []  # nothing there: no section
    hand = {
        "hand": [
            {
                "uncorrected": 0.5,
                "closed_form_auto": 0.8,
                "default": 0.9,
                "reference_true_phase": 0.85,
                "ceiling_target_phase": 0.97,
            },
            {
                "uncorrected": 0.6,
                "closed_form_auto": 0.8,
                "default": 0.92,
                "reference_true_phase": 0.85,
                "ceiling_target_phase": 0.97,
            },
        ]
    }
    (tmp_path / "field_handheld.json").write_text(json.dumps(hand))
    _section_field(tmp_path, lines)
    text = "\n".join(lines)
    assert "Field conditions" in text
    row = next(line for line in lines if line.startswith("| hand"))
    # mean ± population sd of the draws, as every table of the report
    assert "| 2 | 0.550 ± 0.050 |" in row and "0.910 ± 0.010" in row
    # one draw has no spread: the value alone, as in the other tables
    (tmp_path / "field_handheld.json").write_text(json.dumps({"hand": hand["hand"][:1]}))
    lines = []
    _section_field(tmp_path, lines)
    row = next(line for line in lines if line.startswith("| hand"))
    assert "| 1 | 0.500 | 0.800 | 0.900 |" in row and "±" not in row
