"""PNG pictures of focusing results, no display needed.

``summary.png`` (every image side by side) is drawn with Pillow alone in ~0.05 s: it is what
``twinfocus focus`` writes by default. The other pictures (one per image with axes, loss curve,
phase) use matplotlib, whose import and drawing cost ~1 s, and are written on request
(``--pictures all``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from twinfocus.imaging.grid import ImageGrid
from twinfocus.imaging.metrics import image_ssim
from twinfocus.io.png import pyplot

#: which pictures ``twinfocus focus --pictures`` writes
PICTURES = ("summary", "all", "none")

# matplotlib's "inferno" as a degree-6 polynomial per channel (within 0.034 of the table, checked
# by tests/test_pictures.py), so the summary needs no matplotlib.
_INFERNO = np.array(
    [
        [0.0002189403691192265, 0.001651004631001012, -0.01948089843709184],
        [0.1065134194856116, 0.5639564367884091, 3.932712388889277],
        [11.60249308247187, -3.972853965665698, -15.9423941062914],
        [-41.70399613139459, 17.43639888205313, 44.35414519872813],
        [77.162935699427, -33.40235894210092, -81.80730925738993],
        [-71.31942824499214, 32.62606426397723, 73.20951985803202],
        [25.13112622477341, -12.24266895238567, -23.07032500287172],
    ]
)


def inferno(t: np.ndarray) -> np.ndarray:
    """float (...) in [0, 1] -> float64 (..., 3) RGB in [0, 1] (matplotlib's inferno, approximated)."""
    t = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0)[..., None]
    rgb = _INFERNO[6]
    for c in _INFERNO[5::-1]:
        rgb = c + t * rgb
    return np.clip(rgb, 0.0, 1.0)


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: the bitmap font has one size
        return ImageFont.load_default()


def summary_panels(o) -> list[tuple[np.ndarray, ImageGrid, str]]:
    """(image, grid, title) of every image of a :class:`~twinfocus.focus.pipeline.FocusOutputs`."""
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
    return panels


def write_summary_png(path: str | Path, panels: list[tuple[np.ndarray, ImageGrid, str]], panel_px: int = 260) -> None:
    """Amplitude images (each max-normalised, inferno) in a grid of at most 3 columns, each with
    its title and its extent in millimetres; the panel's longer side is ``panel_px`` pixels and
    its aspect that of the region. Scene frame as seen from the radar: x right, y down."""
    from PIL import Image, ImageDraw

    title_font, small = _font(14), _font(11)
    cols = 3 if len(panels) > 4 else len(panels)
    rows = -(-len(panels) // cols)
    head, foot, pad = 40, 20, 12
    cell_w, cell_h = panel_px + 2 * pad, panel_px + head + foot + pad
    canvas = Image.new("RGB", (cols * cell_w, rows * cell_h), "white")
    draw = ImageDraw.Draw(canvas)
    for n, (img, grid, title) in enumerate(panels):
        amp = np.abs(np.asarray(img, dtype=np.complex128 if np.iscomplexobj(img) else np.float64))
        amp = amp / max(float(amp.max()), 1e-30)
        w_m, h_m = grid.x1 - grid.x0, grid.y1 - grid.y0
        scale = panel_px / max(w_m, h_m)
        size = (max(1, round(w_m * scale)), max(1, round(h_m * scale)))
        tile = Image.fromarray((inferno(amp) * 255 + 0.5).astype(np.uint8), "RGB").resize(
            size, Image.Resampling.BILINEAR
        )
        x0 = (n % cols) * cell_w + pad + (panel_px - size[0]) // 2
        y0 = (n // cols) * cell_h + head
        canvas.paste(tile, (x0, y0))
        draw.multiline_text(
            ((n % cols) * cell_w + pad, (n // cols) * cell_h + 4), title, fill="black", font=title_font, spacing=2
        )
        extent = f"x {grid.x0 * 1e3:.0f}..{grid.x1 * 1e3:.0f} mm, y {grid.y0 * 1e3:.0f}..{grid.y1 * 1e3:.0f} mm, z {grid.z * 1e3:.0f} mm"
        draw.text(((n % cols) * cell_w + pad, y0 + size[1] + 3), extent, fill="dimgray", font=small)
    canvas.save(path, optimize=False)


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


def _save(fig, path: str | Path, dpi: int = 110) -> None:
    """Lay out a matplotlib figure, write it to ``path`` (PNG at ``dpi``) and close it."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)


def save_image_png(path: str | Path, image: np.ndarray, grid: ImageGrid, title: str) -> None:
    """One amplitude image (max-normalised) with axes in millimetres (matplotlib)."""
    plt = pyplot()
    fig, ax = plt.subplots(
        figsize=(
            4,
            4 * grid.height / grid.width * (grid.y1 - grid.y0) / (grid.x1 - grid.x0) * grid.width / grid.height + 0.6,
        )
    )
    _show(ax, image, grid, title)
    _save(fig, path)


def write_focus_pictures(out_dir: Path, o, which: str = "summary") -> None:
    """Pictures of a :class:`~twinfocus.focus.pipeline.FocusOutputs` into ``out_dir``.

    which : "summary" (default): summary.png only (Pillow, ~0.05 s); "all": that, one PNG per
        image, loss.png and phase.png (matplotlib, ~1-2 s more); "extra": the others alone;
        "none": nothing.
    """
    if which not in PICTURES + ("extra",):
        raise ValueError(f"which must be one of {PICTURES + ('extra',)}, got {which!r}")
    out_dir = Path(out_dir)
    if which in ("summary", "all"):
        write_summary_png(out_dir / "summary.png", summary_panels(o))
    if which in ("all", "extra"):
        write_detail_pictures(out_dir, o)


def write_detail_pictures(out_dir: Path, o) -> None:
    """One PNG per image with axes, loss.png and phase.png (matplotlib)."""
    plt = pyplot()
    m = o.metrics
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
    if o.rung_targets:
        save_rungs_png(out_dir / "model_ladder.png", o)

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
        _save(fig, out_dir / "loss.png")

    fig, ax = plt.subplots(figsize=(6, 3))
    ax.plot(np.angle(np.exp(1j * o.phase_rad)), ".", ms=2, label="estimated")
    if o.phase_oracle_rad is not None:
        d = o.phase_rad - o.phase_oracle_rad
        offset = np.angle(np.exp(1j * d).mean())
        ax.plot(np.angle(np.exp(1j * (o.phase_oracle_rad + offset))), ".", ms=2, label="true (at target centre)")
    ax.set_xlabel("radar position")
    ax.set_ylabel("phase (rad)")
    ax.legend(fontsize=8)
    _save(fig, out_dir / "phase.png")


def save_rungs_png(path: Path, o) -> None:
    """The target as each tried rung of the ladder left it, side by side, simplest first: the
    rung, kept or not, and its target SSIM against the truth when the scan carries it."""
    plt = pyplot()
    entries = {e["rung"]: e for e in o.metrics.get("model", {}).get("rungs", [])}
    names = list(o.rung_targets)
    fig, axes = plt.subplots(1, len(names), figsize=(2.6 * len(names), 3.0), squeeze=False)
    for ax, name in zip(axes[0], names):
        kept = "kept" if entries.get(name, {}).get("kept") else "not kept"
        score = "" if o.target_truth is None else f", SSIM {image_ssim(o.rung_targets[name], o.target_truth):.3f}"
        _show(ax, o.rung_targets[name], o.target_grid, f"{name} ({kept}{score})")
    _save(fig, path, dpi=100)


def _ssim_tag(value) -> str:
    return "" if value is None else f"\nSSIM {value:.3f}"
