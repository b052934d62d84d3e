"""The radar-camera clock offset found from the data (twinfocus.sensors.clock_offset): injected offsets
recovered, the scan's positions re-sampled along its track, one-line refusals."""

from __future__ import annotations

import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.backprojection.numba_backend import backproject
from twinfocus.imaging.grid import ImageGrid
from twinfocus.imaging.metrics import image_sharpness
from twinfocus.motion.trajectory import handheld_zigzag
from twinfocus.radar.fmcw import Chirp
from twinfocus.sensors.clock_offset import (
    along_track,
    focus_offset,
    leg_starts,
    range_history_offset,
    refine_offset,
    shift_positions,
    template_match,
)
from twinfocus.sensors.emulators.radar_scene import monostatic_if

CHIRP = Chirp(n_samples=64)
POINT = np.array([[0.03, 0.02, 0.6]])


def _sweep(rows: int = 40, period_s: float = 0.05):
    # 0.258 m per leg in rows x period seconds: about a hand's 0.13 m/s at 40 rows of 50 ms
    poses = handheld_zigzag(3, rows, frame_period_s=period_s, column_change_s=0.3, rng=1)
    return poses.timestamps_ns * 1e-9, poses.position_m


@pytest.mark.parametrize("offset_s", [0.0, 0.04, -0.03])
def test_range_history_recovers_an_injected_offset(offset_s):
    t, track = _sweep()
    centres = track[:, None, :] + np.array([[-0.01, 0, 0], [0.01, 0, 0]])[None]
    data = monostatic_if(CHIRP, centres, POINT).astype(np.complex64)
    # the radar's stamps run offset_s behind the camera's: adding offset_s puts them back
    est = range_history_offset(data, CHIRP, t - offset_s, t, track)
    assert abs(est.offset_s - offset_s) < 2e-3
    assert est.sigma_s < 5e-3
    np.testing.assert_allclose(est.scatterer_m, POINT[0], atol=5e-3)


def test_range_history_refuses_noise_a_still_radar_and_a_few_frames():
    t, track = _sweep()
    rng = np.random.default_rng(0)
    noise = (rng.normal(size=(len(t), 2, 64)) + 1j * rng.normal(size=(len(t), 2, 64))).astype(np.complex64)
    with pytest.raises(TwinFocusError, match="no static scatterer"):
        range_history_offset(noise, CHIRP, t, t, track)
    still = np.zeros_like(track)
    data = monostatic_if(CHIRP, still[:, None, :], POINT).astype(np.complex64)
    with pytest.raises(TwinFocusError, match="too short"):
        range_history_offset(data, CHIRP, t, t, still)
    with pytest.raises(TwinFocusError, match="too few"):
        range_history_offset(data[:5], CHIRP, t[:5], t, still)


def test_shift_positions_moves_each_position_along_its_motion():
    t = np.arange(5) * 0.1
    pos = np.zeros((5, 1, 3))
    pos[:, 0, 1] = np.array([0, 1, 2, 1, 0]) * 0.02  # up, then down: the sign flips with the leg
    moved = shift_positions(pos, t, 0.05)
    np.testing.assert_allclose(moved[1:4, 0, 1], [0.03, 0.03, 0.01])


def _two_legs():
    # up a column at 0.2 m/s, a 1 s turn with no frame kept, down the next column
    t = np.concatenate([np.arange(20) * 0.01, 1.2 + np.arange(20) * 0.01])
    pos = np.zeros((40, 2, 3))
    pos[:20, :, 1] = (np.arange(20) * 0.002)[:, None]
    pos[20:, :, 0] = 0.08
    pos[20:, :, 1] = (0.038 - np.arange(20) * 0.002)[:, None]
    pos[:, 1, 0] += 0.01  # a second channel beside the first
    return t, pos


def test_legs_end_at_a_gap_in_time_or_without_stamps_at_a_jump_in_place():
    t, pos = _two_legs()
    np.testing.assert_array_equal(leg_starts(t, pos), [0, 20])
    np.testing.assert_array_equal(leg_starts(np.arange(40.0), pos), [0, 20])
    np.testing.assert_array_equal(leg_starts(np.arange(20) * 0.01, pos[:20]), [0])


