"""twinfocus.focus.settings: one table of the focus settings makes the ``focus`` options, the solver's
parameters and AutofocusConfig's defaults; one function decides the device."""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import pytest

from nodes.runtime import launch
from nodes.runtime.params import resolve
from nodes.runtime.testing import local_broker
from nodes.solver import Solver
from twinfocus.cli import focus
from twinfocus.errors import TwinFocusError
from twinfocus.focus.autofocus import AutofocusConfig
from twinfocus.focus.settings import FOCUS_SETTINGS, default_settings
from twinfocus.imaging.device import resolve_device
from twinfocus.option_types import CHECKS, finite_float
from twinfocus.radar.fmcw import Chirp

REF_ROI = [-0.15, 0.0, -0.11, 0.12, 0.6]
TGT_ROI = [0.02, 0.13, -0.11, 0.12, 0.6]
REQUIRED_FOCUS = [
    "scan.npz",
    "--reference-roi",
    *map(str, REF_ROI),
    "--target-roi",
    *map(str, TGT_ROI),
    "--template",
    "t.npz",
    "--out",
    "out",
]


def _focus_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    focus.add_arguments(p)
    return p


def test_every_setting_is_a_focus_option_and_a_solver_parameter_with_the_same_default():
    actions = {a.dest: a for a in _focus_parser()._actions}
    for s in FOCUS_SETTINGS:
        a = actions[s.name]
        assert (
            a.option_strings == [s.option]
            and a.default == s.default
            and a.type in (s.type, CHECKS.get(s.check or ""), finite_float)
        ), s.name
        assert a.choices == s.choices and a.help, s.name
        p = Solver.PARAMS[s.name]
        assert p.default == s.default and p.choices == s.choices and p.kind == s.type.__name__ and p.help, s.name
    # the options users and docs already spell keep their spelling
    for option in (
        "--size",
        "--iterations",
        "--lr",
        "--lr-min",
        "--threshold-centre",
        "--threshold-steepness",
        "--loss-steepness",
        "--precision",
        "--basis-dtype",
        "--device",
        "--oversample",
        "--estimator",
        "--projection-iterations",
        "--projection-restarts",
        "--coarse-iterations",
        "--phase-ramp",
        "--space-variant",
        "--tracking-error-mm",
    ):
        assert any(option in a.option_strings for a in actions.values()), option


def test_help_names_other_settings_as_each_entry_point_spells_them():
    helps = {a.dest: a.help for a in _focus_parser()._actions}
    assert "--estimator projection also" in helps["projection_restarts"]
    assert helps["tracking_error_mm"].endswith("(default 0.5 mm)")
    assert helps["device"].endswith("(default cuda if present, else cpu)")
    assert Solver.PARAMS["projection_restarts"].help.startswith("estimator projection also")
    assert not any("{" in helps[s.name] or "{" in Solver.PARAMS[s.name].help for s in FOCUS_SETTINGS)


def test_autofocus_config_defaults_are_the_tables():
    fields = {f.name: f.default for f in dataclasses.fields(AutofocusConfig)}
    mapped = [s for s in FOCUS_SETTINGS if s.config]
    assert {s.config for s in mapped} <= set(fields)
    for s in mapped:
        if s.config != "device":  # a config's device is a decided one; the setting's None is "decide"
            assert fields[s.config] == s.default, s.name


def test_focus_with_no_options_gives_the_tables_config():
    args = _focus_parser().parse_args(REQUIRED_FOCUS)
    assert {s.name: getattr(args, s.name) for s in FOCUS_SETTINGS} == default_settings()
    cfg = AutofocusConfig.from_settings(vars(args))
    want = AutofocusConfig(device=resolve_device(None))
    assert cfg == want
    for s in FOCUS_SETTINGS:
        if s.config and s.config != "device":
            assert getattr(cfg, s.config) == s.default, s.name
    # and a given option reaches the config
    args = _focus_parser().parse_args([*REQUIRED_FOCUS, "--projection-restarts", "2", "--basis-dtype", "float16"])
    cfg = AutofocusConfig.from_settings(vars(args))
    assert (cfg.projection_restarts, cfg.basis_dtype) == (2, "float16")


