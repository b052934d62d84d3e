"""Heavy libraries load only on the paths that use them, and the torch-free replacements equal
what they replace: numpy SSIM vs the torch SSIM the optimiser differentiates, the Pillow summary's
colour map vs matplotlib's."""

import subprocess
import sys

import numpy as np
import pytest

HEAVY = ("torch", "matplotlib", "open3d", "scipy.ndimage")


def _loaded_after(imports: str) -> list[str]:
    code = f"import sys; {imports}; print(','.join(m for m in {HEAVY!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    return [m for m in out.split(",") if m]


def test_focus_command_and_numerics_import_no_heavy_library():
    assert (
        _loaded_after(
            "import twinfocus.cli.focus, twinfocus.imaging.backprojection.numba_backend, twinfocus.twins.templates, "
            "twinfocus.twins.cache, twinfocus.outputs.plotting, twinfocus.imaging.metrics, twinfocus.radar.scan, "
            "twinfocus.focus.estimators"
        )
        == []
    )


def test_pipeline_imports_no_torch():
    assert _loaded_after("import twinfocus.focus.pipeline") == []


def test_numpy_ssim_equals_torch_ssim():
    torch = pytest.importorskip("torch")
    from twinfocus.imaging.metrics import ssim, ssim_torch

    rng = np.random.default_rng(0)
    for shape in ((40, 37), (9, 12)):
        a, b = rng.random(shape), rng.random(shape)
        b = 0.6 * a + 0.4 * b
        want = float(ssim_torch(torch.from_numpy(a), torch.from_numpy(b)))
        assert abs(ssim(a, b) - want) < 1e-12


def test_summary_colour_map_is_matplotlibs_inferno():
    matplotlib = pytest.importorskip("matplotlib")
    from twinfocus.outputs.plotting import inferno

    t = np.linspace(0, 1, 256)
    assert np.abs(inferno(t) - matplotlib.colormaps["inferno"](t)[:, :3]).max() < 0.034


def test_summary_png_shows_each_image_where_it_is(tmp_path):
    """A bright pixel of each panel's image lands inside that panel of the PNG."""
    from PIL import Image

    from twinfocus.imaging.grid import ImageGrid
    from twinfocus.outputs.plotting import write_summary_png

    grid = ImageGrid(-0.05, 0.05, -0.05, 0.05, 0.6, 30, 30)
    panels = []
    for n in range(5):
        img = np.zeros(grid.shape)
        img[3 + 5 * n, 3 + 5 * n] = 1.0
        panels.append((img, grid, f"panel {n}"))
    write_summary_png(tmp_path / "s.png", panels, panel_px=90)
    rgb = np.asarray(Image.open(tmp_path / "s.png").convert("RGB")).astype(int)
    cols, cell_w = 3, 90 + 24
    cell_h = rgb.shape[0] // 2
    for n in range(5):
        cell = rgb[(n // cols) * cell_h : (n // cols + 1) * cell_h, (n % cols) * cell_w : (n % cols + 1) * cell_w]
        # inferno's top is pale yellow: R and G high; the background of the image is near black
        bright = np.argwhere((cell[..., 0] > 200) & (cell[..., 1] > 150) & (cell[..., 2] < 200))
        assert bright.size, n
        y, x = bright.mean(axis=0)
        assert abs(x - 12 - (3 + 5 * n + 0.5) * 3) < 6 and abs(y - 40 - (3 + 5 * n + 0.5) * 3) < 6, (n, x, y)
