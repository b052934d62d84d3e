"""nodes.runtime.launch: finding launch files from any folder, shared argument files (``include:``),
and the paper's values in launch/paper.yaml agreeing with twinfocus.simulation.scenario."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from nodes.runtime import launch
from twinfocus.errors import TwinFocusError
from twinfocus.focus.autofocus import AutofocusConfig
from twinfocus.simulation.scenario import PAPER_IMAGE_SIZE, PAPER_ITERATIONS, PAPER_REFERENCE_ROI, PAPER_TARGET_ROI

REPO = Path(__file__).resolve().parent.parent
CLI = [sys.executable, "-c", "import sys; from twinfocus.cli import main; sys.exit(main())"]
# The arguments each bundled file requires (no default).
REQUIRED = {"sim": [], "live": ["template:=t.npz"], "replay": ["log:=run.mcap"]}
SHARED = {
    "reference_roi": list(PAPER_REFERENCE_ROI),
    "target_roi": list(PAPER_TARGET_ROI),
    "size": PAPER_IMAGE_SIZE,
    "iterations": PAPER_ITERATIONS,
}


def test_paper_yaml_holds_the_scenario_values():
    doc = yaml.safe_load((REPO / "launch" / "paper.yaml").read_text())
    assert {k: v["default"] for k, v in doc["arguments"].items()} == SHARED
    # The optimiser's own default iterations are the paper's too.
    assert AutofocusConfig().iterations == PAPER_ITERATIONS


@pytest.mark.parametrize("name", sorted(REQUIRED))
def test_bundled_launch_files_take_the_regions_and_sizes_from_paper_yaml(name):
    own = yaml.safe_load((REPO / "launch" / f"{name}.yaml").read_text())
    assert not set(SHARED) & set(own["arguments"]), "declared again instead of shared"
    graph = launch.load(name, REQUIRED[name])
    assert {k: graph.arguments[k] for k in SHARED} == SHARED
    solver = next(n for n in graph.nodes if n.name == "solver")
    assert {k: solver.parameters[k] for k in SHARED} == SHARED
    # An included argument is overridden on the command line like an own one.
    graph = launch.load(name, [*REQUIRED[name], "size:=40", "target_roi:=[0, 0.1, -0.1, 0.1, 0.5]"])
    solver = next(n for n in graph.nodes if n.name == "solver")
    assert solver.parameters["size"] == 40 and solver.parameters["target_roi"] == [0, 0.1, -0.1, 0.1, 0.5]


def _write(path: Path, doc: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(doc))
    return path


def _graph_doc(**extra) -> dict:
    return {
        **extra,
        "nodes": [
            {"name": "s", "node": "solver", "parameters": {"size": "$(arg size)", "reference_roi": "$(arg roi)"}}
        ],
    }


def test_includes_resolve_relative_to_the_launch_file_not_the_working_folder(tmp_path, monkeypatch):
    _write(
        tmp_path / "conf" / "shared" / "geometry.yaml", {"arguments": {"size": {"default": 64}, "roi": [1, 2, 3, 4, 5]}}
    )
    lf = _write(tmp_path / "conf" / "g.yaml", _graph_doc(include=["shared/geometry.yaml"]))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    graph = launch.load(lf)
    assert graph.nodes[0].parameters == {"size": 64, "reference_roi": [1, 2, 3, 4, 5]}
    # A single file name is accepted as well as a list.
    lf2 = _write(tmp_path / "conf" / "g2.yaml", _graph_doc(include="shared/geometry.yaml"))
    assert launch.load(lf2, ["size:=8"]).nodes[0].parameters["size"] == 8


def test_include_errors_name_the_files(tmp_path):
    _write(tmp_path / "a.yaml", {"arguments": {"size": {"default": 64}}})
    _write(tmp_path / "b.yaml", {"arguments": {"size": {"default": 32}, "roi": {"default": 0}}})
    cases = {
        "missing.yaml": "included file 'missing.yaml' not found",
        "twice": "is also declared in",
        "own": "is also declared in",
        "nodes": "holds only 'description' and an 'arguments' mapping (found nodes)",
    }
    docs = {
        "missing.yaml": _graph_doc(include=["missing.yaml"]),
        "twice": _graph_doc(include=["a.yaml", "b.yaml"]),
        "own": _graph_doc(include=["b.yaml"], arguments={"size": {"default": 1}}),
        "nodes": _graph_doc(include=["bad.yaml"]),
    }
    _write(tmp_path / "bad.yaml", {"arguments": {"size": 1, "roi": 2}, "nodes": []})
    for i, (key, doc) in enumerate(docs.items()):
        lf = _write(tmp_path / f"case{i}.yaml", doc)
        with pytest.raises(TwinFocusError) as err:
            launch.load(lf)
        assert cases[key] in str(err.value), (key, str(err.value))
    with pytest.raises(TwinFocusError, match="'include' must be a file name or a list"):
        launch.load(_write(tmp_path / "num.yaml", _graph_doc(include=3)))


def test_bundled_files_are_found_by_name_from_any_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    want = launch.LAUNCH_DIR / "sim.yaml"
    for name in ("sim", "sim.yaml", "launch/sim.yaml", str(want)):
        assert launch.find_launch_file(name) == want, name
    # A path that names another folder is not silently replaced by the bundled file of that name.
    with pytest.raises(
        TwinFocusError, match=r"nowhere/sim.yaml: no such launch file \(bundled in .*: live, replay, sim\)"
    ):
        launch.find_launch_file("nowhere/sim.yaml")
    # A file in the working folder wins over a bundled one of the same name.
    mine = _write(tmp_path / "sim.yaml", _graph_doc(arguments={"size": 1, "roi": 2}))
    assert launch.find_launch_file("sim.yaml") == mine.resolve()


def test_without_the_bundled_folder_the_error_says_so(tmp_path, monkeypatch):
    monkeypatch.setattr(launch, "LAUNCH_DIR", tmp_path / "not_installed" / "launch")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(TwinFocusError, match="this installation lacks: give a launch file's path"):
        launch.find_launch_file("sim")


@pytest.mark.slow  # 1.4 s x
def test_cli_launch_show_from_another_folder(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    for name in ("launch/sim.yaml", "sim"):
        r = subprocess.run(
            [*CLI, "launch", "--show", name, "size:=40"],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert r.returncode == 0, r.stderr
        assert r.stdout.splitlines()[0].startswith(f"# {REPO / 'launch' / 'sim.yaml'}:")
        assert "reference_roi=[-0.15, 0.0, -0.11, 0.12, 0.6]" in r.stdout and "size=40" in r.stdout
    r = subprocess.run(
        [*CLI, "launch", "--show", "launch/nosuch.yaml"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "no such launch file" in r.stderr
