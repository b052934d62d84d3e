"""The template cache: a reference is paid for once, its cached image equals the recomputed one,
and any change of input, grid or back-projection option misses it."""

import numpy as np
import pytest

from tests.helpers import REF_ROI, ROIS, cli, metrics, simulate
from twinfocus.imaging.grid import ImageGrid
from twinfocus.io.checksums import file_sha256
from twinfocus.radar.scan import Scan
from twinfocus.twins import cache as cache_module
from twinfocus.twins.cache import TemplateCache, cache_dir, remembered_sha256, template_key
from twinfocus.twins.templates import load_template, template_from_scan


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    return simulate(tmp_path_factory.mktemp("sim"), "--columns 2 --rows 30 --seed 5")


def _focus(scan, out, *extra, size=40):
    assert cli("focus", scan, *ROIS, "--size", size, "--out", out, "--quiet --pictures none", *extra) == 0
    return metrics(out)


@pytest.mark.slow  # 12 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_second_focus_reads_the_template_from_the_cache(scans, tmp_path, monkeypatch):
    monkeypatch.setenv("TWINFOCUS_CACHE_DIR", str(tmp_path / "cache"))
    tpl = ["--template-scan", str(scans / "tpl.npz")]
    first = _focus(scans / "scan.npz", tmp_path / "a", *tpl)

    # a hit costs a file hash and a small read, not a back-projection
    def no_back_projection(*args, **kwargs):
        raise AssertionError("a cache hit must not form the template scan's image")

    with monkeypatch.context() as m:
        m.setattr("twinfocus.twins.templates.template_from_scan", no_back_projection)
        second = _focus(scans / "scan.npz", tmp_path / "b", *tpl)
    assert (first["template_cache"], second["template_cache"]) == ("miss", "hit")
    # the same result bit for bit, and the cached image is the recomputed one exactly
    for name in ("phase.npy", "target.npy"):
        assert np.array_equal(np.load(tmp_path / "a" / name), np.load(tmp_path / "b" / name)), name
    grid = ImageGrid.from_roi([float(v) for v in REF_ROI], 40)
    fresh = template_from_scan(Scan.load(scans / "tpl.npz"), grid, keep_phase=True, oversample=16, precision="float32")
    (entry,) = (tmp_path / "cache" / "templates").glob("*.npz")
    cached = np.load(entry)["image"]
    assert cached.dtype == fresh.dtype and np.array_equal(cached, fresh)
    # --no-cache neither reads nor writes
    off = _focus(scans / "scan.npz", tmp_path / "c", *tpl, "--no-cache")
    assert off["template_cache"] == "off"
    assert len(list((tmp_path / "cache" / "templates").glob("*.npz"))) == 1


@pytest.mark.slow  # 9 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_changed_inputs_miss_the_cache(scans, tmp_path, monkeypatch):
    monkeypatch.setenv("TWINFOCUS_CACHE_DIR", str(tmp_path / "cache"))
    tpl = ["--template-scan", str(scans / "tpl.npz")]
    assert _focus(scans / "scan.npz", tmp_path / "a", *tpl)["template_cache"] == "miss"
    # the same reference scan with one sample changed: another file hash
    s = Scan.load(scans / "tpl.npz")
    data = s.data.copy()
    data[0, 0, 0] += 1.0
    s.with_data(data).save(tmp_path / "tpl2.npz")
    assert (
        _focus(scans / "scan.npz", tmp_path / "b", "--template-scan", str(tmp_path / "tpl2.npz"))["template_cache"]
        == "miss"
    )
    # another back-projection option, then another grid
    assert _focus(scans / "scan.npz", tmp_path / "c", *tpl, "--oversample", "8")["template_cache"] == "miss"
    assert _focus(scans / "scan.npz", tmp_path / "d", *tpl, size=41)["template_cache"] == "miss"
    assert len(list((tmp_path / "cache" / "templates").glob("*.npz"))) == 4
    assert _focus(scans / "scan.npz", tmp_path / "e", *tpl)["template_cache"] == "hit"


@pytest.mark.slow  # 4 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_save_template_is_what_template_takes(scans, tmp_path):
    """``--save-template`` writes the template file that ``--template`` reads back: the same
    phase to the file format's float32 amplitude/phase round-off."""
    tpl = ["--template-scan", str(scans / "tpl.npz")]
    a = _focus(scans / "scan.npz", tmp_path / "a", *tpl, "--save-template", str(tmp_path / "ref_template.npz"))
    b = _focus(scans / "scan.npz", tmp_path / "b", "--template", str(tmp_path / "ref_template.npz"))
    assert a["estimator"] == b["estimator"]
    grid = ImageGrid.from_roi([float(v) for v in REF_ROI], 40)
    fresh = template_from_scan(Scan.load(scans / "tpl.npz"), grid, keep_phase=True)
    saved = load_template(tmp_path / "ref_template.npz", grid)
    assert np.abs(saved - fresh).max() < 1e-5 * np.abs(fresh).max()
    pa, pb = np.load(tmp_path / "a" / "phase.npy"), np.load(tmp_path / "b" / "phase.npy")
    assert np.abs(np.angle(np.exp(1j * (pa - pb)))).max() < 1e-3


