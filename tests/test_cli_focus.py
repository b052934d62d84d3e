"""The offline commands end to end on a small scene, and their answers to bad input."""

import json

import numpy as np
import pytest

from tests.helpers import REF_ROI, ROIS, TGT_ROI, cli, metrics
from twinfocus.cli import main
from twinfocus.errors import TwinFocusError
from twinfocus.io.arrays import save_npz_atomic
from twinfocus.radar.scan import Scan


def _focus(scan, out, *extra):
    return cli("focus", scan, *ROIS, "--size 48 --iterations 150 --out", out, "--quiet", *extra)


@pytest.mark.slow
def test_simulate_then_focus_with_template_scan(small_scene, tmp_path):
    out = tmp_path / "focus"
    assert _focus(small_scene / "scan.npz", out, "--template-scan", str(small_scene / "tpl.npz")) == 0
    for name in ("target.npy", "target_uncorrected.npy", "reference.npy", "phase.npy", "metrics.json", "summary.png"):
        assert (out / name).is_file(), name
    # by default only the summary picture (the others cost matplotlib's second or two)
    assert sorted(p.name for p in out.glob("*.png")) == ["summary.png"]
    assert (
        _focus(
            small_scene / "scan.npz",
            tmp_path / "all",
            "--template-scan",
            str(small_scene / "tpl.npz"),
            "--pictures",
            "all",
        )
        == 0
    )
    for name in ("summary.png", "target.png", "template.png", "loss.png", "phase.png"):
        assert (tmp_path / "all" / name).is_file(), name
    target = np.load(out / "target.npy")
    assert target.dtype == np.complex64 and target.shape == (48, 48)
    assert np.load(out / "phase.npy").shape == (120,)
    m = metrics(out)
    assert m["target_ssim_corrected"] > m["target_ssim_uncorrected"] + 0.03
    assert m["reference_ssim_vs_template_corrected"] > m["reference_ssim_vs_template_uncorrected"]


@pytest.mark.slow
def test_estimators_from_a_template_scan(small_scene, tmp_path, capsys):
    """auto = registration + closed form with a physical twin (its phase is known); every
    estimator improves the target; one that needs a phase refuses an amplitude template."""
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.twins.templates import save_template, template_from_scan

    tpl = ["--template-scan", str(small_scene / "tpl.npz")]
    ssim = {}
    for est in ("auto", "paper", "correlation-refined"):
        assert _focus(small_scene / "scan.npz", tmp_path / est, *tpl, "--estimator", est) == 0
        m = metrics(tmp_path / est)
        ssim[est] = m["target_ssim_corrected"]
        assert ssim[est] > m["target_ssim_uncorrected"] + 0.03, est
    auto = metrics(tmp_path / "auto")
    assert auto["estimator"] == {"init": "correlation", "template_registration": "correlation", "iterations": 0}
    # the simulated template scan places the reference 1 mm off in x (Scenario.template_offset_m)
    dx_px = auto["template_registration"]["shift_px"][1]
    pixel_m = 0.15 / 47
    assert dx_px * pixel_m == pytest.approx(-1e-3, abs=0.35 * pixel_m)
    grid = ImageGrid.from_roi([float(v) for v in REF_ROI], 48)
    save_template(tmp_path / "amp.npz", template_from_scan(Scan.load(small_scene / "tpl.npz"), grid), grid)
    capsys.readouterr()
    assert (
        _focus(
            small_scene / "scan.npz",
            tmp_path / "x",
            "--template",
            str(tmp_path / "amp.npz"),
            "--estimator",
            "correlation",
        )
        == 2
    )
    assert "needs the template's phase" in capsys.readouterr().err
    # an amplitude template (a digital twin's kind): auto takes alternating projections, and the
    # optimiser after them only where their phases have wrapped; the scan decides, not the stated
    # tracking error (the choice against the truth: test_template_match)
    amp = ["--template", str(tmp_path / "amp.npz")]
    expect = {
        "template_registration": "none",
        "projection_iterations": 30,
        "projection_restarts": 0,
        "init": "projection",
    }
    chosen = []
    for err_mm in ("0.5", "1.6"):
        assert _focus(small_scene / "scan.npz", tmp_path / f"auto{err_mm}", *amp, "--tracking-error-mm", err_mm) == 0
        m = metrics(tmp_path / f"auto{err_mm}")
        check = m["estimator"].pop("refine_check")
        assert check["refined"] == (check["coherence_sqrt_m"] < check["refine_below"])
        assert m["estimator"] == {**expect, "iterations": 150 if check["refined"] else 0}, err_mm
        assert m["confidence"]["estimator_choice"] == check["why"]
        assert m["target_ssim_corrected"] > m["target_ssim_uncorrected"] + 0.03
        chosen.append((check, m["estimator"]))
    assert chosen[0] == chosen[1]
    refined = [*amp, "--estimator", "projection-refined", "--coarse-iterations", "50", "--projection-restarts", "2"]
    assert _focus(small_scene / "scan.npz", tmp_path / "proj", *refined) == 0
    m = metrics(tmp_path / "proj")
    assert m["estimator"] == {
        **expect,
        "init": "projection",
        "iterations": 150,
        "projection_restarts": 2,
        "coarse_iterations": 50,
    }
    assert len(m["projection_restarts"]["losses"]) == 3
    assert m["target_ssim_corrected"] > m["target_ssim_uncorrected"] + 0.03
    capsys.readouterr()
    assert (
        _focus(
            small_scene / "scan.npz", tmp_path / "y", *amp, "--estimator", "projection", "--projection-iterations", "0"
        )
        == 2
    )
    assert "projection_iterations must be >= 1" in capsys.readouterr().err