@pytest.mark.parametrize("offset_s", [0.03, -0.05])
def test_a_shift_goes_on_along_each_leg_past_its_ends_not_across_the_turn(offset_s):
    t, pos = _two_legs()
    moved = shift_positions(pos, t, offset_s)
    # every position, the ones past a leg's end included, moves along its own leg by 0.2 m/s x offset
    np.testing.assert_allclose(moved[:20, :, 1] - pos[:20, :, 1], 0.2 * offset_s, atol=1e-12)
    np.testing.assert_allclose(moved[20:, :, 1] - pos[20:, :, 1], -0.2 * offset_s, atol=1e-12)
    np.testing.assert_allclose(moved[..., 0], pos[..., 0], atol=1e-12)  # never towards the other column
    # jitter on the positions: the extrapolated ends stay within it (a line fitted over the end)
    rng = np.random.default_rng(3)
    noisy = pos + rng.normal(0, 2e-4, pos.shape[:1])[:, None, None]
    err = shift_positions(noisy, t, offset_s) - shift_positions(pos, t, offset_s)
    assert np.abs(err).max() < 1.5e-3


def test_the_template_match_scores_focus_not_place():
    rng = np.random.default_rng(0)
    tpl = np.zeros((24, 24))
    tpl[8:16, 6:18] = 1 + 0.3 * rng.random((8, 12))
    moved = np.roll(tpl, (1, -2), axis=(0, 1))  # in focus, two pixels off
    blurred = sum(np.roll(tpl, (0, k), axis=(0, 1)) for k in range(-3, 4)) / 7  # in place, smeared
    assert template_match(tpl)(moved) > 0.99
    assert template_match(tpl)(moved) > template_match(tpl)(blurred)
    assert template_match(tpl, 0)(moved) < template_match(tpl, 0)(blurred)  # held in place it prefers the smear


def test_refine_finds_the_centre_of_a_bumpy_peak():
    # a broad peak at 12 ms with a dip of a frame's width on top of it: the best sample is off,
    # the parabola through the peak's upper half is not
    def score(shift_m):
        dt = float(shift_m) / 0.2 - 0.012
        return -((dt / 0.01) ** 2) - 0.15 * np.exp(-((dt / 0.0015) ** 2)) + 0.1 * np.cos(dt / 0.004)

    t = np.arange(30) * 0.01
    pos = np.zeros((30, 1, 3))
    pos[:, 0, 1] = 0.2 * t
    est, tried = refine_offset(lambda p: p[10, 0, 1] - pos[10, 0, 1], along_track(pos, t), 0.0, 0.002, score)
    best_sample = max(tried, key=lambda kv: kv[1])[0]
    assert abs(best_sample - 0.012) > 1.5e-3
    assert abs(est.offset_s - 0.012) < 1e-3, (est, tried)
    assert 0 < est.sigma_s < 5e-3


@pytest.mark.parametrize("offset_s", [0.05, -0.03])
def test_focus_search_undoes_an_offset_of_the_tracked_positions(offset_s):
    t, track = _sweep(rows=24, period_s=0.05)
    offsets = np.stack([np.linspace(-0.04, 0.04, 8), np.zeros(8), np.zeros(8)], axis=1)
    true = track[:, None, :] + offsets[None]
    pts = np.array([[0.0, 0.0, 0.5], [0.02, 0.03, 0.5], [-0.03, -0.02, 0.5]])
    data = monostatic_if(CHIRP, true, pts).astype(np.complex64)
    tracked = shift_positions(true, t, offset_s)  # the camera's poses taken offset_s late
    grid = ImageGrid.from_roi((-0.06, 0.06, -0.06, 0.06, 0.5), 24)
    est, tried = focus_offset(lambda p: backproject(data, p, CHIRP, grid), along_track(tracked, t), 0.12)
    assert abs(est.offset_s + offset_s) < 2e-3, tried


