"""Complex-template registration and the closed-form phase (twinfocus.focus.template_match), against
brute-force sums and injected shifts / phase errors past lambda/4."""

from dataclasses import replace

import numpy as np
import pytest

from twinfocus.errors import TwinFocusError
from twinfocus.focus.autofocus import AutofocusConfig, fit_linear_phase, template_loss, twin_autofocus
from twinfocus.focus.template_match import (
    MatchScores,
    correlation_phase,
    match_scores,
    projection_phase,
    register_template,
    shift_image,
)
from twinfocus.imaging.backprojection.numba_backend import backproject, subimage_basis
from twinfocus.imaging.basis import form_image
from twinfocus.imaging.grid import ImageGrid
from twinfocus.imaging.metrics import oracle_phase, phase_error_rms
from twinfocus.motion.tracking_errors import apply_position_errors, gaussian_errors
from twinfocus.motion.trajectory import paper_raster, phase_centres
from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array
from twinfocus.simulation.if_simulator import simulate_if
from twinfocus.twins.templates import load_template, save_template

Z = 0.4
GRID = ImageGrid(-0.03, 0.03, -0.03, 0.03, Z, 32, 32)


def test_match_scores_equal_brute_force_sums():
    rng = np.random.default_rng(0)
    basis = (rng.normal(size=(7, 20, 24)) + 1j * rng.normal(size=(7, 20, 24))).astype(np.complex64)
    tpl = np.zeros((20, 24), np.complex64)
    tpl[5:15, 6:18] = rng.normal(size=(10, 12)) + 1j * rng.normal(size=(10, 12))
    scores = match_scores(basis, tpl, max_shift_px=3)
    flat = basis.reshape(7, -1)
    for dy, dx in [(0, 0), (2, -3), (-3, 1), (1, 3)]:
        moved = np.zeros_like(tpl)
        moved[max(dy, 0) : 20 + min(dy, 0), max(dx, 0) : 24 + min(dx, 0)] = tpl[
            max(-dy, 0) : 20 - max(dy, 0), max(-dx, 0) : 24 - max(dx, 0)
        ]
        want = np.abs(flat.conj() @ moved.reshape(-1)).sum() / np.linalg.norm(moved)
        assert scores[3 + dy, 3 + dx] == pytest.approx(want, rel=1e-4)
        # shift_image moves content the same way for whole pixels
        assert np.allclose(shift_image(tpl, dy, dx), moved, atol=1e-4)


_S = np.arange(-0.018, 0.0181, 0.002)
#: the scatterers (x, y) of an 'F' 36 mm tall, 2 mm apart, metres
_F_XY = [(-0.018, y) for y in _S] + [(x, 0.018) for x in _S] + [(x * 0.6, 0.0) for x in _S]


def _rough_f_samples(seed, z_sigma_m, n_columns=2, n_rows=36, row_pitch_m=0.003):
    """The 'F' of :data:`_F_XY` with every scatterer its own phase, seen from a raster with
    ``z_sigma_m`` of z jitter. Returns (pts, amps, chirp, true, tracked, data)."""
    rng = np.random.default_rng(seed)
    pts = np.array([(x, y, Z) for x, y in _F_XY])
    amps = np.exp(2j * np.pi * rng.random(len(pts)))
    poses = paper_raster(n_columns=n_columns, n_rows=n_rows, column_pitch_m=0.08, row_pitch_m=row_pitch_m)
    true = phase_centres(poses, mmwcas_virtual_array())
    tracked = apply_position_errors(true, gaussian_errors(true.shape[0], (0, 0, z_sigma_m), rng))
    ch = Chirp()
    return pts, amps, ch, true, tracked, simulate_if(pts, amps, true, ch)


def _letter_scene(offset_m, z_sigma_m=1.6e-3):
    """An 'F'-shaped speckled reference; positions with ``z_sigma_m`` of z jitter (1.6 mm: every
    phase wraps); the template: the same scatterers moved by ``offset_m``, back-projected on exact
    positions."""
    pts, amps, ch, true, tracked, data = _rough_f_samples(3, z_sigma_m)
    stage = simulate_if(pts + np.asarray(offset_m), amps, true, ch)
    basis = subimage_basis(data, tracked, ch, GRID)
    template = backproject(stage, true, ch, GRID)
    return ch, true, tracked, basis, template


@pytest.fixture(scope="module")
def misplaced():
    return _letter_scene((1.5e-3, -1.0e-3, 0.0))