@pytest.mark.slow
def test_confidence_report_warns_when_transfer_cannot_be_trusted(small_scene, tmp_path, capsys):
    assert _focus(small_scene / "scan.npz", tmp_path / "ok", "--method", "none") == 0
    ok = metrics(tmp_path / "ok")["confidence"]
    # the regions' centres (x = -0.075 and 0.075 m at 0.6 m) seen from the aperture centre
    assert ok["trusted"] and ok["separation_deg"] == pytest.approx(2 * np.degrees(np.arctan(0.075 / 0.6)), abs=0.2)
    capsys.readouterr()
    # 3 mm of tracking error at 10 degrees: the first-order bound passes pi/4
    assert _focus(small_scene / "scan.npz", tmp_path / "bad", "--method", "none", "--tracking-error-mm", "3") == 0
    assert "not to be trusted" in capsys.readouterr().err
    bad = metrics(tmp_path / "bad")["confidence"]
    assert not bad["trusted"] and bad["transfer_bound_rad_max"] > np.pi / 4


@pytest.mark.slow
def test_template_file_path_and_baselines(small_scene, tmp_path):
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.twins.templates import save_template, template_from_scan

    grid = ImageGrid.from_roi([float(v) for v in REF_ROI], 60)  # another grid: resampled on load
    save_template(tmp_path / "t.npz", template_from_scan(Scan.load(small_scene / "tpl.npz"), grid), grid)
    assert _focus(small_scene / "scan.npz", tmp_path / "a", "--template", str(tmp_path / "t.npz")) == 0
    assert _focus(small_scene / "scan.npz", tmp_path / "b", "--method", "none") == 0
    assert _focus(small_scene / "scan.npz", tmp_path / "c", "--method", "sharpness") == 0
    np.testing.assert_array_equal(np.load(tmp_path / "b" / "phase.npy"), 0)


def _corrupt(src, dst, **changes):
    z = dict(np.load(src))
    z.update(changes)
    save_npz_atomic(dst, z)
    return dst