@pytest.mark.parametrize("scale", [1e-20, 1.0, 1e12, 1e30])
def test_the_searchs_sharpness_is_the_same_at_any_scale_and_ranks_a_point_above_a_blur(scale):
    # a capture's ADC counts put |I|^4 past float32's range: then every offset scored 0
    point = np.zeros((16, 16), np.complex64)
    point[8, 8] = 1.0
    point[8, 9] = 0.5j
    blur = np.full((16, 16), 0.3 + 0.1j, np.complex64)
    blur[8, 8] = 1.0
    exact = (1.0 + 0.25**2) / (1.0 + 0.25) ** 2  # sum |I|^4 / (sum |I|^2)^2, by hand
    assert image_sharpness((point * np.float32(scale)).astype(np.complex64)) == pytest.approx(exact, rel=1e-6)
    assert image_sharpness(blur * np.float32(scale)) < image_sharpness(point * np.float32(scale))
    assert image_sharpness(np.zeros((4, 4), np.complex64)) == 0.0


def _cli(*argv: str) -> int:
    from twinfocus.cli import main

    return main(list(argv))


@pytest.mark.slow  # 3.9 s (2 cores, idle): out of make test-fast (benchmarks/results/test_fast.json)
def test_a_ti_capture_with_a_shifted_camera_clock_converts_to_the_synchronised_scan(tmp_path, capsys):
    import json

    from twinfocus.motion.trajectory import Poses
    from twinfocus.radar.scan import Scan
    from twinfocus.sensors.emulators.__main__ import main as emulate
    from twinfocus.sensors.trajectory_files import read_tum, write_tum

    cap = tmp_path / "cap"
    assert (
        emulate(
            [
                "capture",
                str(cap),
                "--columns",
                "2",
                "--rows",
                "60",
                "--row-pitch",
                "0.004",
                "--column-pitch",
                "0.15",
                "--n-samples",
                "64",
            ]
        )
        == 0
    )
    synced = read_tum(cap / "trajectory.txt")
    # the camera started 60 ms before the radar and stopped after it: --align start is 60 ms off
    lead_ns, pad = 60_000_000, 4
    before = synced.timestamps_ns[0] - lead_ns + np.arange(pad) * lead_ns // pad
    after = synced.timestamps_ns[-1] + (np.arange(pad) + 1) * lead_ns // pad
    ts = np.concatenate([before, synced.timestamps_ns, after])
    pos = np.concatenate(
        [np.repeat(synced.position_m[:1], pad, 0), synced.position_m, np.repeat(synced.position_m[-1:], pad, 0)]
    )
    quat = np.concatenate(
        [np.repeat(synced.quat_xyzw[:1], pad, 0), synced.quat_xyzw, np.repeat(synced.quat_xyzw[-1:], pad, 0)]
    )
    write_tum(tmp_path / "camera.txt", Poses(ts, pos, quat))
    common = ["--n-samples", "64", "--frame", "world", "--quiet"]
    out = {}
    for name, traj, align in (
        ("synced", cap / "trajectory.txt", "start"),
        ("start", tmp_path / "camera.txt", "start"),
        ("scan", tmp_path / "camera.txt", "scan"),
    ):
        out[name] = tmp_path / f"{name}.npz"
        assert (
            _cli("convert", str(cap), "--trajectory", str(traj), "--out", str(out[name]), "--align", align, *common)
            == 0
        )
    ref, start, found = (Scan.load(out[k]) for k in ("synced", "start", "scan"))
    n = min(ref.n_positions, found.n_positions)
    # median over positions: the raster's one-frame jump between columns stays off by a lot either way
    err_scan = np.median(np.linalg.norm(found.positions[:n] - ref.positions[:n], axis=-1))
    err_start = np.median(np.linalg.norm(start.positions[:n] - ref.positions[:n], axis=-1))
    assert err_start > 2e-3  # the trap: the first frame on the first pose
    # the range history alone is good to about 10 ms here; the focus of the brightest region, on the
    # camera's poses, ends on the emulator's 60 ms: the synchronised scan's positions, to a tenth of a mm
    clock = json.loads((tmp_path / "scan.capture.json").read_text())["clock"]
    assert clock["stage"] == "focus" and clock["applied"], clock
    assert abs(clock["offset_s"] - lead_ns * 1e-9) < 2e-3, clock
    assert abs(clock["range_history"]["offset_s"] - lead_ns * 1e-9) < 3 * clock["range_history"]["sigma_s"], clock
    assert err_scan < 1e-4, (err_scan, err_start)
    assert clock["focus"]["score"] == "sharpness"
    # the synchronised scan as the stage's (its positions the truth here), matched on the region the
    # sharpness found: the same 60 ms, and the record says the template chose it
    roi = [str(v) for v in clock["focus"]["region_m"]]
    templated = tmp_path / "templated.npz"
    assert _cli("convert", str(cap), "--trajectory", str(tmp_path / "camera.txt"), "--out", str(templated),
                "--reference-roi", *roi, "--template-scan", str(out["synced"]), *common) == 0  # fmt: skip
    clock = json.loads((tmp_path / "templated.capture.json").read_text())["clock"]
    assert clock["stage"] == "focus" and clock["focus"]["score"] == "template_match", clock
    assert clock["focus"]["region_m"] == [float(v) for v in roi]
    assert abs(clock["offset_s"] - lead_ns * 1e-9) < 2e-3, clock