def test_registration_finds_a_misplaced_template_when_every_phase_wraps(misplaced):
    ch, true, tracked, basis, template = misplaced
    assert phase_error_rms(np.zeros(basis.shape[0]), oracle_phase(true, tracked, GRID.centre_m, ch)) > 1.5  # wrapped
    _, (dy, dx), info = register_template(basis, template, max_shift_px=4)
    sy, sx = GRID.spacing_m
    # the template sits +1.5 mm in x, -1.0 mm in y: it must move back by that
    assert dx * sx == pytest.approx(-1.5e-3, abs=0.25 * sx)
    assert dy * sy == pytest.approx(1.0e-3, abs=0.25 * sy)
    assert info["score_gain"] > 1.0 and not info["at_limit"]


def test_closed_form_phase_recovers_wrapped_errors_once_registered(misplaced):
    ch, true, tracked, basis, template = misplaced
    oracle = oracle_phase(true, tracked, np.array([0.0, 0.0, Z]), ch)
    registered, _, _ = register_template(basis, template)
    err_registered = phase_error_rms(correlation_phase(basis, registered), oracle)
    err_misplaced = phase_error_rms(correlation_phase(basis, template), oracle)
    assert err_registered < 0.3
    # unregistered, the misplacement's phase ramp stays in the estimate
    assert err_misplaced > 2 * err_registered
    # through twin_autofocus with no iterations: the same closed form
    res = twin_autofocus(
        basis, template, AutofocusConfig(iterations=0, init="correlation", template_registration="correlation")
    )
    assert phase_error_rms(res.phase_rad, oracle) == pytest.approx(err_registered, abs=1e-6)
    assert res.extra["registration"]["shift_px"][1] < 0


def test_scores_added_as_a_scan_arrives_equal_the_whole_basis_and_register_alike(misplaced):
    """MatchScores fed batch by batch (as the solver node does while a scan arrives) against brute
    force sums at every stage, and the registration and estimate from them against the whole
    basis's."""
    ch, true, tracked, basis, template = misplaced
    acc = MatchScores(template, max_shift_px=4)
    flat = basis.reshape(basis.shape[0], -1)
    cuts = [0, 1, 1, 9, 30, basis.shape[0]]  # batches of 1, 0, 8, 21 and the rest
    for a, b in zip(cuts, cuts[1:]):
        acc.add(basis[a:b])
        assert acc.n_positions == b
        for dy, dx in [(0, 0), (1, -2), (-4, 3)]:  # registration on the rows so far: the same sums
            moved = shift_image(template, dy, dx)  # whole pixels: a plain move (the test above)
            want = np.abs(flat[:b].conj() @ moved.reshape(-1)).sum() / np.linalg.norm(moved)
            assert acc.scores()[4 + dy, 4 + dx] == pytest.approx(want, rel=1e-4)
    np.testing.assert_allclose(acc.scores(), match_scores(basis, template), rtol=1e-6)
    moved, shift, info = register_template(basis, template, scores=acc.scores())
    moved_whole, shift_whole, info_whole = register_template(basis, template)
    assert shift == pytest.approx(shift_whole, abs=1e-4) and info["at_limit"] == info_whole["at_limit"]
    np.testing.assert_allclose(moved, moved_whole, atol=1e-4 * np.abs(template).max())
    cfg = AutofocusConfig(iterations=0, init="correlation", template_registration="correlation")
    res = twin_autofocus(basis, template, cfg, registration_scores=acc.scores())
    res_whole = twin_autofocus(basis, template, cfg)
    np.testing.assert_allclose(np.angle(np.exp(1j * (res.phase_rad - res_whole.phase_rad))), 0.0, atol=1e-4)
    with pytest.raises(TwinFocusError, match="scores must be"):
        register_template(basis, template, max_shift_px=3, scores=acc.scores())
    with pytest.raises(TwinFocusError, match="basis rows must be"):
        acc.add(basis[:2, :, :31])
    with pytest.raises(TwinFocusError, match="template's phase"):
        MatchScores(np.abs(template))


@pytest.fixture(scope="module")
def placed():
    return _letter_scene((0.0, 0.0, 0.0))


@pytest.fixture(scope="module")
def coherent():
    """The placed scene with 0.15 mm of z jitter: the phases hold together."""
    return _letter_scene((0.0, 0.0, 0.0), z_sigma_m=0.15e-3)


def _error_but_a_plane(oracle, ap):
    """rms (rad) of a phase (M,) against ``oracle`` (M,), wrapped, less the plane across the
    aperture ``ap`` (M, 2) m fitted to their difference (a shift of the image, not a blur)."""
    return lambda p: phase_error_rms(
        np.angle(np.exp(1j * (p - oracle))) - fit_linear_phase(p - oracle, ap)[0], np.zeros_like(p)
    )