def test_cache_location_and_soft_failures(tmp_path, monkeypatch):
    monkeypatch.delenv("TWINFOCUS_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "xdg" / "twinfocus"
    monkeypatch.setenv("TWINFOCUS_CACHE_DIR", str(tmp_path / "mine"))
    assert cache_dir() == tmp_path / "mine"
    grid = ImageGrid(-0.01, 0.01, -0.01, 0.01, 0.5, 4, 5)
    key = template_key("template_scan", {"file_sha256": "0" * 64}, grid, {"oversample": 16})
    assert key != template_key("template_scan", {"file_sha256": "1" + "0" * 63}, grid, {"oversample": 16})
    # the torch device does not change the image, so it is not part of the key
    assert key == template_key("template_scan", {"file_sha256": "0" * 64}, grid, {"oversample": 16, "device": "cuda"})
    cache = TemplateCache()
    image = (np.arange(20).reshape(4, 5) + 1j).astype(np.complex64)
    cache.put(key, image, grid)
    assert np.array_equal(cache.get(key, grid), image)
    assert cache.get(key, ImageGrid(-0.01, 0.01, -0.01, 0.01, 0.5, 5, 4)) is None  # another grid's shape
    cache.path(key).write_bytes(b"damaged")
    assert cache.get(key, grid) is None  # a damaged entry is a miss, not an error
    (tmp_path / "file").write_text("x")
    blocked = TemplateCache(tmp_path / "file" / "cache")
    assert blocked.put(key, image, grid) is None and "could not write" in blocked.warning
    assert TemplateCache(enabled=False).get(key, grid) is None
    assert len(file_sha256(tmp_path / "file")) == 64


def test_an_entry_keeps_its_info_and_one_stored_without_it_is_recomputed(tmp_path):
    """A digital twin's entry carries what its conditioning chose (metrics.json); an entry stored
    before it did is recomputed when the info is asked for, not returned without it."""
    grid = ImageGrid(-0.01, 0.01, -0.01, 0.01, 0.5, 4, 5)
    cache = TemplateCache(tmp_path)
    image = np.arange(20, dtype=np.float32).reshape(4, 5)
    cache.put("old", image, grid)
    calls = []

    def compute():
        calls.append(1)
        return image + 1, {"surface": "smooth", "curved": True, "curvature_m": np.float64(6e-3)}

    got, info, status = cache.get_or_compute("old", grid, compute, with_info=True)
    assert status == "miss" and calls == [1] and np.array_equal(got, image + 1)
    got, info, status = cache.get_or_compute("old", grid, compute, with_info=True)
    assert status == "hit" and calls == [1] and np.array_equal(got, image + 1)
    assert info == {"surface": "smooth", "curved": True, "curvature_m": 6e-3}
    got, status = cache.get_or_compute("old", grid, lambda: None)
    assert status == "hit" and np.array_equal(got, image + 1)
    got, info, status = TemplateCache(enabled=False).get_or_compute("k", grid, compute, with_info=True)
    assert status == "off" and info["curved"] and calls == [1, 1]


@pytest.mark.slow  # 36 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_digital_twin_template_is_cached_per_cloud_and_aperture(scans, tmp_path, monkeypatch):
    """A digital twin's template depends on the cloud and on the scan's aperture: the same pair
    hits, another scan (other tracked positions) misses."""
    from twinfocus.simulation.scenario import Scenario

    monkeypatch.setenv("TWINFOCUS_CACHE_DIR", str(tmp_path / "cache"))
    pts, _ = Scenario().scene().scatterers(2e-3, 1, speckle=False)
    np.save(tmp_path / "cloud.npy", pts[pts[:, 0] < 0.0])
    twin = ["--digital-twin", str(tmp_path / "cloud.npy")]
    first, second = _focus(scans / "scan.npz", tmp_path / "a", *twin), _focus(scans / "scan.npz", tmp_path / "b", *twin)
    assert (first["template_cache"], second["template_cache"]) == ("miss", "hit")
    # what the conditioning chose and why, in metrics.json, from the cache too
    assert first["digital_twin"] == second["digital_twin"] and first["digital_twin"]["surface_reason"]
    assert np.array_equal(np.load(tmp_path / "a" / "phase.npy"), np.load(tmp_path / "b" / "phase.npy"))
    s = Scan.load(scans / "scan.npz")
    moved = Scan(s.data, s.positions + 1e-4, s.chirp, positions_true=s.positions_true)
    moved.save(tmp_path / "moved.npz")
    assert _focus(tmp_path / "moved.npz", tmp_path / "c", *twin)["template_cache"] == "miss"


def test_a_files_digest_is_remembered_until_the_file_changes(tmp_path, monkeypatch):
    """The template scan's digest is read from the memo while the file is as it was, and computed
    anew (the right one, against hashlib on its bytes) once it is rewritten, even at the same size
    and modification time; a file changed just now is not remembered."""
    import hashlib
    import os
    import time

    calls = []

    def counted(path):
        calls.append(path)
        return file_sha256(path)

    monkeypatch.setattr(cache_module, "file_sha256", counted)
    f = tmp_path / "stage.npz"
    f.write_bytes(b"a" * 1000)
    assert remembered_sha256(f, tmp_path / "c") == hashlib.sha256(b"a" * 1000).hexdigest()
    assert remembered_sha256(f, tmp_path / "c") and len(calls) == 2  # just written: not remembered
    monkeypatch.setattr(cache_module, "RACY_S", 0.0)
    remembered_sha256(f, tmp_path / "c")
    assert remembered_sha256(f, tmp_path / "c") == hashlib.sha256(b"a" * 1000).hexdigest() and len(calls) == 3
    mtime = f.stat().st_mtime_ns
    time.sleep(0.05)  # past the file system's clock tick
    f.write_bytes(b"b" * 1000)
    os.utime(f, ns=(mtime, mtime))  # same size, same modification time: only the change time moved
    assert remembered_sha256(f, tmp_path / "c") == hashlib.sha256(b"b" * 1000).hexdigest() and len(calls) == 4
    # a memo folder that cannot be written: the digest all the same
    (tmp_path / "file").write_text("x")
    assert remembered_sha256(f, tmp_path / "file" / "c") == hashlib.sha256(b"b" * 1000).hexdigest()