def test_clock_search_of_a_scan_without_stamps_counts_positions():
    from twinfocus.radar.scan import Scan
    from twinfocus.sensors.clock_offset import search_scan_clock

    t, track = _sweep(rows=24, period_s=0.05)
    offsets = np.stack([np.linspace(-0.04, 0.04, 8), np.zeros(8), np.zeros(8)], axis=1)
    true = track[:, None, :] + offsets[None]
    pts = np.array([[0.0, 0.0, 0.5], [0.02, 0.03, 0.5], [-0.03, -0.02, 0.5]])
    data = monostatic_if(CHIRP, true, pts).astype(np.complex64)
    # one position late (50 ms at this sweep's 50 ms period); the scan carries no stamps
    late = Scan(data, shift_positions(true, t, 0.05), CHIRP, positions_true=true)
    found, rec = search_scan_clock(late, (-0.06, 0.06, -0.06, 0.06, 0.5), 24, step_s=0.02)
    assert rec["unit"] == "positions"
    assert abs(rec["offset_s"] + 1.0) < 0.1, rec
    # median over positions: at the turns between legs the order's time is no time at all
    err = lambda p: np.median(np.linalg.norm(p - true, axis=-1))  # noqa: E731
    assert err(found.positions) < err(late.positions) / 3
    with pytest.raises(TwinFocusError, match="needs --reference-roi"):
        search_scan_clock(late, None, 24)


def test_focus_clock_search_records_the_offset_it_undid(tmp_path):
    import json

    from twinfocus.radar.scan import Scan

    t, track = _sweep(rows=24, period_s=0.05)
    offsets = np.stack([np.linspace(-0.04, 0.04, 8), np.zeros(8), np.zeros(8)], axis=1)
    true = track[:, None, :] + offsets[None]
    pts = np.array([[0.0, 0.0, 0.5], [0.02, 0.03, 0.5], [-0.03, -0.02, 0.5], [0.1, 0.0, 0.5]])
    data = monostatic_if(CHIRP, true, pts).astype(np.complex64)
    stamps = np.round(t * 1e9).astype(np.int64)
    Scan(data, shift_positions(true, t, 0.04), CHIRP, positions_true=true, timestamps_ns=stamps).save(
        tmp_path / "s.npz"
    )
    roi = [
        "--reference-roi",
        "-0.06",
        "0.06",
        "-0.06",
        "0.06",
        "0.5",
        "--target-roi",
        "0.07",
        "0.13",
        "-0.03",
        "0.03",
        "0.5",
    ]
    out = tmp_path / "out"
    rc = _cli("focus", str(tmp_path / "s.npz"), *roi, "--method", "none", "--clock-search", "--size", "24",
              "--out", str(out), "--quiet", "--no-pictures")  # fmt: skip
    assert rc == 0
    clock = json.loads((out / "metrics.json").read_text())["clock_search"]
    assert clock["unit"] == "s" and abs(clock["offset_s"] + 0.04) < 2e-3


