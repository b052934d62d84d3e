"""The focus plan (twinfocus.focus.plan): what it makes of the settings and the template, what it
says a run needs, and the refusals it makes before any work. The command and the solver node both
focus through it, so these hold for both."""

import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.focus.estimators import AUTO_REFINE_BELOW_COHERENCE, estimator_settings
from twinfocus.focus.plan import FocusPlan, ladder_modes

AMPLITUDE = np.ones((8, 8), np.float32)
AMPLITUDE[2:5, 3] = 4.0


def plan(**settings):
    return FocusPlan.from_settings({"device": "cpu", **settings})


def test_the_estimator_follows_the_template_kind_and_explicit_settings_win():
    # an amplitude template: the projections, the optimiser only where their phases have wrapped
    cfg = plan().for_reference(AMPLITUDE).config
    assert (cfg.init, cfg.loss_steepness, cfg.refine_below_coherence) == (
        "projection",
        5.0,
        AUTO_REFINE_BELOW_COHERENCE,
    )
    assert cfg.iterations > 0 and plan().for_reference(AMPLITUDE).estimator == "projection-refined"
    physical = plan().for_reference(AMPLITUDE.astype(np.complex64))  # with its phase: the closed form
    assert (physical.config.init, physical.config.iterations, physical.estimator) == ("correlation", 0, "correlation")
    outline = plan().for_reference(AMPLITUDE, support=AMPLITUDE > 1)
    assert outline.config.init == "outline" and outline.config.outline_ensemble
    chosen = plan(estimator="projection-refined", loss_steepness=2.0, iterations=40).for_reference(AMPLITUDE).config
    want = {**estimator_settings("projection-refined", False), "loss_steepness": 2.0}
    assert {k: getattr(chosen, k) for k in want} == want and chosen.iterations == 40
    # without a template (a reference-free method) the settings' config alone
    free = FocusPlan.from_settings({"device": "cpu", "iterations": 7}, "sharpness").for_reference(None)
    assert free.estimator == "" and free.config.iterations == 7 and free.config.init == "zero"


def test_what_a_run_needs_follows_the_ladder():
    assert plan().needs.torch and plan().needs.half_bases and plan().needs.upper_band
    fast = plan(model="fast").needs
    assert fast.torch and not fast.half_bases  # fast climbs the drift, never the tilt
    assert not plan(model="phase").needs.torch and not plan(space_variant="off").needs.torch
    assert not plan(phase_ramp="keep").needs.upper_band  # an explicit ramp setting: no range errors
    assert plan(model="phase", space_variant="on").needs.half_bases  # --space-variant wins over --model
    free = FocusPlan.from_settings({"device": "cpu"}, "sharpness").needs
    assert not (free.torch or free.half_bases or free.upper_band)


def test_the_mode_words_users_type_map_to_the_rungs_modes():
    modes = ladder_modes(phase_ramp="remove")
    assert modes["placement"] == "on" and modes["range_errors"] == "off"
    assert ladder_modes(phase_ramp="keep")["placement"] == "off"
    assert ladder_modes("full")["refine"] == "on" and ladder_modes("full")["drift"] == "try"
    assert list(ladder_modes("placement").values()) == ["auto", "auto", "auto", "on", "off", "off", "off"]
    # the baseline always, the estimate unless off; the others as the words say
    assert [r.mode for r in plan(phase_ramp="remove").rungs] == ["on", "on", "auto", "on", "off", "auto", "auto"]


def test_bad_settings_are_refused_before_any_work():
    with pytest.raises(TwinFocusError, match="needs the template's phase"):
        plan(estimator="correlation").for_reference(AMPLITUDE)
    with pytest.raises(TwinFocusError, match="not a rung of this ladder"):
        FocusPlan.from_settings({"device": "cpu", "model": "drift"}, "sharpness")
    with pytest.raises(TwinFocusError, match="model must be one of"):
        plan(model="everything")


def test_the_rung_registry_names_each_rung_once_and_its_ladder():
    """The command's choices (read without the numerics) and the ladder's classes come from one
    registry: each entry's class carries the entry's name, and is a reference-free rung exactly
    when the registry puts it in no ladder but its own."""
    from twinfocus.focus.estimators import REFERENCE_FREE_RUNGS, RUNG_REGISTRY, TWIN_RUNGS
    from twinfocus.focus.rungs import RUNGS, ReferenceFree, reference_free_rungs

    assert list(RUNGS) == list(RUNG_REGISTRY) == [*TWIN_RUNGS, *REFERENCE_FREE_RUNGS]
    assert all(cls.name == name for name, cls in RUNGS.items())
    assert reference_free_rungs() == REFERENCE_FREE_RUNGS
    assert {n for n, c in RUNGS.items() if issubclass(c, ReferenceFree)} == set(REFERENCE_FREE_RUNGS)
    assert list(ladder_modes("auto")) == list(TWIN_RUNGS)