@pytest.mark.slow  # 3 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_bad_inputs_give_clear_errors_and_keep_old_results(small_scene, tmp_path, capsys):
    scan = small_scene / "scan.npz"
    tpl = ["--template-scan", str(small_scene / "tpl.npz")]
    out = tmp_path / "out"
    out.mkdir()
    (out / "target.npy").write_bytes(b"earlier result")
    z = np.load(scan)
    cases = {
        "NaN or inf": _corrupt(
            scan,
            tmp_path / "nan.npz",
            data=np.where(np.arange(z["data"].size).reshape(z["data"].shape) == 5, np.nan, z["data"]).astype(
                np.complex64
            ),
        ),
        "positions must have shape": _corrupt(scan, tmp_path / "shape.npz", positions=z["positions"][:, :10]),
        "all zeros": _corrupt(scan, tmp_path / "zeros.npz", data=np.zeros_like(z["data"])),
        "must be complex": _corrupt(scan, tmp_path / "real.npz", data=z["data"].real.astype(np.float32)),
        "missing key": _corrupt(scan, tmp_path / "nokey.npz", f0_hz=None) if False else None,
    }
    cases.pop("missing key")
    for message, path in cases.items():
        assert _focus(path, out, *tpl, "--overwrite") == 2, message
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err
    # a region of interest with nothing in it
    empty = ["-0.5", "-0.4", "0.3", "0.4", "0.6"]
    rc = cli(
        "focus",
        scan,
        "--reference-roi",
        *empty,
        "--target-roi",
        *TGT_ROI,
        "--size 32 --out",
        out,
        "--quiet --overwrite",
        *tpl,
    )
    assert rc == 2 and "no object" in capsys.readouterr().err
    # a template file that is constant
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.twins.templates import save_template

    grid = ImageGrid.from_roi([float(v) for v in REF_ROI], 48)
    save_template(tmp_path / "flat.npz", np.ones(grid.shape), grid)
    assert _focus(scan, out, "--template", str(tmp_path / "flat.npz"), "--overwrite") == 2
    assert "constant" in capsys.readouterr().err
    assert _focus(tmp_path / "missing.npz", out, *tpl, "--overwrite") == 2
    assert "no such file" in capsys.readouterr().err
    # nothing of the earlier result was touched
    assert (out / "target.npy").read_bytes() == b"earlier result"
    assert sorted(p.name for p in out.iterdir()) == ["target.npy"]


def test_unknown_options_are_refused(capsys):
    with pytest.raises(SystemExit) as e:
        main(["focus", "x.npz", "--bogus"])
    assert e.value.code == 2
    with pytest.raises(SystemExit):
        main(["no-such-command"])


def test_confidence_asks_more_of_a_registered_physical_twin_than_of_an_amplitude_template():
    from twinfocus.focus.pipeline import MIN_REFERENCE_MATCH, MIN_REFERENCE_MATCH_PHYSICAL, confidence_report
    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.motion.trajectory import paper_raster, phase_centres
    from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array

    pos = phase_centres(paper_raster(6, 10), mmwcas_virtual_array())
    ref, tgt = ImageGrid.from_roi([float(v) for v in REF_ROI], 20), ImageGrid.from_roi([float(v) for v in TGT_ROI], 20)
    between = (MIN_REFERENCE_MATCH + MIN_REFERENCE_MATCH_PHYSICAL) / 2
    registered = {
        "reference_ssim_vs_template_corrected": between,
        "template_registration": {"shift_px": [0.0, 0.0], "at_limit": False},
    }
    physical = confidence_report(registered, pos, Chirp(), ref, tgt, 0.5e-3)
    amplitude = confidence_report({"reference_ssim_vs_template_corrected": between}, pos, Chirp(), ref, tgt, 0.5e-3)
    assert not physical["trusted"] and "matches its template poorly" in physical["warnings"][0]
    assert amplitude["trusted"]


def _one_line_error(capsys, *needles):
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    for needle in needles:
        assert needle in err, (needle, err)
    return err


