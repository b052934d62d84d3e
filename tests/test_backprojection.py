import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.imaging.backprojection.numba_backend import (
    backproject,
    backproject_points,
    matched_filter_bruteforce,
    subimage_basis,
)
from twinfocus.imaging.grid import ImageGrid
from twinfocus.radar.fmcw import C_M_PER_S, Chirp, mmwcas_virtual_array, uniform_virtual_array


def point_scan(chirp, positions, point, amplitude=1.0):
    """Data of one scatterer under the project's IF model (written out independently)."""
    r = np.linalg.norm(positions - np.asarray(point), axis=-1)
    return (amplitude * np.exp(1j * 2 * np.pi * chirp.frequencies_hz * 2 * r[..., None] / C_M_PER_S)).astype(
        np.complex64
    )


def small_aperture(n_rows=24, row_pitch=0.004, columns=(0.0,)):
    va = mmwcas_virtual_array()
    pos = []
    for cx in columns:
        for y in (np.arange(n_rows) - (n_rows - 1) / 2) * row_pitch:
            pos.append(va.offsets_m + np.array([cx, y, 0.0]))
    return np.array(pos)


@pytest.mark.parametrize(
    "backend",
    # torch: 2.4 s (2 cores, idle): out of make test-fast (benchmarks/results/test_fast.json); numba stays
    ["numba", pytest.param("torch", marks=pytest.mark.slow)],
)
def test_point_focuses_and_matches_bruteforce(backend):
    ch = Chirp()
    pos = small_aperture()
    point = np.array([0.012, -0.004, 0.6])
    data = point_scan(ch, pos, point)
    grid = ImageGrid(-0.01, 0.03, -0.02, 0.02, 0.6, 11, 9)
    img = backproject(data, pos, ch, grid, backend=backend)
    ref = matched_filter_bruteforce(data, pos, ch, grid.points()).reshape(grid.shape)
    # stated tolerance: linear interpolation of 16x oversampled profiles, < 0.3 % of the peak
    assert np.abs(img - ref).max() / np.abs(ref).max() < 3e-3
    i, j = np.unravel_index(np.argmax(np.abs(img)), img.shape)
    assert abs(grid.x_m[j] - point[0]) <= grid.spacing_m[1] / 2 + 1e-9
    assert abs(grid.y_m[i] - point[1]) <= grid.spacing_m[0] / 2 + 1e-9


def test_numba_and_torch_agree_and_basis_sums_to_image():
    ch = Chirp()
    pos = small_aperture(n_rows=10)
    rng = np.random.default_rng(3)
    data = (
        rng.standard_normal((*pos.shape[:2], ch.n_samples)) + 1j * rng.standard_normal((*pos.shape[:2], ch.n_samples))
    ).astype(np.complex64)
    grid = ImageGrid(-0.05, 0.05, -0.05, 0.05, 0.5, 16, 16)
    a = backproject(data, pos, ch, grid)
    b = backproject(data, pos, ch, grid, backend="torch")
    basis = subimage_basis(data, pos, ch, grid)
    assert basis.shape == (pos.shape[0], 16, 16)
    scale = np.abs(a).max()
    assert np.abs(a - b).max() / scale < 1e-4
    assert np.abs(basis.sum(0) - a).max() / scale < 1e-4


def _half_power_width(x, amp):
    a = amp / amp.max()
    above = np.flatnonzero(a >= np.sqrt(0.5))
    lo, hi = above[0], above[-1]
    # linear interpolation of the -3 dB crossings
    xl = np.interp(np.sqrt(0.5), [a[lo - 1], a[lo]], [x[lo - 1], x[lo]])
    xr = np.interp(np.sqrt(0.5), [a[hi + 1], a[hi]], [x[hi + 1], x[hi]])
    return xr - xl


@pytest.mark.slow  # 5 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_resolution_matches_theory():
    """Half-power widths of a uniform aperture: 0.886 lambda R / (2 D) across, 0.886 c / (2 B) in range."""
    ch = Chirp()
    va = uniform_virtual_array(201, ch.wavelength_m / 4)
    pos = va.offsets_m[None]  # one position, a 0.2 m line along x
    d = np.ptp(va.offsets_m[:, 0]) + ch.wavelength_m / 4
    r0 = 0.5
    data = point_scan(ch, pos, [0.0, 0.0, r0])
    xs = np.linspace(-0.01, 0.01, 401)
    line = np.stack([xs, np.zeros_like(xs), np.full_like(xs, r0)], 1)
    cross = np.abs(backproject_points(data, pos, ch, line, precision="float64"))
    expected = 0.886 * ch.wavelength_m * r0 / (2 * d)
    assert _half_power_width(xs, cross) == pytest.approx(expected, rel=0.05)
    # range: one channel alone (no aperture focusing in depth), pure range compression
    one = pos[:, 100:101]
    zs = np.linspace(r0 - 0.05, r0 + 0.05, 401)
    depth = np.stack([np.zeros_like(zs), np.zeros_like(zs), zs], 1)
    along = np.abs(backproject_points(data[:, 100:101], one, ch, depth, precision="float64"))
    assert _half_power_width(zs, along) == pytest.approx(0.886 * ch.range_resolution_m, rel=0.05)