def _placed_error(scene):
    """:func:`_error_but_a_plane` against the oracle's phase at the centre of a :func:`_letter_scene`."""
    ch, true, tracked, _, _ = scene
    return _error_but_a_plane(oracle_phase(true, tracked, np.array([0.0, 0.0, Z]), ch), tracked.mean(axis=1)[:, :2])


@pytest.mark.slow
def test_projection_phase_recovers_wrapped_errors_from_the_amplitude_alone(placed):
    ch, true, tracked, basis, template = placed
    oracle = oracle_phase(true, tracked, np.array([0.0, 0.0, Z]), ch)
    amplitude = np.abs(template)
    assert phase_error_rms(np.zeros(basis.shape[0]), oracle) > 1.5  # every phase wrapped
    # F(phi) = sum A |I(phi)| never decreases from one projection step to the next
    f = [
        float((amplitude * np.abs(form_image(basis, projection_phase(basis, amplitude, k)))).sum()) for k in range(1, 9)
    ]
    assert all(b >= a * (1 - 1e-5) for a, b in zip(f, f[1:]))
    assert f[-1] > 1.2 * f[0]
    phi = projection_phase(basis, amplitude, 30)
    assert phase_error_rms(phi, oracle) < 0.15
    # the same start through twin_autofocus: with no iterations it is the whole estimate; the
    # optimiser from there keeps it, while the optimiser from zero stays far from the truth
    res = twin_autofocus(basis, amplitude, AutofocusConfig(init="projection", iterations=0))
    assert np.allclose(res.phase_rad, phi)
    refined = twin_autofocus(basis, amplitude, AutofocusConfig(init="projection", loss_steepness=5.0))
    from_zero = twin_autofocus(basis, amplitude, AutofocusConfig(loss_steepness=5.0))
    err = _placed_error(placed)
    assert err(refined.phase_rad) < 0.2
    assert err(from_zero.phase_rad) > 2 * err(refined.phase_rad)
    # restarts: every start is projected, the one with the lowest optimiser loss is kept
    res = twin_autofocus(basis, amplitude, AutofocusConfig(init="projection", iterations=0, projection_restarts=3))
    losses = res.extra["projection_restarts"]["losses"]
    assert len(losses) == 4 and res.extra["projection_restarts"]["chosen"] == int(np.argmin(losses))
    assert res.loss_history[0] == pytest.approx(min(losses), abs=1e-9)
    assert res.loss_history[0] == pytest.approx(template_loss(basis, res.phase_rad, amplitude), abs=1e-9)


def test_projection_phase_refuses_bad_input(placed):
    basis, template = placed[3], placed[4]
    with pytest.raises(TwinFocusError, match="iterations"):
        projection_phase(basis, np.abs(template), 0)
    with pytest.raises(TwinFocusError, match="one value per radar position"):
        projection_phase(basis, np.abs(template), 3, np.zeros(basis.shape[0] + 1))
    with pytest.raises(TwinFocusError, match="empty"):
        projection_phase(basis, np.zeros(template.shape), 3)
    bad = np.abs(template)
    bad[0, 0] = np.nan
    with pytest.raises(TwinFocusError, match="NaN"):
        projection_phase(basis, bad, 3)
    with pytest.raises(TwinFocusError, match="projection_iterations"):
        AutofocusConfig(init="projection", projection_iterations=0).validate()
    with pytest.raises(TwinFocusError, match="projection_restarts"):
        AutofocusConfig(init="projection", projection_restarts=-1).validate()
    with pytest.raises(TwinFocusError, match="init must be"):
        AutofocusConfig(init="random").validate()


def test_correlation_needs_the_templates_phase(misplaced):
    _, _, _, basis, template = misplaced
    with pytest.raises(TwinFocusError, match="phase"):
        twin_autofocus(basis, np.abs(template), AutofocusConfig(iterations=0, init="correlation"))
    with pytest.raises(TwinFocusError, match="iterations"):
        AutofocusConfig(iterations=0).validate()


def test_ramp_fit_leaves_wrapped_noise_alone_and_finds_a_real_ramp():
    rng = np.random.default_rng(1)
    ap = np.column_stack([np.repeat(np.arange(6) * 0.082, 130), np.tile(np.arange(130) * 0.0018, 6)])
    noise = rng.uniform(-np.pi, np.pi, ap.shape[0])
    ramp, coeffs = fit_linear_phase(noise, ap)
    assert coeffs[1] == 0.0 and coeffs[2] == 0.0
    assert np.ptp(ramp) == 0.0
    true = 0.7 + ap @ np.array([20.0, -9.0])
    ramp, coeffs = fit_linear_phase(true + rng.normal(0, 1.0, ap.shape[0]), ap)
    assert coeffs[1:] == pytest.approx([20.0, -9.0], abs=1.0)


