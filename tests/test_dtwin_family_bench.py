"""The family bench's placement measure (benchmarks/bench_dtwin_family.py), which docs/digital_twin_field.md
quotes: against an injected misplacement and an injected image shift."""

from types import SimpleNamespace

import numpy as np

from benchmarks.bench_dtwin_family import placement
from twinfocus.grid import ImageGrid
from twinfocus.metrics import oracle_phase
from twinfocus.radar import Chirp
from twinfocus.subpixel import shift_image


def test_placement_reads_an_injected_ramp_as_its_shift_and_finds_an_injected_image_shift():
    rng = np.random.default_rng(5)
    chirp = Chirp()
    # 12 x 10 positions 4 mm apart, 3 channels each along x, tracked to 0.3 mm
    gx, gy = np.meshgrid(np.arange(12) * 4e-3, np.arange(10) * 4e-3)
    centres = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    channels = np.array([[-2e-3, 0, 0], [0, 0, 0], [2e-3, 0, 0]])
    tracked = centres[:, None, :] + channels[None]
    true = tracked + rng.normal(0, 0.3e-3, tracked.shape)
    grid = ImageGrid.from_roi([-0.03, 0.03, -0.03, 0.03, 0.6], 32)
    yy, xx = np.mgrid[:32, :32]
    truth = (np.exp(-((yy - 16.0) ** 2 + (xx - 14.0) ** 2) / 20.0) * np.exp(1j * 0.3 * xx)).astype(np.complex64)
    # the truth's phase plus a ramp that stands for a known image shift (b R / k)
    slope = np.array([-6.0, 9.0])  # rad/m across x, y
    range_m = 0.6
    shift_m = slope * range_m * chirp.wavelength_m / (4 * np.pi)
    phase = oracle_phase(true, tracked, grid.centre_m, chirp) + (centres[:, :2] - centres[:, :2].mean(0)) @ slope + 0.7
    d = {"scan": SimpleNamespace(positions=tracked, positions_true=true, chirp=chirp), "rg": grid,
         "truth": {"truth_target": truth}}
    out = SimpleNamespace(phase_rad=phase, target=shift_image(truth, 1.0, -0.5),
                          metrics={"estimator": {"phase_coherence_sqrt_m": 3.2}})
    got = placement(d, out)
    assert np.allclose(got["error_mm"], shift_m * 1e3, atol=0.01)
    assert got["best_shift_px"] == [-1.0, 0.5] and got["best_shift_ssim"] > 0.99
    assert got["phase_coherence_sqrt_m"] == 3.2
