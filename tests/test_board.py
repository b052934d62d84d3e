"""The array as TI built it: the board file (TI's module_param.m positions at their 76.8 GHz design
frequency), a user's own board file, bad board files refused in one line, and what a wrong TX
offset does to a corner reflector's channels (what a calibration shows)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from tests.helpers import convert_capture
from twinfocus.errors import TwinFocusError
from twinfocus.radar.board import DEFAULT_BOARD_FILE, default_board, load_board
from twinfocus.radar.fmcw import C_M_PER_S, Chirp, mmwcas_rx_positions_m, mmwcas_tx_positions_m, mmwcas_virtual_array
from twinfocus.sensors.ti_mmwcas import RX_ARRAY_ORDER

# TI's module_param.m, copied by hand: TX1..TX12 azimuth / elevation, RX data channel 1..16 azimuth
TI_TX_AZI = [11, 10, 9, 32, 28, 24, 20, 16, 12, 8, 4, 0]
TI_TX_ELE = [6, 4, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0]
TI_RX_AZI = [11, 12, 13, 14, 50, 51, 52, 53, 46, 47, 48, 49, 0, 1, 2, 3]


def _board_file(path, **changes):
    doc = yaml.safe_load(DEFAULT_BOARD_FILE.read_text())
    doc.update(changes)
    path.write_text(yaml.safe_dump(doc))
    return path


def test_default_board_is_tis_layout_at_76_8_ghz():
    b = default_board()
    lam = C_M_PER_S / 76.8e9
    assert b.design_frequency_hz == 76.8e9 and b.design_wavelength_m == pytest.approx(lam)
    tx, rx = mmwcas_tx_positions_m(), mmwcas_rx_positions_m()
    # TX t of the project is TI's TX 12 - t; RX a is data channel RX_ARRAY_ORDER[a]
    for t in range(12):
        n = 12 - t
        assert tx[t, 0] == pytest.approx(TI_TX_AZI[n - 1] * lam / 2 + 8 * lam)
        assert tx[t, 1] == pytest.approx(-TI_TX_ELE[n - 1] * lam / 2 + 17 * lam)
    np.testing.assert_allclose(rx[:, 0], np.array(TI_RX_AZI)[RX_ARRAY_ORDER] * lam / 2)
    assert np.all(np.diff(rx[:, 0]) > 0)  # ascending along the board
    va = mmwcas_virtual_array()
    assert va.n_channels == 86
    np.testing.assert_allclose(np.diff(va.offsets_m[:, 0]), lam / 4)  # 0.9759 mm
    # 85 pitches of 0.9759 mm instead of the 0.9862 mm of a 76 GHz design: 0.88 mm shorter
    assert 85 * (C_M_PER_S / 76e9 - lam) / 4 == pytest.approx(0.88e-3, abs=0.01e-3)


def test_a_users_board_file_changes_the_array(tmp_path):
    b76 = load_board(_board_file(tmp_path / "b76.yaml", design_frequency_hz=76e9, name="76 GHz"))
    va = mmwcas_virtual_array(b76)
    assert b76.name == "76 GHz" and va.n_channels == 86
    np.testing.assert_allclose(np.diff(va.offsets_m[:, 0]), C_M_PER_S / 76e9 / 4)  # 0.9862 mm
    near = load_board(_board_file(tmp_path / "near.yaml", tx_offset_wavelengths=[8, 5]))
    va_near = mmwcas_virtual_array(near)
    np.testing.assert_allclose(va_near.offsets_m, mmwcas_virtual_array().offsets_m, atol=1e-12)  # same virtual line
    assert va_near.separation_m[0, 1] == pytest.approx(5 * near.design_wavelength_m)  # another TX-RX separation


@pytest.mark.parametrize(
    "change, message",
    [
        ({"design_frequency_hz": 76.8}, "design_frequency_hz must be a frequency in Hz"),
        ({"tx_along_half_wavelengths": [0, 1, 2]}, "tx_along_half_wavelengths must be a list of 12 numbers"),
        ({"rx_across_half_wavelengths": "zero"}, "rx_across_half_wavelengths must be a list of 16 numbers"),
        ({"tx_offset": [8, 17]}, "unknown board key(s) tx_offset"),
        ({"rx_along_half_wavelengths": [0] * 16}, "two RX antennas share a position"),
    ],
)
def test_bad_board_files_are_one_line(tmp_path, change, message):
    with pytest.raises(TwinFocusError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_board(_board_file(tmp_path / "bad.yaml", **change))


def test_convert_and_simulate_refuse_a_bad_board_and_write_nothing(tmp_path, capsys):
    from twinfocus.cli import main

    (tmp_path / "bad.yaml").write_text("name: x\ndesign_frequency_hz: [1\n")
    (tmp_path / "traj.txt").write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n")
    (tmp_path / "cap").mkdir()
    (tmp_path / "cap" / "master_0000_idx.bin").write_bytes(b"")
    rc = convert_capture(tmp_path, "--board", tmp_path / "bad.yaml")
    err = capsys.readouterr().err
    assert rc == 2 and "bad.yaml: not a YAML board file" in err and len(err.strip().splitlines()) == 1
    rc = main(["simulate", "--out", str(tmp_path / "sim.npz"), "--board", str(tmp_path / "missing.yaml")])
    err = capsys.readouterr().err
    assert rc == 2 and "missing.yaml: cannot read the board file" in err
    assert not (tmp_path / "s.npz").exists() and not (tmp_path / "sim.npz").exists()


def test_a_wrong_tx_offset_shows_in_a_corner_reflectors_channels(tmp_path):
    """A corner at the known range z0 captured by a board whose TX block sits elsewhere than the
    board file says: its channels' phases, against a point at that range, are off by
    k (|d_true|^2 - |d_file|^2) / (4 z0), d each channel's TX-RX separation -- the pattern a
    channel calibration finds. An error along the array spreads the channels' phases; one across
    it is nearly the same for every channel (a common phase, which imaging does not see)."""
    from twinfocus.motion.trajectory import Poses
    from twinfocus.sensors.emulators.radar_scene import monostatic_if, simulate_mimo_frames
    from twinfocus.sensors.frames import frame_to_virtual_channels, mmwcas_antenna_positions_body_m

    chirp = Chirp(n_samples=16)
    z0 = 0.6
    pose = Poses(np.array([0]), np.zeros((1, 3)), np.array([[0.0, 0.0, 0.0, 1.0]]))
    corner = np.array([[0.0, 0.0, z0]])
    truth = monostatic_if(chirp, mmwcas_virtual_array().offsets_m, corner)
    k_c = 2 * np.pi * chirp.fc_hz / C_M_PER_S

    def spread(phase):  # rad, about the channels' common phase
        return np.angle(np.exp(1j * phase) * np.conj(np.exp(1j * phase).mean()))

    for offset, spread_min, spread_max in (([6, 17], 1.0, np.inf), ([8, 12], 0.0, 0.05)):
        true_board = load_board(_board_file(tmp_path / "true.yaml", tx_offset_wavelengths=offset))
        tx, rx = mmwcas_antenna_positions_body_m(board=true_board)
        frame = simulate_mimo_frames(chirp, pose, corner, tx_body_m=tx, rx_body_m=rx)[0]

        def residual(board, frame=frame):
            ch = frame_to_virtual_channels(frame, chirp, z0, mmwcas_virtual_array(board))
            return np.angle((ch * np.conj(truth)).mean(axis=-1))  # per channel, rad

        assert np.abs(residual(true_board)).max() < 0.05  # the right board file: calibrated already
        wrong = residual(default_board())
        d_true = (mmwcas_virtual_array(true_board).separation_m ** 2).sum(1)
        d_file = (mmwcas_virtual_array().separation_m ** 2).sum(1)
        predicted = k_c * (d_true - d_file) / (4 * z0)
        assert np.abs(np.angle(np.exp(1j * (wrong - predicted)))).max() < 0.1
        assert spread_min <= np.ptp(spread(wrong)) <= spread_max
