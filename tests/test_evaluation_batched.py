"""The evaluation's batched paper optimiser: each estimate of a batch is the single run's
(``twin_autofocus``), a bad template fails alone, and a tiny experiment gives the same SSIM per
record with and without the batch."""

from __future__ import annotations

import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.evaluation import runner
from twinfocus.evaluation.batched import paper_estimates
from twinfocus.evaluation.experiments import paper_experiments
from twinfocus.focus.autofocus import AutofocusConfig, twin_autofocus
from twinfocus.imaging import metrics
from twinfocus.imaging.basis import form_image

CFG = AutofocusConfig(iterations=80, basis_dtype="float16")


def _basis_and_templates(seed: int = 0, m: int = 48, n: int = 24):
    """A random basis and two templates: the image at a true phase and at a perturbed one."""
    rng = np.random.default_rng(seed)
    basis = (rng.standard_normal((m, n, n)) + 1j * rng.standard_normal((m, n, n))).astype(np.complex64)
    true = rng.uniform(-1.0, 1.0, m)
    tpl_a = np.abs(form_image(basis, true))
    tpl_b = np.abs(form_image(basis, true + 0.3 * rng.standard_normal(m)))
    return basis, [tpl_a, tpl_b]


@pytest.mark.slow  # 49 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_each_batched_estimate_is_the_single_run():
    basis, templates = _basis_and_templates()
    batched, seconds = paper_estimates(basis, templates, CFG)
    assert seconds > 0
    for tpl, got in zip(templates, batched):
        assert isinstance(got, np.ndarray) and got.shape == (basis.shape[0],)
        single = twin_autofocus(basis, tpl, CFG).phase_rad
        assert np.abs(np.angle(np.exp(1j * (got - single)))).max() < 2e-3
        s_single = metrics.ssim(np.abs(form_image(basis, single)), tpl / tpl.max())
        s_batch = metrics.ssim(np.abs(form_image(basis, got)), tpl / tpl.max())
        assert s_batch == pytest.approx(s_single, abs=1e-4)
        # the optimiser did move from zero towards the template
        assert s_single > metrics.ssim(np.abs(form_image(basis, np.zeros(basis.shape[0]))), tpl / tpl.max())


@pytest.mark.slow  # 19 s (2 cores, load ~6): out of make test-fast (benchmarks/results/test_fast_before.json)
def test_a_bad_template_fails_alone():
    basis, templates = _basis_and_templates(seed=1)
    got, _ = paper_estimates(basis, [np.ones(basis.shape[1:]), templates[0]], CFG)
    assert isinstance(got[0], TwinFocusError) and "constant" in str(got[0])
    single = twin_autofocus(basis, templates[0], CFG).phase_rad
    assert isinstance(got[1], np.ndarray)
    assert np.abs(np.angle(np.exp(1j * (got[1] - single)))).max() < 2e-3


def test_only_the_paper_optimiser_is_batched():
    basis, templates = _basis_and_templates()
    with pytest.raises(TwinFocusError, match="single-stage"):
        paper_estimates(basis, templates, AutofocusConfig(iterations=10, basis_dtype="float16", coarse_iterations=5))


@pytest.mark.slow
def test_a_tiny_experiment_scores_the_same_with_and_without_the_batch(monkeypatch):
    """Two conditions of the environment sweep share their scene and draw: its physical templates
    of both rooms and its digital twin run as one batch; the same seed gives the same SSIM per
    record as the methods run one by one."""
    exp = paper_experiments(quick=True, only=["environment"])[0]
    exp.conditions = exp.conditions[:2]  # open room: the open-room and the cluttered-room template
    settings = runner.quick_settings()
    batched = runner.run_experiment(exp, settings, log=lambda m: None)
    monkeypatch.setattr(runner, "paper_twin_estimates", lambda *a, **k: {})
    single = runner.run_experiment(exp, settings, log=lambda m: None)
    key = [(r["condition"], r["method"]) for r in single["records"]]
    assert key == [(r["condition"], r["method"]) for r in batched["records"]]
    assert {m for _, m in key} >= {"physical", "digital"}
    for a, b in zip(single["records"], batched["records"]):
        assert a["status"] == b["status"] == "ok"
        assert b["ssim"] == pytest.approx(a["ssim"], abs=2e-3), (a["condition"], a["method"])


@pytest.mark.slow
def test_scenes_of_one_reference_share_its_physical_template_not_its_digital_twin():
    """The template cache a run (or a Dask worker) keeps across scenes: the reference's motion-stage
    template is reused by every scene with the same reference; the digital twin, whose camera sees
    the target too, is the scene's own, so a scene's twins do not depend on the scenes before it."""
    from twinfocus.evaluation.cases import EvalScenario, prepare_scene

    settings = runner.quick_settings()

    def scene(target: str, cache: dict):
        sc = EvalScenario(reference="A", target=target, n_rows=settings.n_rows, spacing_m=settings.spacing_m)
        return prepare_scene(sc, settings, "paper", template_cache=cache)

    cache: dict = {}
    first, second = scene("F", cache), scene("C", cache)
    assert second.templates["physical:open"] is first.templates["physical:open"]
    alone = scene("C", {})
    np.testing.assert_array_equal(second.templates["physical:open"], alone.templates["physical:open"])
    assert second.templates["digital"] is not None
    np.testing.assert_array_equal(second.templates["digital"], alone.templates["digital"])
