"""The channel calibration's picture (``twinfocus calibrate``'s PNG), drawn from the calibration
and its report (:mod:`twinfocus.radar.calibration`), which never write files themselves."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from twinfocus.io.atomic import atomic_writer
from twinfocus.io.png import pyplot
from twinfocus.radar.calibration import CalibrationReport, ChannelCalibration


def save_calibration_png(path: str | os.PathLike, cal: ChannelCalibration, report: CalibrationReport) -> Path:
    """The calibration's picture: per channel, the corner's phase and amplitude before and after,
    the delays, and the corner's range profile (matplotlib, ~1 s)."""
    plt = pyplot()
    k = np.arange(cal.n_channels)
    q = cal.quality
    fig, ax = plt.subplots(2, 2, figsize=(10, 6.5))
    b = report.before * np.exp(-1j * np.angle(np.nansum(report.before)))
    a = report.after * np.exp(-1j * np.angle(np.nansum(report.after)))
    ax[0, 0].plot(
        k, np.degrees(np.angle(b)), ".", color="0.6", label=f"before ({q['phase_spread_before_deg']:.0f} deg rms)"
    )
    ax[0, 0].plot(
        k, np.degrees(np.angle(a)), ".", color="C3", label=f"after ({q['residual_phase_deg_rms']:.1f} deg rms)"
    )
    ax[0, 0].set(xlabel="virtual channel", ylabel="corner's phase, deg", ylim=(-185, 185), title="phase per channel")
    ax[0, 0].legend(fontsize=8, loc="lower right")
    norm = lambda v: 20 * np.log10(np.abs(v) / np.sqrt(np.nanmean(np.abs(v) ** 2)))
    ax[0, 1].plot(k, norm(report.before), ".", color="0.6", label="before")
    ax[0, 1].plot(k, norm(report.after), ".", color="C3", label="after")
    ax[0, 1].set(xlabel="virtual channel", ylabel="dB re rms", title="amplitude per channel")
    ax[0, 1].legend(fontsize=8)
    ax[1, 0].plot(k, cal.delay_m * 1e3, ".", color="C0")
    ax[1, 0].set(xlabel="virtual channel", ylabel="mm", title="range offset per channel (corrected)")
    p = report.peak
    ax[1, 1].plot(p.profile_ranges_m, p.profile_db, color="C0", lw=0.8)
    ax[1, 1].axvline(
        p.range_m, color="C3", ls=":", label=f"corner {q['corner_range_m']:.3f} m, {q['peak_snr_db']:.0f} dB"
    )
    ax[1, 1].set(xlabel="range, m", ylabel="dB re peak", ylim=(-70, 3), title="range profile (all channels)")
    ax[1, 1].legend(fontsize=8)
    fig.suptitle(
        f"channel calibration: residual {q['residual_phase_deg_rms']:.1f} deg rms, peak sharpness "
        f"{q['peak_sharpness_before']:.2f} -> {q['peak_sharpness']:.2f}",
        fontsize=10,
    )
    fig.tight_layout()
    with atomic_writer(path) as f:
        fig.savefig(f, format="png", dpi=80)
    plt.close(fig)
    return Path(path)