def test_float32_is_exact_enough_at_long_range():
    ch = Chirp()
    pos = small_aperture(n_rows=8, row_pitch=0.01) + np.array([100.0, -50.0, 0.0])  # far from the origin too
    point = np.array([100.01, -50.0, 5.0])
    data = point_scan(ch, pos, point)
    grid = ImageGrid(99.98, 100.04, -50.03, -49.97, 5.0, 13, 13)
    f32 = backproject(data, pos, ch, grid, precision="float32")
    f64 = backproject(data, pos, ch, grid, precision="float64")
    assert np.isfinite(f32).all()
    assert np.abs(f32 - f64).max() / np.abs(f64).max() < 1e-3
    ref = matched_filter_bruteforce(data, pos, ch, grid.points()).reshape(grid.shape)
    assert np.abs(f64 - ref).max() / np.abs(ref).max() < 3e-3


@pytest.mark.parametrize("size", [8, 512])
def test_extreme_image_sizes(size):
    ch = Chirp()
    pos = small_aperture(n_rows=5, row_pitch=0.002)
    data = point_scan(ch, pos, [0.0, 0.0, 0.6])
    grid = ImageGrid(-0.1, 0.1, -0.1, 0.1, 0.6, size, size)
    img = backproject(data, pos, ch, grid)
    assert img.shape == (size, size) and np.isfinite(img).all()
    i, j = np.unravel_index(np.argmax(np.abs(img)), img.shape)
    assert abs(grid.x_m[j]) <= 0.2 / (size - 1) and abs(grid.y_m[i]) <= 0.2 / (size - 1)


def test_bad_inputs_are_named():
    ch = Chirp()
    pos = small_aperture(n_rows=2)
    data = point_scan(ch, pos, [0.0, 0.0, 0.6])
    grid = ImageGrid(-0.1, 0.1, -0.1, 0.1, 0.6, 4, 4)
    with pytest.raises(TwinFocusError, match="positions must be"):
        backproject(data, pos[:, :3], ch, grid)
    bad = pos.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(TwinFocusError, match="NaN"):
        backproject(data, bad, ch, grid)
    with pytest.raises(TwinFocusError, match="backend"):
        backproject(data, pos, ch, grid, backend="fortran")
    with pytest.raises(TwinFocusError, match="precision"):
        backproject(data, pos, ch, grid, precision="float16")
    with pytest.raises(TwinFocusError, match="complex"):
        backproject(data.real, pos, ch, grid)
    with pytest.raises(TwinFocusError, match="X0 < X1"):
        ImageGrid(0.1, -0.1, -0.1, 0.1, 0.6, 4, 4)


def test_volume_backprojection_finds_the_point_in_depth():
    from twinfocus.imaging.grid import VolumeGrid

    ch = Chirp()
    pos = small_aperture(n_rows=12, row_pitch=0.004)
    point = np.array([0.0, 0.0, 0.62])
    data = point_scan(ch, pos, point)
    vol = VolumeGrid(ImageGrid(-0.02, 0.02, -0.02, 0.02, 0.6, 9, 9), 0.55, 0.69, 15)
    img = backproject(data, pos, ch, vol)
    assert img.shape == (15, 9, 9)
    d, i, j = np.unravel_index(np.argmax(np.abs(img)), img.shape)
    assert abs(vol.z_m[d] - point[2]) <= 0.005 + 1e-9
    assert (i, j) == (4, 4)


@pytest.mark.gpu
def test_cuda_backend_matches_cpu():
    ch = Chirp()
    pos = small_aperture(n_rows=6)
    data = point_scan(ch, pos, [0.01, 0.0, 0.6])
    grid = ImageGrid(-0.03, 0.03, -0.03, 0.03, 0.6, 16, 16)
    cpu = backproject(data, pos, ch, grid)
    gpu = backproject(data, pos, ch, grid, backend="torch", device="cuda")
    assert np.abs(cpu - gpu).max() / np.abs(cpu).max() < 1e-4


@pytest.mark.slow  # 22 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_the_kernels_run_on_openmp_without_a_warning_beside_open3d():
    """open3d (the digital twin's clouds) loads its own TBB, older than numba accepts: numba, whose
    first choice is TBB, then warned on every digital-twin run before falling back to OpenMP.
    twinfocus puts OpenMP first, so a kernel runs there and nothing is printed."""
    import os
    import subprocess
    import sys

    pytest.importorskip("open3d")
    code = (
        "import twinfocus, open3d, numba, numpy as np\n"
        "from twinfocus.imaging.backprojection.numba_backend import subimage_basis\n"
        "from twinfocus.imaging.grid import ImageGrid\n"
        "from twinfocus.radar.fmcw import Chirp\n"
        "pos = np.zeros((2, 2, 3)); pos[:, 1, 0] = 1e-3\n"
        "subimage_basis(np.ones((2, 2, 8), np.complex64), pos, Chirp(n_samples=8),"
        " ImageGrid(-0.01, 0.01, -0.01, 0.01, 0.3, 4, 4))\n"
        "print(numba.threading_layer())\n"
    )
    r = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=300,
        env={k: v for k, v in os.environ.items() if not k.startswith("NUMBA_THREADING")},
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[-1] == "omp" and "TBB" not in r.stderr, (r.stdout, r.stderr)