LAUNCH = """
nodes:
  - name: solver
    node: solver
    parameters:
      reference_roi: {ref}
      target_roi: {tgt}
      size: 8
      warm_up: false
      lr: 0.01
      projection_iterations: 12
      projection_restarts: 1
      coarse_iterations: 5
      basis_dtype: float16
      loss_steepness: 3
      space_variant: "off"
      phase_ramp: keep
      estimator: auto
      tracking_error_mm: 2.0
"""


def test_solver_settings_from_a_launch_file_reach_its_config(tmp_path):
    path = tmp_path / "graph.yaml"
    path.write_text(LAUNCH.format(ref=REF_ROI, tgt=TGT_ROI))
    spec = launch.load(path).nodes[0]
    with local_broker() as ep:
        solver = Solver(broker=ep, params=spec.parameters)
    cfg = solver.cfg
    assert (cfg.lr, cfg.projection_iterations, cfg.projection_restarts, cfg.coarse_iterations, cfg.basis_dtype) == (
        0.01,
        12,
        1,
        5,
        "float16",
    )
    assert (solver.params["space_variant"], solver.params["phase_ramp"]) == ("off", "keep")
    assert solver.ref_grid.shape == (8, 8)
    # 2 mm of tracking error is past lambda/4 at 77 GHz: auto takes projection-refined, and the
    # explicit loss steepness wins over the estimator's 5
    solver.template = np.ones((8, 8), np.float32)
    per_scan = solver._config(Chirp())
    assert (per_scan.init, per_scan.iterations, per_scan.loss_steepness) == ("projection", 300, 3.0)


def test_solver_refuses_the_old_metres_parameter_and_bad_choices():
    base = {"reference_roi": REF_ROI, "target_roi": TGT_ROI}
    with pytest.raises(TwinFocusError, match="'tracking_error_m' was renamed: use tracking_error_mm"):
        resolve("solver", Solver.PARAMS, {**base, "tracking_error_m": 5e-4}, renamed=Solver.RENAMED_PARAMS)
    with pytest.raises(TwinFocusError, match="'phase_ramp' must be one of auto, remove, keep"):
        resolve("solver", Solver.PARAMS, {**base, "phase_ramp": "drop"})
    # null is "unset", as leaving it out
    assert resolve("solver", Solver.PARAMS, {**base, "loss_steepness": None, "device": None})["loss_steepness"] is None


@pytest.mark.parametrize("name,required", [("sim", []), ("live", ["template:=t.npz"]), ("replay", ["log:=run.mcap"])])
def test_bundled_launch_files_set_only_known_solver_parameters(name, required):
    solver = next(n for n in launch.load(name, required).nodes if n.name == "solver")
    resolve("solver", Solver.PARAMS, solver.parameters, renamed=Solver.RENAMED_PARAMS)


def test_device_resolver(monkeypatch):
    torch = pytest.importorskip("torch")
    assert resolve_device("cpu") == "cpu"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device(None) == "cpu" and resolve_device("") == "cpu"
    for asked in ("cuda", "cuda:0"):
        with pytest.raises(TwinFocusError, match=f"device '{asked}': no CUDA device is available"):
            resolve_device(asked)
    with pytest.raises(TwinFocusError, match="device 'gpu': not a torch device"):
        resolve_device("gpu")
    # the three users: focus, the solver, the torch back-projection
    with pytest.raises(TwinFocusError, match="no CUDA device"):
        AutofocusConfig.from_settings({**default_settings(), "device": "cuda"})
    with local_broker() as ep, pytest.raises(TwinFocusError, match="no CUDA device"):
        Solver(broker=ep, params={"reference_roi": REF_ROI, "target_roi": TGT_ROI, "device": "cuda", "warm_up": False})
    from twinfocus.imaging.backprojection.torch_backend import backproject_points_torch

    with pytest.raises(TwinFocusError, match="no CUDA device"):
        backproject_points_torch(
            np.zeros((1, 1, 8), np.complex64), np.zeros((1, 1, 3)), Chirp(n_samples=8), np.zeros((1, 3)), device="cuda"
        )


def test_unset_device_takes_cuda_only_when_present(monkeypatch):
    torch = pytest.importorskip("torch")
    monkeypatch.setattr("twinfocus.imaging.device._accelerator_present", lambda: True)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device(None) == "cuda"
    monkeypatch.setattr("twinfocus.imaging.device._accelerator_present", lambda: False)
    assert resolve_device(None) == "cpu"  # no GPU device node: cpu without asking torch