def test_template_file_keeps_the_phase(tmp_path, misplaced):
    template = misplaced[4].astype(np.complex64)
    save_template(tmp_path / "t.npz", template, GRID)
    back = load_template(tmp_path / "t.npz", GRID)
    assert back.dtype == np.complex64
    assert np.allclose(back, template, rtol=1e-5, atol=1e-6 * np.abs(template).max())
    # onto a finer grid inside it: bilinear on the complex image, so a pixel half-way between two
    # of the file's is their complex mean
    fine = ImageGrid(GRID.x_m[1], GRID.x_m[3], GRID.y_m[1], GRID.y_m[3], Z, 5, 5)
    res = load_template(tmp_path / "t.npz", fine)
    assert res[0, 1] == pytest.approx((template[1, 1] + template[1, 2]) / 2, rel=1e-4)
    save_template(tmp_path / "a.npz", np.abs(template), GRID)
    assert load_template(tmp_path / "a.npz", GRID).dtype == np.float32


def _outline(grid, radius_m=2.5e-3):
    """The 'F' of :func:`_letter_scene` as a support mask: pixels within ``radius_m`` of a scatterer."""
    xy = np.array(_F_XY)
    yy, xx = np.meshgrid(grid.y_m, grid.x_m, indexing="ij")
    d = np.hypot(xx[..., None] - xy[:, 0], yy[..., None] - xy[:, 1]).min(axis=-1)
    return d <= radius_m


def test_outline_phase_recovers_wrapped_errors_from_the_outline_alone(placed):
    from twinfocus.focus.template_match import outline_phase

    ch, true, tracked, basis, _ = placed
    err = _placed_error(placed)
    assert err(np.zeros(basis.shape[0])) > 1.5  # every phase wrapped; the scatterers' own phases are random
    support = _outline(GRID)
    phi, info = outline_phase(basis, support)
    assert err(phi) < 0.3
    # the start was chosen by the rule, and the energy inside rose from the uncorrected image
    e0 = np.abs(basis.sum(axis=0)) ** 2
    _assert_chosen_by_the_rule(info)
    assert max(info["energy_inside"]) > e0[support].sum() / e0.sum() + 0.1
    # an outline placed 2 pixels off (a camera cloud's offset) is moved back by the data, where
    # the image resolves it: across the two columns (x) but not along them (y: a 7 mm beam width
    # here, 3.6 pixels, over which the energy inside hardly changes)
    from twinfocus.focus.template_match import _shift_mask

    phi, info = outline_phase(basis, _shift_mask(support, 0, -2))
    assert info["support_shift_px"] == [0, 2]
    assert err(phi) < 0.3
    # through twin_autofocus, as --estimator outline runs it
    res = twin_autofocus(
        basis, np.abs(basis.sum(axis=0)), AutofocusConfig(init="outline", iterations=0), support=support
    )
    assert err(res.phase_rad) < 0.3 and "energy_inside" in res.extra["outline"]


def test_outline_phase_refuses_bad_input(placed):
    from twinfocus.focus.template_match import outline_phase

    basis = placed[3]
    with pytest.raises(TwinFocusError, match="outline"):
        outline_phase(basis, np.zeros(GRID.shape, bool))
    with pytest.raises(TwinFocusError, match="support is"):
        outline_phase(basis, np.ones((5, 5), bool))
    with pytest.raises(TwinFocusError, match="needs the reference's outline"):
        twin_autofocus(basis, np.abs(basis.sum(axis=0)), AutofocusConfig(init="outline", iterations=0))


def test_outlines_run_together_give_each_outline_its_own_run(placed):
    """outline_phases shares the matrix products between outlines; each outline's estimate must be
    what it gets alone, shifts and all."""
    from twinfocus.focus.template_match import _shift_mask, outline_phase, outline_phases

    basis = placed[3]
    a = _outline(GRID)
    b = _shift_mask(a, 2, -1) | a  # another outline, larger and moved
    together = outline_phases(basis, [a, b], starts=3, iterations=8, rounds=2)
    for support, (phi, info) in zip((a, b), together):
        alone_phi, alone_info = outline_phase(basis, support, starts=3, iterations=8, rounds=2)
        assert np.abs(np.angle(np.exp(1j * (phi - alone_phi)))).max() < 1e-4
        assert info["chosen"] == alone_info["chosen"] and info["support_shift_px"] == alone_info["support_shift_px"]
        assert info["energy_inside"] == pytest.approx(alone_info["energy_inside"], abs=2e-4)
    assert not np.allclose(together[0][0], together[1][0])  # the two outlines did pull differently
    with pytest.raises(TwinFocusError, match="at least one outline"):
        outline_phases(basis, [])
    with pytest.raises(TwinFocusError, match="support is"):
        outline_phases(basis, [a, np.ones((5, 5), bool)])