def test_the_search_line_says_to_convert_again_only_past_a_large_offset():
    from twinfocus.sensors.clock_offset import RECONVERT_ABOVE_S, clock_search_line

    rec = {"unit": "s", "sigma_s": 1e-3, "images_formed": 76, "seconds": 2.0}
    small = clock_search_line({**rec, "offset_s": -0.02})
    large = clock_search_line({**rec, "offset_s": -(RECONVERT_ABOVE_S + 0.04)})
    assert "-20.00 +- 1.00 ms" in small and "convert" not in small
    assert "--time-offset-s" in large and f"{-(RECONVERT_ABOVE_S + 0.04):+.3f}" in large
    counted = clock_search_line({**rec, "unit": "positions", "offset_s": -10.0})
    assert "positions" in counted and "convert" not in counted


@pytest.mark.slow  # 150 s on 2 cores under a load of 4 (five conversions of a 300-frame capture)
def test_convert_ends_an_emulated_zigzag_on_its_true_clock_offset(tmp_path):
    """The emulated capture's camera started ``lead`` before the radar (its clock, the truth): a
    hand's 0.2 m/s over 3 columns, 0.5 mm tracking error, the board's errors uncalibrated.
    ``--align start`` puts the first frame that much early; the range history's offset on top of
    it lies within 2 sigma of ``lead``, and its focus stage ends within 1 ms of it, on the
    synchronised scan's positions; on a 4 s sweep no rate is fitted."""
    import json

    from twinfocus.motion.trajectory import Poses
    from twinfocus.radar.scan import Scan
    from twinfocus.sensors.emulators.__main__ import main as emulate
    from twinfocus.sensors.emulators.zed_bag import camera_track
    from twinfocus.sensors.trajectory_files import read_tum, write_tum

    cap = tmp_path / "cap"
    sweep = ["--columns", "3", "--column-pitch", "0.1", "--rows", "100", "--row-pitch", "0.0025", "--period", "0.0125"]
    board = ["--array-errors", "typical", "--array-seed", "3", "--tracking-error-mm", "0.5", "--seed", "1"]
    assert emulate(["capture", str(cap), *sweep, *board, "--n-samples", "128"]) == 0
    common = ["--frame", "world", "--n-samples", "128", "--quiet"]
    synced = tmp_path / "synced.npz"
    assert _cli("convert", str(cap), "--trajectory", str(cap / "trajectory.txt"), "--out", str(synced), "--align",
                "start", *common) == 0  # fmt: skip
    ref = Scan.load(synced).positions
    track = read_tum(cap / "trajectory.txt")
    for lead_ms in (0, 15, 50, 100):
        ts, pos, quat = camera_track(track.timestamps_ns, track.position_m, track.quat_xyzw, lead_ms * 1_000_000)
        write_tum(tmp_path / f"camera{lead_ms}.txt", Poses(ts, pos, quat))
        out = tmp_path / f"scan{lead_ms}.npz"
        rc = _cli("convert", str(cap), "--trajectory", str(tmp_path / f"camera{lead_ms}.txt"), "--out", str(out),
                  "--align", "scan", *common)  # fmt: skip
        assert rc == 0
        clock = json.loads(out.with_name(out.stem + ".capture.json").read_text())["clock"]
        rh = clock["range_history"]
        assert abs(rh["offset_s"] - lead_ms * 1e-3) < 2 * rh["sigma_s"] and rh["sigma_s"] < 0.05, (lead_ms, rh)
        assert clock["stage"] == "focus" and abs(clock["offset_s"] - lead_ms * 1e-3) < 1e-3, (lead_ms, clock)
        assert 1e-3 <= clock["sigma_s"] < rh["sigma_s"]  # honest: the tracker's jitter over the hand's speed
        assert clock["rate"] == 0.0 and "not measurable: sweep 3.7 s" in clock["rate_note"]
        # a frame past the trajectory's end may drop; the frames at the raster's one-frame jump
        # between columns (10 cm in 12.5 ms) stay off by cm for a fraction of a ms: the median
        got = Scan.load(out).positions
        n = min(len(got), len(ref))
        assert np.median(np.linalg.norm(got[:n] - ref[:n], axis=-1)) < 0.25e-3, lead_ms


