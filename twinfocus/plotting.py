"""PNG pictures of focusing results (matplotlib, no display needed)."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from twinfocus.grid import ImageGrid  # noqa: E402


def _show(ax, image: np.ndarray, grid: ImageGrid, title: str) -> None:
    amp = np.abs(image)
    amp = amp / max(amp.max(), 1e-30)
    # Scene frame as seen from the radar: x right, y down (right-handed with z into the scene).
    extent = [grid.x0 * 1e3, grid.x1 * 1e3, grid.y1 * 1e3, grid.y0 * 1e3]
    ax.imshow(amp, origin="upper", extent=extent, cmap="inferno", vmin=0, vmax=1)
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("x (mm)", fontsize=8)
    ax.set_ylabel("y (mm)", fontsize=8)
    ax.tick_params(labelsize=7)


def save_image_png(path: str | Path, image: np.ndarray, grid: ImageGrid, title: str) -> None:
    """One amplitude image (max-normalised) with axes in millimetres."""
    fig, ax = plt.subplots(figsize=(4, 4 * grid.height / grid.width * (grid.y1 - grid.y0) / (grid.x1 - grid.x0) * grid.width / grid.height + 0.6))
    _show(ax, image, grid, title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_focus_pictures(out_dir: Path, o) -> None:
    """summary.png (all panels), one PNG per image, loss.png and phase.png."""
    m = o.metrics
    panels = []
    if o.template is not None:
        panels.append((o.template, o.reference_grid, "reference template"))
    panels += [
        (o.reference_uncorrected, o.reference_grid, "reference, uncorrected"),
        (o.reference, o.reference_grid, "reference, corrected"),
        (o.target_uncorrected, o.target_grid, "target, uncorrected" + _ssim_tag(m.get("target_ssim_uncorrected"))),
        (o.target, o.target_grid, f"target, {o.method}" + _ssim_tag(m.get("target_ssim_corrected"))),
    ]
    if o.target_truth is not None:
        panels.append((o.target_truth, o.target_grid, "target, true positions"))
    cols = 3 if len(panels) > 4 else len(panels)
    rows = int(np.ceil(len(panels) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 3.9 * rows), squeeze=False)
    for ax in axes.ravel()[len(panels):]:
        ax.axis("off")
    for ax, (img, grid, title) in zip(axes.ravel(), panels):
        _show(ax, img, grid, title)
    fig.tight_layout()
    fig.savefig(out_dir / "summary.png", dpi=110)
    plt.close(fig)

    names = {
        "template.png": (o.template, o.reference_grid, "reference template"),
        "reference_uncorrected.png": (o.reference_uncorrected, o.reference_grid, "reference, uncorrected"),
        "reference.png": (o.reference, o.reference_grid, "reference, corrected"),
        "target_uncorrected.png": (o.target_uncorrected, o.target_grid, "target, uncorrected"),
        "target.png": (o.target, o.target_grid, f"target, {o.method}"),
        "target_truth.png": (o.target_truth, o.target_grid, "target, true positions"),
    }
    for name, (img, grid, title) in names.items():
        if img is not None:
            save_image_png(out_dir / name, img, grid, title)

    if o.loss_history.size:
        fig, ax = plt.subplots(figsize=(5, 3))
        if o.loss_history.size == 1:
            # a closed-form estimate has one loss and no curve: show the point and say why
            ax.plot([0], o.loss_history, "o")
            init = m.get("estimator", {}).get("init", "closed-form")
            ax.set_title(f"{init} estimate, no optimiser: loss {o.loss_history[0]:.3f}", fontsize=9)
        else:
            ax.plot(o.loss_history)
        ax.set_xlabel("iteration")
        ax.set_ylabel("loss")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(out_dir / "loss.png", dpi=110)
        plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 3))
    ax.plot(np.angle(np.exp(1j * o.phase_rad)), ".", ms=2, label="estimated")
    if o.phase_oracle_rad is not None:
        d = o.phase_rad - o.phase_oracle_rad
        offset = np.angle(np.exp(1j * d).mean())
        ax.plot(np.angle(np.exp(1j * (o.phase_oracle_rad + offset))), ".", ms=2, label="true (at target centre)")
    ax.set_xlabel("radar position")
    ax.set_ylabel("phase (rad)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out_dir / "phase.png", dpi=110)
    plt.close(fig)


def _ssim_tag(value) -> str:
    return "" if value is None else f"\nSSIM {value:.3f}"