def test_grown_outlines_fill_a_hole_where_the_image_is_bright_and_nowhere_else():
    from twinfocus.focus.template_match import _shift_mask, grown_outlines

    # the reference: a bar 4 px wide, 24 tall; the image bright on it, dim elsewhere, and bright on a
    # blob 15 px away (another object: too far to be the reference's)
    bar = np.zeros((40, 40), bool)
    bar[8:32, 10:14] = True
    energy = np.where(bar, 1.0, 0.01)
    energy[18:22, 28:32] = 1.0
    # the cloud's outline: the bar with a 3-row hole, placed 2 px left of where the radar sees it
    holed = bar.copy()
    holed[18:21] = False
    support = _shift_mask(holed, 0, -2)
    grown = grown_outlines(support, energy, shift_px=(0, 2))
    assert len(grown) == 4
    want = _shift_mask(bar, 0, -2)  # the whole bar, in the outline's frame
    for g in grown:
        assert (g | ~support).all()  # never loses a pixel of the cloud's outline
        assert g[18:21, 9:11].all()  # the hole is filled (a closing rounds its corners: the middle columns)
        assert not (g & ~want).any()  # nothing dim is taken, nor the far blob
    # growth into the bright pixels fills the hole to its corners: the bar exactly
    assert (grown[2] == want).all() and (grown[3] == want).all()
    with pytest.raises(TwinFocusError, match="energy is"):
        grown_outlines(support, energy[:-1])
    with pytest.raises(TwinFocusError, match="finite"):
        grown_outlines(support, np.full((40, 40), np.nan))
    with pytest.raises(TwinFocusError, match="leaves the region"):
        grown_outlines(support, energy, shift_px=(0, 40))


def test_averaged_outlines_beat_one_outline_with_a_hole(placed):
    from twinfocus.focus.template_match import averaged_outline_phase, outline_phase

    ch, true, tracked, basis, _ = placed
    ap = tracked.mean(axis=1)[:, :2]
    err = _placed_error(placed)
    # the 'F' with 8 mm of its stem missing (a camera cloud's hole)
    yy, xx = np.meshgrid(GRID.y_m, GRID.x_m, indexing="ij")
    support = _outline(GRID) & ~((np.abs(yy - 0.004) < 0.004) & (xx < -0.012))
    one, _ = outline_phase(basis, support)
    # as `twinfocus focus` runs the outline estimator with outline_ensemble (the aperture from the
    # tracked positions), the reference region standing in for the target too
    from twinfocus.focus.pipeline import Bases, Reference
    from twinfocus.focus.plan import FocusPlan

    cfg = AutofocusConfig(init="outline", iterations=0, outline_ensemble=True)
    out = FocusPlan.make(config=cfg).focus_bases(
        Bases(basis, basis, tracked, ch, GRID, GRID),
        Reference(template=np.abs(basis.sum(axis=0)), support=support),
    )
    assert err(one) > 0.2  # the hole costs the single outline
    assert err(out.phase_rad) < 0.7 * err(one)
    est = out.metrics["estimator"]
    info = est["outline_ensemble"]
    # the cloud's outline grown first, then the ensemble around the grown one
    rounds = cfg.outline_growth_rounds
    assert len(info["growth_px"]) == rounds + 1 and info["growth_px"][0] == support.sum()
    assert np.all(np.diff(info["growth_px"]) >= 0) and info["outlines_px"][0] == info["growth_px"][-1]
    assert min(info["outlines_px"][1:]) >= info["outlines_px"][0]
    # growing it first brings the estimate nearer the truth than the ensemble around the cloud's outline
    not_grown, plain = averaged_outline_phase(basis, support, ap, growth_rounds=0)
    assert plain["growth_px"] == [support.sum()] and plain["outlines_px"][0] == support.sum()
    assert err(out.phase_rad) < 0.85 * err(not_grown)
    assert len(info["energy_inside"]) == len(info["support_shift_px"]) == 5 and 0.9 < info["agreement"] <= 1.0
    # the cloud's outline's run, which the confidence report reads
    assert "energy_inside" in est["outline"] and "outline_energy_inside" in out.metrics["confidence"]
    # the config's choice of end reaches every run: the least contrast's end, each time
    by_speckle = FocusPlan.make(config=replace(cfg, outline_choice="speckle")).focus_bases(
        Bases(basis, basis, tracked, ch, GRID, GRID),
        Reference(template=np.abs(basis.sum(axis=0)), support=support),
    )
    run = by_speckle.metrics["estimator"]["outline"]
    assert run["chosen_by"] == "speckle" and run["contrast"][run["chosen"]] == min(run["contrast"])
    with pytest.raises(TwinFocusError, match="aperture"):
        twin_autofocus(basis, np.abs(basis.sum(axis=0)), cfg, support=support)
    with pytest.raises(TwinFocusError, match="aperture_m must be"):
        averaged_outline_phase(basis, support, ap[:-1])
    with pytest.raises(TwinFocusError, match="NaN"):
        averaged_outline_phase(basis, support, np.full_like(ap, np.nan))