def test_inputs_are_checked_before_any_work(small_scene, tmp_path, capsys):
    """Each bad input is one line, exit 2, before any back-projection (each
    answer comes in well under the time one back-projection would take)."""
    import time

    scan, tpl_path = small_scene / "scan.npz", small_scene / "tpl.npz"
    tpl = ["--template-scan", str(tpl_path)]
    raw = scan.read_bytes()
    (tmp_path / "trunc.npz").write_bytes(raw[: len(raw) // 2])
    damaged = bytearray(tpl_path.read_bytes())
    damaged[len(damaged) // 3 : len(damaged) // 3 + 64] = bytes(64)  # inside data.npy: a CRC failure on load
    (tmp_path / "damaged.npz").write_bytes(bytes(damaged))
    (tmp_path / "file").write_text("not a folder")
    cases = [
        ((tmp_path / "trunc.npz", tmp_path / "o1", *tpl), ("trunc.npz", "truncated or damaged")),
        (
            (scan, tmp_path / "o2", "--template-scan", str(tmp_path / "trunc.npz")),
            ("trunc.npz", "truncated or damaged"),
        ),
        (
            (scan, tmp_path / "o3", "--template-scan", str(tmp_path / "damaged.npz"), "--no-cache"),
            ("damaged.npz", "truncated or damaged"),
        ),
        ((scan, tmp_path / "o4", "--digital-twin", str(tpl_path)), ("--digital-twin", ".npz archive")),
        ((scan, tmp_path / "file", *tpl), ("--out", "existing file")),
        ((scan, tmp_path / "file" / "sub", *tpl), ("--out", "not a folder")),
        ((scan, tmp_path / "o5", *tpl, "--save-template", str(tmp_path)), ("--save-template", "is a folder")),
    ]
    for args, needles in cases:
        t = time.perf_counter()
        assert _focus(*args) == 2, needles
        _one_line_error(capsys, *needles)
        assert time.perf_counter() - t < 5, needles
    # an unwritable place: a read-only file system refuses even root
    assert _focus(scan, "/proc/twinfocus-out", *tpl) == 2
    _one_line_error(capsys, "--out", "cannot write")
    # --size 100000: the memory estimate is refused with its figure, at once
    t = time.perf_counter()
    rc = cli("focus", scan, *ROIS, "--size 100000 --out", tmp_path / "o6", "--quiet", *tpl)
    assert rc == 2 and time.perf_counter() - t < 5
    err = _one_line_error(capsys, "--size 100000", "GiB")
    import re

    # 120 positions x 1e10 pixels x (two complex64 bases + the optimiser's copies)
    gib = float(re.search(r"about ([0-9.]+) GiB", err).group(1))
    assert 120 * 1e10 * 24 / 2**30 <= gib <= 120 * 1e10 * 64 / 2**30
    assert not any((tmp_path / f"o{i}").exists() for i in range(1, 7))


def test_memory_estimate_against_the_bases_it_counts():
    """The estimate covers at least the two complex64 bases and the optimiser's float32 copy."""
    from twinfocus.cli.focus import check_memory

    need = check_memory(780, 100, available=10**12)
    assert need >= 780 * 100 * 100 * (2 * 8 + 8)
    with pytest.raises(TwinFocusError, match="GiB"):
        check_memory(780, 100, available=need - 1)


@pytest.mark.slow  # 4 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_pictures_of_an_earlier_run_do_not_stay_beside_new_results(small_scene, tmp_path):
    out = tmp_path / "o"
    assert _focus(small_scene / "scan.npz", out, "--method", "none", "--pictures", "all") == 0
    assert len(list(out.glob("*.png"))) > 1
    assert _focus(small_scene / "scan.npz", out, "--method", "none", "--pictures", "summary", "--overwrite") == 0
    assert sorted(p.name for p in out.glob("*.png")) == ["summary.png"]
    assert _focus(small_scene / "scan.npz", out, "--method", "none", "--no-pictures", "--overwrite") == 0
    assert not list(out.glob("*.png")) and (out / "metrics.json").is_file()


def test_capture_gaps_of_a_converted_scan_reach_metrics(small_scene, tmp_path):
    """The gaps `convert` records beside a scan (<scan>.capture.json) are in the
    metrics.json of a focus of that scan; a scan without the record has no `capture` entry."""
    import shutil

    from twinfocus.sensors.capture_to_scan import capture_report_path

    scan = tmp_path / "converted.npz"
    shutil.copy(small_scene / "scan.npz", scan)
    gaps = {
        "capture": "/data/adc_data_Raw_0.bin",
        "frames": 122,
        "frames_used": 120,
        "frames_dropped_flagged": 2,
        "frames_lost": 1,
        "frames_zero_filled": 1,
        "frames_device_skew": 0,
        "bytes_lost": 2912,
    }
    capture_report_path(scan).write_text(json.dumps(gaps))
    assert _focus(scan, tmp_path / "f", "--method", "none", "--no-pictures") == 0
    assert metrics(tmp_path / "f")["capture"] == gaps
    assert _focus(small_scene / "scan.npz", tmp_path / "g", "--method", "none", "--no-pictures") == 0
    assert "capture" not in metrics(tmp_path / "g")