@pytest.mark.slow  # 2.0 s (2 cores, idle): out of make test-fast (benchmarks/results/test_fast.json)
def test_a_clock_rate_is_fitted_only_over_a_sweep_long_enough_to_show_one(monkeypatch):
    import twinfocus.sensors.clock_offset as clock

    # one point, 6 legs of 60 frames 50 ms apart (19.5 s); the radar's clock runs 3000 ppm slow:
    # its stamps t - offset - rate (t - t0), so the offset added grows by rate per second
    rate, offset = 3e-3, 0.02
    poses = handheld_zigzag(6, 60, frame_period_s=0.05, column_change_s=0.3, rng=1)
    t, track = poses.timestamps_ns * 1e-9, poses.position_m
    centres = track[:, None, :] + np.array([[-0.01, 0, 0], [0.01, 0, 0]])[None]
    data = monostatic_if(CHIRP, centres, POINT).astype(np.complex64)
    stamps = t - offset - rate * (t - t[0])
    # two free-running clocks drift by 100 ppm at most: 19.5 s cannot show that, the rate is held at 0
    held = range_history_offset(data, CHIRP, stamps, t, track, fit_rate=True)
    needs = clock.rate_needs_s(held.sigma_s)
    assert held.rate == 0.0 and held.sigma_rate is None and needs > np.ptp(stamps)
    assert held.rate_note == f"not measurable: sweep {np.ptp(stamps):.1f} s, needs > {needs:.0f} s"
    assert "rate not measurable" in held.line()
    assert needs * clock.MAX_CLOCK_RATE == pytest.approx(8 * held.sigma_s)
    # clocks that could drift by 2 %: the same sweep shows the rate, and the two halves find it
    monkeypatch.setattr(clock, "MAX_CLOCK_RATE", 0.02)
    est = range_history_offset(data, CHIRP, stamps, t, track, fit_rate=True)
    assert est.rate_note is None and est.sigma_rate is not None and est.sigma_rate < rate / 3
    assert abs(est.rate - rate) < 2 * est.sigma_rate, est


def test_converts_focus_stage_matches_a_template_on_the_reference_region_where_given(tmp_path, capsys):
    from twinfocus.radar.scan import Scan
    from twinfocus.sensors.clock_offset import ClockEstimate, on_track, refine_by_focus
    from twinfocus.twins.templates import scan_template_on

    t, track = _sweep(rows=24, period_s=0.05)
    offsets = np.stack([np.linspace(-0.04, 0.04, 8), np.zeros(8), np.zeros(8)], axis=1)
    true = track[:, None, :] + offsets[None]
    pts = np.array([[0.0, 0.0, 0.5], [0.02, 0.03, 0.5], [-0.03, -0.02, 0.5], [0.1, 0.0, 0.5]])
    data = monostatic_if(CHIRP, true, pts).astype(np.complex64)
    lag = 0.03  # the camera stamps each pose 30 ms late: the frames' stamps + 30 ms find it
    positions_at = on_track(t + lag, true, t)
    roi = (-0.06, 0.06, -0.06, 0.06, 0.5)
    # a motion-stage scan of the reference alone (its three points), on the true positions
    stage = Scan(monostatic_if(CHIRP, true, pts[:3]).astype(np.complex64), true, CHIRP, positions_true=true)
    rh = ClockEstimate(lag + 0.012, 0.008, "range_history")  # the range history 12 ms off
    est, rec = refine_by_focus(data, CHIRP, positions_at, rh, 0.5, region_m=roi, template=scan_template_on(stage, roi))
    assert rec["score"] == "template_match" and rec["region_m"] == list(roi)
    assert abs(est.offset_s - lag) < 1.5e-3, rec
    plain, rec = refine_by_focus(data, CHIRP, positions_at, rh, 0.5)
    assert rec["score"] == "sharpness" and rec["region_m"] != list(roi)  # the brightest box, found
    with pytest.raises(TwinFocusError, match="needs the reference's region"):
        refine_by_focus(data, CHIRP, positions_at, rh, 0.5, template=scan_template_on(stage, roi))
    # on the command line the template needs its region, refused before any work
    assert _cli("convert", str(tmp_path / "none"), "--trajectory", "x.txt", "--out", str(tmp_path / "s.npz"),
                "--template-scan", "stage.npz") == 2  # fmt: skip
    assert "--template-scan needs --reference-roi" in capsys.readouterr().err