def test_growing_the_outline_fills_a_hole_at_the_edge_and_never_drops_a_pixel(placed):
    from twinfocus.focus.template_match import OUTLINE_GROWTH_ROUNDS, grown_outline, grown_outlines, outline_phase

    ch, true, tracked, basis, _ = placed
    yy, xx = np.meshgrid(GRID.y_m, GRID.x_m, indexing="ij")
    letter = _outline(GRID)
    support = letter & ~((np.abs(yy - 0.004) < 0.004) & (xx < -0.012))  # 8 mm of the stem missing, at its edge
    assert (letter & ~support).sum() >= 10
    same, sizes = grown_outline(basis, support, 0)
    assert (same == support).all() and sizes == [support.sum()]
    grown, sizes = grown_outline(basis, support, 2)
    assert (grown | ~support).all()  # never loses a pixel
    assert (grown & letter).sum() == letter.sum()  # the missing stem is back
    assert sizes[0] == support.sum() and sizes[-1] == grown.sum() and len(sizes) == 3
    # one round is the union of grown_outlines from the cloud's outline's own estimate
    phi, info = outline_phase(basis, support)
    energy = np.abs(form_image(basis, phi)) ** 2
    one, _ = grown_outline(basis, support, 1)
    assert (one == np.logical_or.reduce(grown_outlines(support, energy, info["support_shift_px"]))).all()
    # the estimator's default is the library's (one number, measured in docs/digital_twin.md)
    assert AutofocusConfig().outline_growth_rounds == OUTLINE_GROWTH_ROUNDS
    # the estimator's own options pass through, its rounds included
    fewer, _ = grown_outline(basis, support, growth_rounds=1, rounds=1, starts=2)
    assert (fewer | ~support).all()
    with pytest.raises(TwinFocusError, match="growth rounds"):
        grown_outline(basis, support, -1)
    with pytest.raises(TwinFocusError, match="outline_growth_rounds"):
        AutofocusConfig(init="outline", iterations=0, outline_growth_rounds=-1).validate()
    with pytest.raises(TwinFocusError, match="outline_choice must be one of energy, speckle, auto, got 'most'"):
        AutofocusConfig(init="outline", iterations=0, outline_choice="most").validate()


def test_auto_runs_the_optimiser_only_where_the_projections_phases_have_wrapped(placed, coherent):
    """auto with an amplitude template decides from the projections' own phases, not from a
    stated tracking error: checked against the truth (the oracle phase's coherence) on a scene
    whose errors wrap and on one whose errors hold together."""
    from twinfocus.focus.estimators import AUTO_REFINE_BELOW_COHERENCE, estimator_settings

    for (ch, true, tracked, basis, template), wraps in ((placed, True), (coherent, False)):
        oracle = oracle_phase(true, tracked, np.array([0.0, 0.0, Z]), ch)
        truth_coherence = np.abs(np.exp(1j * oracle).mean()) * np.sqrt(oracle.size)
        assert (truth_coherence < AUTO_REFINE_BELOW_COHERENCE) == wraps  # the scenes are what they say
        ap = tracked.mean(axis=1)[:, :2]
        amplitude = np.abs(template)
        cfg = AutofocusConfig(**{**estimator_settings("auto", False), "iterations": 20})
        res = twin_autofocus(basis, amplitude, cfg, aperture_m=ap)
        check = res.extra["refine_check"]
        assert check["refined"] == wraps and (check["coherence_sqrt_m"] < AUTO_REFINE_BELOW_COHERENCE) == wraps
        projections = twin_autofocus(basis, amplitude, AutofocusConfig(**estimator_settings("projection", False)))
        if wraps:  # the optimiser ran from the projections
            assert len(res.loss_history) == 20 and res.loss_history[-1] < projections.loss_history[0]
        else:  # the projections alone, as --estimator projection gives them, and close to the truth
            assert np.array_equal(res.phase_rad, projections.phase_rad)
            assert phase_error_rms(res.phase_rad, oracle) < 0.3
    with pytest.raises(TwinFocusError, match="aperture_m"):
        twin_autofocus(basis, amplitude, cfg)
    with pytest.raises(TwinFocusError, match="refine_below_coherence"):
        AutofocusConfig(init="projection", refine_below_coherence=-1.0).validate()


