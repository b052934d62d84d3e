"""Faults a careless or hostile user makes: each refused in one line, exit 2, earlier
results unchanged, nothing written outside the folder the output belongs in."""

import errno
import hashlib
import json

import numpy as np
import pytest

from tests.helpers import REF_ROI, ROIS, TGT_ROI, cli
from twinfocus.cli import main
from twinfocus.errors import TwinFocusError
from twinfocus.io.atomic import WRITTEN, output_folder, output_lock
from twinfocus.io.safe_paths import child_path


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    assert main(["simulate", "--out", str(d / "scan.npz"), "--columns", "2", "--rows", "12", "--quiet"]) == 0
    return d / "scan.npz"


def _focus(scan, out, *extra):
    return cli("focus", scan, *ROIS, "--size 12 --method none --pictures none --out", out, "--quiet", *extra)


def _one_line(capsys, *words):
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    for w in words:
        assert w in err, err
    return err


@pytest.mark.parametrize("name", ["../../x", "/etc/x", "a/b", "..", "", "x\0y"])
def test_a_name_from_data_never_leaves_its_folder(tmp_path, name):
    with pytest.raises(TwinFocusError, match="scan id"):
        child_path(tmp_path, name, what="scan id")


def test_a_symlink_out_of_the_folder_is_refused(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "link").symlink_to(tmp_path)
    assert child_path(tmp_path / "out", "plain", what="scan id") == tmp_path / "out" / "plain"
    with pytest.raises(TwinFocusError, match="symbolic link"):
        child_path(tmp_path / "out", "link/x", what="name", subfolders=True)


def test_focus_again_into_its_out_is_refused_and_overwrite_keeps_the_users_files(scan, tmp_path, capsys):
    out = tmp_path / "f"
    assert _focus(scan, out) == 0
    before = _sha(out / "target.npy")
    capsys.readouterr()
    assert _focus(scan, out, "--iterations", "1") == 2
    _one_line(capsys, "--out", "already exists", "--overwrite")
    assert _sha(out / "target.npy") == before
    (out / "mine.png").write_bytes(b"user")
    assert _focus(scan, out, "--overwrite") == 0
    assert (out / "mine.png").read_bytes() == b"user"  # never written by a run: kept
    assert "mine.png" not in (out / WRITTEN).read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]  # no temporary or lock file left


def test_a_second_run_on_a_locked_out_refuses(scan, tmp_path, capsys):
    out = tmp_path / "f"
    with output_lock(out):
        assert _focus(scan, out) == 2
    _one_line(capsys, "another twinfocus run")
    assert not out.exists()


@pytest.mark.parametrize(
    "option,value", [("--iterations", "-1"), ("--lr", "nan"), ("--size", "inf"), ("--tracking-error-mm", "-3")]
)
def test_bad_numbers_are_one_line(scan, tmp_path, capsys, option, value):
    with pytest.raises(SystemExit) as exc:
        _focus(scan, tmp_path / "f", option, value)
    assert exc.value.code == 2
    _one_line(capsys, option, repr(value))
    assert not (tmp_path / "f").exists()


@pytest.mark.parametrize(
    "option,value",
    [("--height", "1e308"), ("--target-height", "1e6"), ("--distance", "1e9"), ("--rows", "abc"), ("--snr-db", "nan")],
)
def test_simulate_refuses_absurd_numbers(tmp_path, capsys, option, value):
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--out", str(tmp_path / "s.npz"), option, value])
    assert exc.value.code == 2
    _one_line(capsys, option)
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_is_one_line_and_keeps_the_earlier_result(scan, tmp_path, capsys, monkeypatch):
    out = tmp_path / "f"
    assert _focus(scan, out) == 0
    before = _sha(out / "metrics.json")
    import twinfocus.focus.pipeline as pipeline

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pipeline.np, "save", full)
    capsys.readouterr()
    assert _focus(scan, out, "--overwrite") == 2
    _one_line(capsys, "no space left")
    assert _sha(out / "metrics.json") == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]


def test_simulate_refuses_an_existing_out(scan, tmp_path, capsys):
    before = _sha(scan)
    assert main(["simulate", "--out", str(scan), "--columns", "1", "--rows", "2", "--quiet"]) == 2
    _one_line(capsys, "already exists")
    assert _sha(scan) == before


def test_a_failed_publish_leaves_the_earlier_folder(tmp_path):
    out = tmp_path / "o"
    with output_folder(out, False) as d:
        (d / "a.txt").write_text("1")
    with pytest.raises(RuntimeError), output_folder(out, True) as d:
        (d / "a.txt").write_text("2")
        raise RuntimeError
    assert (out / "a.txt").read_text() == "1"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o"]


def test_batch_save_template_stays_inside_out(tmp_path, scan):
    from twinfocus.cli.batch_jobs import read_manifest

    m = tmp_path / "m.yaml"
    m.write_text(
        f"- scan: {scan}\n  method: none\n  reference_roi: {' '.join(REF_ROI)}\n  target_roi: {' '.join(TGT_ROI)}\n"
        "  save_template: ../../t.npz\n"
    )
    with pytest.raises(TwinFocusError, match="save_template"):
        read_manifest(m, tmp_path / "out")
    m.write_text(m.read_text().replace("../../t.npz", "templates/t.npz"))
    (item,) = read_manifest(m, tmp_path / "out")
    assert str((tmp_path / "out" / "templates" / "t.npz").resolve()) in item.argv


@pytest.mark.slow  # 3.7 s CPU (2 cores, load ~9): out of make test-fast
def test_a_cloud_with_nan_points_is_dropped_in_one_line_and_counted(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("TWINFOCUS_CACHE_DIR", str(tmp_path / "cache"))
    d = tmp_path / "sim"
    assert (
        cli("simulate --out", d / "scan.npz", "--reference-cloud-out", d / "cloud.npy", "--columns 2 --rows 12 --quiet")
        == 0
    )
    cloud = np.load(d / "cloud.npy")
    cloud[::10] = np.nan  # as a stereo camera writes the points it could not match
    np.save(d / "cloud_nan.npy", cloud)
    capsys.readouterr()
    out = tmp_path / "out"
    twin = ("--digital-twin", d / "cloud_nan.npy")
    assert cli("focus", d / "scan.npz", *twin, *ROIS, "--size 12 --pictures none --out", out, "--quiet") == 0
    warned = [ln for ln in capsys.readouterr().err.splitlines() if "warning" in ln and "NaN" in ln]
    dropped = len(cloud[::10])
    assert warned == [
        f"twinfocus focus: warning: reference point cloud: dropped {dropped} of {len(cloud)} rows holding NaN or inf"
    ]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["digital_twin"]["non_finite_rows"] == dropped