def test_the_report_warns_that_an_outline_cannot_be_placed_once_the_phases_wrap(placed, coherent):
    """With the phases wrapped, nothing in the scan checks where the outline put the reference, and
    the confidence report says so; while they hold together it does not."""
    from twinfocus.focus.estimators import AUTO_REFINE_BELOW_COHERENCE, estimator_settings
    from twinfocus.focus.pipeline import Bases, Reference
    from twinfocus.focus.plan import FocusPlan

    for (ch, true, tracked, basis, template), wraps in ((placed, True), (coherent, False)):
        oracle = oracle_phase(true, tracked, np.array([0.0, 0.0, Z]), ch)
        assert (np.abs(np.exp(1j * oracle).mean()) * np.sqrt(oracle.size) < AUTO_REFINE_BELOW_COHERENCE) == wraps
        out = FocusPlan.make(config=AutofocusConfig(**estimator_settings("auto", False, has_support=True))).focus_bases(
            Bases(basis, basis, tracked, ch, GRID, GRID),
            Reference(template=np.abs(template), support=_outline(GRID)),
        )
        est, conf = out.metrics["estimator"], out.metrics["confidence"]
        assert (est["phase_coherence_sqrt_m"] < AUTO_REFINE_BELOW_COHERENCE) == wraps
        assert any("phases have wrapped" in w for w in conf["warnings"]) == wraps
        assert 0 < conf["outline_agreement"] <= 1


def test_auto_takes_the_outline_for_a_cloud_twin_and_only_then():
    from twinfocus.focus.estimators import estimator_settings

    assert estimator_settings("auto", False, has_support=True)["init"] == "outline"
    # averaged over the grown outlines (measured on camera clouds, docs/digital_twin.md)
    assert estimator_settings("outline", False, has_support=True)["outline_ensemble"] is True
    assert "outline_ensemble" not in estimator_settings("projection", False)
    assert estimator_settings("auto", False)["init"] == "projection"
    assert estimator_settings("auto", True, has_support=True)["init"] == "correlation"
    with pytest.raises(TwinFocusError, match="outline"):
        estimator_settings("outline", False)


def test_speckle_contrast_equals_its_sums():
    from twinfocus.focus.template_match import speckle_contrast

    rng = np.random.default_rng(5)
    e = rng.exponential(1.0, (3, 400))
    masks = rng.random((3, 400)) < 0.5
    want = [np.mean(row[m] ** 2) / np.mean(row[m]) ** 2 for row, m in zip(e, masks)]
    assert np.allclose(speckle_contrast(e, masks), want)
    # exponential energies (fully developed speckle): 2; one bright pixel among dark ones: far more
    assert speckle_contrast(rng.exponential(1.0, (1, 200000)), np.ones((1, 200000)))[0] == pytest.approx(2.0, rel=0.03)
    spike = np.full((1, 100), 0.01)
    spike[0, 0] = 1.0
    assert speckle_contrast(spike, np.ones((1, 100)))[0] > 20


def _assert_chosen_by_the_rule(info):
    """The end :func:`outline_phase` chose by ``choose="auto"``: the most energy inside unless that
    end's contrast is above PILED_CONTRAST, then the least contrast."""
    from twinfocus.focus.template_match import PILED_CONTRAST

    # (the info's figures are rounded: ends tied there are told apart by the unrounded ones)
    most = [i for i, f in enumerate(info["energy_inside"]) if f == max(info["energy_inside"])]
    if all(info["contrast"][i] > PILED_CONTRAST for i in most):
        assert info["chosen_by"] == "speckle" and info["contrast"][info["chosen"]] == min(info["contrast"])
    else:
        assert info["chosen_by"] == "energy" and info["chosen"] in most


def _rough_field_reference(z_sigma_m, roughness_deg=90.0):
    """A rough 'F' 127 mm tall as the field bench draws it (every scatterer its own phase over
    +-``roughness_deg``; None: a smooth one), 390 positions, 64 x 64 pixels, its outline from a camera cloud with 1 mm noise,
    25 % holes, 2 % outliers and a 2.5 mm offset. Returns (basis, outline, oracle phase, aperture
    (M, 2), target basis, target on the true positions)."""
    from twinfocus.simulation.scenario import Scenario, scenario_grids, simulate_scenario
    from twinfocus.twins.digital_twin.camera_cloud import camera_cloud
    from twinfocus.twins.digital_twin.condition import digital_twin_reference

    sc = Scenario(
        reference="F",
        target="B",
        separation_deg=9.7,
        reference_roughness_deg=roughness_deg,
        reference_amplitude_spread=0.3,
        n_rows=65,
        seed=1001,
        snr_db=15,
        error_sigma_m=(0.2e-3, 0.2e-3, z_sigma_m),
    )
    scan, _ = simulate_scenario(sc)
    rg, tg = scenario_grids(sc, 64)
    surface = sc.scene().object("reference").surface_points(1e-3)
    cloud = camera_cloud(surface, 1e-3, 0.25, 0.02, 2.5e-3, rng=np.random.default_rng(14))
    twin = digital_twin_reference(cloud, scan.positions, scan.chirp, rg)
    basis = subimage_basis(scan.data, scan.positions, scan.chirp, rg)
    oracle = oracle_phase(scan.positions_true, scan.positions, rg.centre_m, scan.chirp)
    tb = subimage_basis(scan.data, scan.positions, scan.chirp, tg)
    truth = backproject(scan.data, scan.positions_true, scan.chirp, tg)
    return basis, twin.support, oracle, scan.positions.mean(axis=1)[:, :2], tb, truth


@pytest.mark.slow
@pytest.mark.parametrize("z_sigma_m", [0.5e-3, 1.6e-3])
def test_the_speckle_choice_finds_the_phase_the_energy_choice_misses(z_sigma_m):
    """On a rough reference whose outline comes from a camera cloud, the start of least speckle
    contrast lies nearer the true phase than the start of most energy inside the outline, also
    when every phase has wrapped (1.6 mm)."""
    from twinfocus.focus.template_match import outline_phase
    from twinfocus.imaging.metrics import image_ssim

    basis, support, oracle, ap, tb, truth = _rough_field_reference(z_sigma_m)
    err = _error_but_a_plane(oracle, ap)
    if z_sigma_m > 1e-3:
        assert err(np.zeros_like(oracle)) > 1.5  # every phase wrapped
    by_energy, info_e = outline_phase(basis, support, choose="energy")
    by_speckle, info_s = outline_phase(basis, support)
    # the same starts: only the choice differs; the energy inside hardly tells the ends apart, and
    # the most energy's end has piled it, so the default rule took the least contrast
    assert info_e["energy_inside"] == info_s["energy_inside"]
    assert info_s["chosen_by"] == "speckle"
    _assert_chosen_by_the_rule(info_s)
    assert info_s["energy_inside"][info_s["chosen"]] > max(info_s["energy_inside"]) - 0.03
    # (measured: 0.96 against 1.17 rad at 0.5 mm, 0.87 against 1.10 at 1.6 mm)
    assert err(by_speckle) < err(by_energy) - 0.15
    # and the target formed with it is nearer the target on the true positions (0.75 against 0.59-0.60)
    assert image_ssim(form_image(tb, by_speckle), truth) > image_ssim(form_image(tb, by_energy), truth) + 0.1


@pytest.mark.slow
def test_on_a_smooth_reference_the_rule_keeps_the_most_energy():
    """On a smooth reference no end piles its energy (every end's contrast is near the others'),
    and the least contrast is the most smeared end: the default rule keeps the end of most energy,
    which forms the target nearer the target on the true positions than the least contrast's."""
    from twinfocus.focus.template_match import outline_phase
    from twinfocus.imaging.metrics import image_ssim

    basis, support, oracle, ap, tb, truth = _rough_field_reference(0.5e-3, roughness_deg=None)
    phi, info = outline_phase(basis, support)
    by_speckle, _ = outline_phase(basis, support, choose="speckle")
    assert info["chosen_by"] == "energy"
    _assert_chosen_by_the_rule(info)
    assert image_ssim(form_image(tb, phi), truth) > image_ssim(form_image(tb, by_speckle), truth) + 0.05
