"""Matching a complex template to the sub-image basis, whatever the phase errors.

A physical twin is a focused *complex* image T of the reference (its motion-stage scan,
back-projected). Against the scan's sub-image basis B (M, H, W) it gives two things no amplitude
template can:

* **Registration** (:func:`register_template`). A per-position phase can absorb any shift that
  is a linear phase across the aperture, which is why an amplitude loss cannot tell where the
  template should sit; but it cannot reshape the image one position sees through its own array
  (the 86 channels resolve the reference along their line, the range spread resolves it a
  little across). The score

      J(s) = sum_m | <B_m, T(. - s)> | / ||T(. - s)||

  is unchanged by any per-position phase and peaks where the template lines up with the
  reference in the scan, so it locates a misplaced template even when every phase has wrapped.
* **A closed-form phase** (:func:`correlation_phase`): phi_m = angle <B_m, T>, the phase that
  best lines up each position's sub-image with the template (the per-position matched filter).
  With a registered template it reaches the transfer ceiling in one matrix-vector product
  (docs/evaluation.md, "beyond the paper").

An amplitude template (a digital twin's) has no phase to correlate with; :func:`projection_phase`
lends it the scan's own image phase and repeats the closed form (alternating projections, as in
Gerchberg-Saxton phase retrieval), which needs no unwrapping either.

A rough reference (every scatterer its own phase and strength) is speckled in the radar image,
whatever a template's texture says; what a camera cloud does tell is its *outline*.
:func:`outline_phase` asks only that the reference's energy fall inside it (Fienup's error
reduction with a support constraint), with the outline registered to the scan and the start
chosen by that same criterion. A camera cloud's holes leave that outline short of the letter;
:func:`grown_outline` grows it, round by round, into the pixels its estimates light up, and
:func:`averaged_outline_phase` grows that once more in several ways and averages the estimates the
outlines give.

<a, b> = sum_pixels conj(a) b throughout.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.fft

from twinfocus.errors import TwinFocusError
from twinfocus.focus.phase_ramp import fit_linear_phase
from twinfocus.imaging.basis import form_image
from twinfocus.imaging.subpixel import parabola_vertex, shift_image


def _check(basis: np.ndarray, template: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    b = np.asarray(basis)
    if b.ndim != 3 or not np.iscomplexobj(b):
        raise TwinFocusError(f"basis must be complex (M, H, W), got {b.dtype} {b.shape}")
    return b, _check_template(template, b.shape[1:])


def _check_template(template: np.ndarray, shape: tuple[int, ...] | None = None) -> np.ndarray:
    """The template as an array, when it is complex, finite, not all zeros and (given) of ``shape``."""
    t = np.asarray(template)
    if not np.iscomplexobj(t):
        raise TwinFocusError(
            "this needs the template's phase (a complex image, e.g. a physical twin's "
            "back-projected scan); an amplitude template cannot be matched per position"
        )
    if t.ndim != 2 or (shape is not None and t.shape != tuple(shape)):
        raise TwinFocusError(f"template is {t.shape} but the reference region is {tuple(shape) if shape else '(H, W)'}")
    if not np.isfinite(t).all():
        raise TwinFocusError("template holds NaN or inf")
    if not np.any(t):
        raise TwinFocusError("template is empty (all zeros)")
    return t


def correlation_phase(basis: np.ndarray, template: np.ndarray) -> np.ndarray:
    """phi_m = angle <B_m, T>: float64 (M,) radians, the per-position phase that lines up
    position m's sub-image with the complex template (maximises Re <T, exp(j phi_m) B_m> for
    each m on its own).

    basis : complex (M, H, W); template : complex (H, W) on the same grid.
    """
    b, t = _check(basis, template)
    flat = b.reshape(b.shape[0], -1)
    # angle <B_m, T> = -angle (B_m . conj T): no conjugate copy of the basis; the template at unit
    # peak so that the products of a basis and a template at 1e20 (or 1e-20) neither overflow nor
    # flush to zero in complex64
    t = _unit_peak(t)
    return -np.angle(flat @ np.conj(t.reshape(-1)).astype(flat.dtype)).astype(np.float64)


def _unit_peak(template: np.ndarray) -> np.ndarray:
    """complex128 (H, W): the template divided by its peak modulus (the scale is free)."""
    t = np.asarray(template).astype(np.complex128)
    return t / np.abs(t).max()


def _shift_limit(max_shift_px: int, shape: tuple[int, ...]) -> int:
    """The registration's search half-width S: ``max_shift_px``, or less on a region too small
    for a search of 2 S + 1 shifts (S = (min(H, W) - 1) // 2)."""
    s = int(max_shift_px)
    if s < 1:
        raise TwinFocusError(f"max_shift_px must be >= 1, got {max_shift_px}")
    fits = (min(shape) - 1) // 2
    if fits < 1:
        raise TwinFocusError(
            f"a {shape[0]} x {shape[1]} region is too small to register a template in (at least 3 x 3 pixels)"
        )
    return min(s, fits)


def projection_phase(
    basis: np.ndarray, amplitude: np.ndarray, iterations: int = 30, init_phase_rad: np.ndarray | None = None
) -> np.ndarray:
    """Per-position phases that fit an *amplitude* template by alternating projections.

    Each step forms I = sum_m exp(j phi_m) B_m, gives it the template's amplitude while keeping
    its own phase, T = A exp(j angle I), and takes the closed form phi_m = angle <B_m, T>
    (:func:`correlation_phase`). That is block-coordinate ascent of F(phi) = sum_p A_p |I_p(phi)|
    (the image's amplitude weighted by the template's), so F never decreases; every step is
    closed form on the unit circle, so errors past lambda/4 (every phase wrapped) cost it nothing
    more than small ones. A local maximum of F is not the truth, which is why
    ``twin_autofocus(init="projection")`` goes on with the SSIM loss from here.

    basis : complex (M, H, W); amplitude : real (H, W) >= 0 on the same grid (a complex template's
    modulus is taken); iterations : projection steps (>= 1); init_phase_rad : (M,) start (zeros).
    Returns float64 (M,) radians.
    """

    a = np.abs(np.asarray(amplitude))
    b, _ = _check(basis, a.astype(np.complex64))  # its shape, finiteness and emptiness checks
    if int(iterations) < 1:
        raise TwinFocusError(f"projection iterations must be >= 1, got {iterations}")
    a = (a / a.max()).astype(np.float32)
    phi = np.zeros(b.shape[0]) if init_phase_rad is None else np.asarray(init_phase_rad, dtype=np.float64)
    if phi.shape != (b.shape[0],):
        raise TwinFocusError(f"init_phase_rad must have one value per radar position ({b.shape[0]}), got {phi.shape}")
    for _ in range(int(iterations)):
        phi = correlation_phase(b, a * np.exp(1j * np.angle(form_image(b, phi))))
    return phi


class MatchScores:
    """J(s) of :func:`match_scores`, accumulated over the basis's positions batch by batch.

    J(s) = sum_m |<B_m, T(. - s)>| / ||T(. - s)|| is a sum over positions, so the rows of a scan
    added as they arrive give, at the end, the whole basis's scores: a live scan registers its
    template while it is captured and pays only for the last batch after it. The
    template's spectrum and the normaliser are computed once, here.

    template : complex (H, W) on the basis's grid; max_shift_px : S, shifts |dy|, |dx| <= S (less
    on a region smaller than 2 S + 1 pixels: :attr:`max_shift_px` holds the S searched).
    """

    def __init__(self, template: np.ndarray, max_shift_px: int = 4):
        # unit peak: the scores are a ratio, and a template at 1e20 would overflow complex64
        t = _unit_peak(_check_template(template))
        s = _shift_limit(max_shift_px, t.shape)
        h, w = t.shape
        self.shape = t.shape
        self.max_shift_px = s
        self._pad = (h + s, w + s)  # enough padding that shifts up to s never wrap
        self._spectrum = np.conj(scipy.fft.fft2(t.astype(np.complex64), self._pad))
        self._rows = np.r_[0 : s + 1, self._pad[0] - s : self._pad[0]]
        self._cols = np.r_[0 : s + 1, self._pad[1] - s : self._pad[1]]
        self._sum = np.zeros((self._rows.size, self._cols.size))
        #: positions added so far
        self.n_positions = 0
        # the part of the moved template that stays on the grid
        energy = np.abs(t) ** 2
        fe = np.conj(scipy.fft.fft2(energy, self._pad))
        kept = np.real(scipy.fft.ifft2(scipy.fft.fft2(np.ones_like(energy), self._pad) * fe))[self._rows][:, self._cols]
        self._norm = np.sqrt(np.maximum(np.roll(kept, s, axis=(0, 1)), 1e-30 * energy.sum()))

    def add(self, rows: np.ndarray, chunk: int = 64) -> None:
        """Add basis rows: complex (k, H, W), the next positions of the scan (any k >= 0)."""
        b = np.asarray(rows)
        if b.ndim != 3 or not np.iscomplexobj(b) or b.shape[1:] != self.shape:
            raise TwinFocusError(
                f"basis rows must be complex (k, {self.shape[0]}, {self.shape[1]}), got {b.dtype} {b.shape}"
            )
        for i in range(0, b.shape[0], chunk):
            fb = scipy.fft.fft2(b[i : i + chunk], self._pad, workers=-1)
            xc = scipy.fft.ifft2(fb * self._spectrum[None], workers=-1)[:, self._rows][:, :, self._cols]
            self._sum += np.abs(xc).sum(axis=0)
        self.n_positions += b.shape[0]

    def scores(self) -> np.ndarray:
        """float64 (2 S + 1, 2 S + 1): entry [S + dy, S + dx] the score of the template moved by
        (dy, dx) pixels over the positions added so far."""
        # xc[u] = sum_p B(p) conj(T(p - u)): the template moved by +u, so index order -s..s after the roll
        return np.roll(self._sum, self.max_shift_px, axis=(0, 1)) / self._norm


def match_scores(basis: np.ndarray, template: np.ndarray, max_shift_px: int = 4, chunk: int = 64) -> np.ndarray:
    """J(s) for every integer shift s = (dy, dx) with |dy|, |dx| <= max_shift_px.

    Returns float64 (2 S + 1, 2 S + 1), S = max_shift_px (less on a small region, as
    :class:`MatchScores`), entry [S + dy, S + dx] the score of the
    template moved by (dy, dx) pixels (:func:`shift_image`'s convention). Computed for all shifts
    at once by zero-padded FFT cross-correlation, ``chunk`` positions at a time
    (:class:`MatchScores` over the whole basis).
    """
    b, t = _check(basis, template)
    acc = MatchScores(t, max_shift_px)
    acc.add(b, chunk)
    return acc.scores()


def register_template(
    basis: np.ndarray, template: np.ndarray, max_shift_px: int = 4, scores: np.ndarray | None = None
) -> tuple[np.ndarray, tuple[float, float], dict]:
    """Move a complex template to where the scan's reference is (the peak of :func:`match_scores`,
    refined to sub-pixel by a parabola through the peak and its neighbours on each axis).

    scores : J(s) of this template against this basis when already at hand (a
    :class:`MatchScores` filled as the scan arrived); computed from ``basis`` when None.

    Returns (template moved, complex64 (H, W); (dy, dx) pixels applied; info with ``score_gain``
    (J at the peak over J unmoved, >= 1) and ``at_limit`` (the peak lies on the search border:
    the template is farther off than ``max_shift_px``, widen it or check the template)).
    """
    s = _shift_limit(max_shift_px, np.shape(template))
    if scores is None:
        scores = match_scores(basis, template, max_shift_px)
    elif scores.shape != (2 * s + 1, 2 * s + 1):
        raise TwinFocusError(f"scores must be ({2 * s + 1}, {2 * s + 1}) for max_shift_px {s}, got {scores.shape}")
    i, j = np.unravel_index(int(np.argmax(scores)), scores.shape)
    at_limit = i in (0, 2 * s) or j in (0, 2 * s)
    fy = 0.0 if i in (0, 2 * s) else parabola_vertex(scores[i - 1, j], scores[i, j], scores[i + 1, j])
    fx = 0.0 if j in (0, 2 * s) else parabola_vertex(scores[i, j - 1], scores[i, j], scores[i, j + 1])
    dy, dx = i - s + fy, j - s + fx
    moved = shift_image(np.asarray(template, np.complex64), dy, dx)
    info = {
        "shift_px": [float(dy), float(dx)],
        "score_gain": float(scores[i, j] / scores[s, s]),
        "at_limit": bool(at_limit),
    }
    return moved, (float(dy), float(dx)), info


def _shift_mask(mask: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """``mask`` moved by whole pixels (dy rows, dx columns), zero-filled (no wrap-around)."""
    out = np.zeros_like(mask)
    h, w = mask.shape
    out[max(dy, 0) : h + min(dy, 0), max(dx, 0) : w + min(dx, 0)] = mask[
        max(-dy, 0) : h + min(-dy, 0), max(-dx, 0) : w + min(-dx, 0)
    ]
    return out


#: how :func:`outline_phases` picks one of its starts' ends: "energy", the largest share F of the
#: image's energy inside the outline; "speckle", the smallest contrast of that energy over the
#: outline (:func:`speckle_contrast`); "auto", the largest share unless that end has piled its
#: energy into a few bright pixels (contrast above :data:`PILED_CONTRAST`), then the smallest
#: contrast. Every end holds about as much energy inside (0.93-0.97), so on a rough reference the
#: share cannot tell a focused end from a piled one and the contrast can; on a speckled one (every
#: scatterer's phase anywhere on the circle) every end's contrast lies at 2.0-2.9 and the least of
#: them is the most smeared. Same draws of the family bench
#: (390 positions, 64 x 64 pixels; docs/digital_twin_field.md), mean target SSIM:
#: rough references energy 0.707, speckle 0.774, auto 0.776; speckled ones 0.811, 0.701, 0.811;
#: smooth ones (every scatterer in phase) 0.661, 0.662, 0.663, where no rule holds
OUTLINE_CHOICES = ("energy", "speckle", "auto")
OUTLINE_CHOICE = "auto"
#: above this contrast an end has piled its energy (rough references on the family bench: focused
#: ends 1.4-2.8, piled 3.2-9.0; every end on a speckled one 2.0-2.9)
PILED_CONTRAST = 3.0
#: random starts besides zeros: the ends of low contrast are a few of many (3-5 of 25 on the
#: field bench's draws), so more starts find one more often; all run in one matrix product
OUTLINE_STARTS = 24


def speckle_contrast(energy: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """mean(e^2) / mean(e)^2 of each row's energy over its mask: float64 (S,).

    energy : float (S, P) |image|^2 of S estimates on P pixels; masks : float or bool (S, P), 1
    inside each estimate's outline. A rough reference focused right is speckle over its outline:
    e about exponentially distributed, contrast near 2 (2.3-2.6 on the field scenes, where the
    outline holds some of the edge's dark pixels). An end that has raised the outline criterion by
    piling the energy into a few bright pixels has a larger one (3.5-7.5 on the same scenes).
    """
    e = np.asarray(energy, dtype=np.float64)
    w = np.asarray(masks, dtype=np.float64)
    n = np.maximum(w.sum(axis=1), 1.0)
    first = (w * e).sum(axis=1) / n
    second = (w * e * e).sum(axis=1) / n
    return second / np.maximum(first * first, 1e-300)


def outline_phase(basis: np.ndarray, support: np.ndarray, **options: Any) -> tuple[np.ndarray, dict]:
    """Per-position phases that put the reference's energy inside its outline.

    Maximises the fraction of the image's energy inside the support S,
    F(phi) = sum_{p in S} |I_p|^2 / sum_p |I_p|^2 with I = sum_m exp(j phi_m) B_m, by projections:
    T = I restricted to S, then the closed form phi_m = angle <B_m, T> (each step raises the energy
    inside S; every step is on the unit circle, so wrapped errors cost nothing more). Between
    ``rounds`` the outline is moved by the whole-pixel shift (up to ``max_shift_px``) that holds the
    most of the current image's energy: a camera cloud sits a few millimetres off where the radar
    sees the reference. All starts (zeros and ``starts`` random ones, fixed ``seed``) run at once
    (one matrix product per step). F has many maxima of about the same height, most of them with
    the energy piled into a few bright pixels rather than spread as a rough reference's speckle;
    ``choose`` "energy" returns the end with the largest F, "speckle" the one whose energy has the
    smallest contrast over its outline (:func:`speckle_contrast`), "auto" (:data:`OUTLINE_CHOICE`)
    the largest F unless that end's contrast shows its energy piled (:data:`PILED_CONTRAST`).

    basis : complex (M, H, W); support : bool (H, W), True inside the reference's outline (e.g.
    :attr:`twinfocus.twins.digital_twin.condition.DigitalTwinReference.support`); options :
    ``starts``, ``iterations``, ``rounds``, ``max_shift_px``, ``seed`` and ``choose``, as (and
    with the defaults of) :func:`outline_phases`.

    Returns (float64 (M,) radians, info: ``energy_inside`` and ``contrast`` per start, ``chosen``
    start, ``chosen_by`` ("energy" or "speckle"), ``support_shift_px`` (dy, dx) of the chosen
    start's outline).
    """
    ((phi, info),) = outline_phases(basis, [support], **options)
    return phi, info


def outline_phases(
    basis: np.ndarray,
    supports: list[np.ndarray],
    starts: int = OUTLINE_STARTS,
    iterations: int = 20,
    rounds: int = 3,
    max_shift_px: int = 3,
    seed: int = 0,
    choose: str = OUTLINE_CHOICE,
) -> list[tuple[np.ndarray, dict]]:
    """:func:`outline_phase` for several outlines of one reference at once: each outline's run is
    what :func:`outline_phase` gives for it alone (the same starts), but all the runs' starts share
    every matrix product, which a wider product does in about half the time per start (four
    outlines x 13 starts: 1.8x faster than four calls). supports : list of K bool (H, W). Returns
    K (phase, info) pairs, in the order of ``supports``."""
    b = np.asarray(basis)
    if b.ndim != 3 or not np.iscomplexobj(b):
        raise TwinFocusError(f"basis must be complex (M, H, W), got {b.dtype} {b.shape}")
    base = [np.asarray(sup, dtype=bool) for sup in supports]
    if not base:
        raise TwinFocusError("outline_phases needs at least one outline")
    for mask in base:
        if mask.shape != b.shape[1:]:
            raise TwinFocusError(f"support is {mask.shape} but the reference region is {b.shape[1:]}")
        if not mask.any() or mask.all():
            raise TwinFocusError("the reference's outline must cover some but not all of the reference region")
    if min(int(starts), int(iterations), int(rounds), int(max_shift_px)) < 0 or int(iterations) < 1 or int(rounds) < 1:
        raise TwinFocusError("outline estimator: iterations and rounds must be >= 1, starts and max_shift_px >= 0")
    if choose not in OUTLINE_CHOICES:
        raise TwinFocusError(f"outline estimator: choose must be one of {', '.join(OUTLINE_CHOICES)}, got {choose!r}")
    m = b.shape[0]
    flat = b.reshape(m, -1)
    rng = np.random.default_rng(seed)
    first = np.vstack([np.zeros((1, m)), rng.uniform(-np.pi, np.pi, (int(starts), m))])  # (S, M)
    per = first.shape[0]
    phi = np.tile(first, (len(base), 1))  # every outline from the same starts: (K S, M)
    n = phi.shape[0]
    shifts = [(0, 0)] * n
    masks = np.vstack([np.repeat(mask.reshape(1, -1), per, axis=0) for mask in base]).astype(np.float32)  # (K S, P)
    r = int(max_shift_px)
    offsets = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
    # the shifted outlines reach only the pixels within r of the unshifted ones, so the image is
    # needed only there (a third of the region for a letter); every shift of each outline, on
    # those pixels, once for all rounds
    from scipy import ndimage  # heavy: only the outline paths load it

    reach = ndimage.binary_dilation(np.logical_or.reduce(base), structure=np.ones((2 * r + 1, 2 * r + 1), bool))
    reach = reach.reshape(-1)
    shifted = [
        np.stack([_shift_mask(mask, dy, dx).reshape(-1)[reach] for dy, dx in offsets]).astype(np.float64)
        for mask in base
    ]  # K x (shifts, reach pixels)
    for rnd in range(int(rounds)):
        # T_s is zero outside its outline, so the steps need the image only on the pixels some
        # start's outline covers (a letter: 10-30 % of the region, as much faster)
        cover = masks.any(axis=0)
        sub, sub_masks = np.ascontiguousarray(flat[:, cover]), masks[:, cover]
        for _ in range(int(iterations)):
            image = np.exp(1j * phi).astype(np.complex64) @ sub  # (S, P inside)
            # angle <B_m, T_s> = -angle (B_m . conj T_s), for all starts in one product
            phi = -np.angle((sub @ np.conj(sub_masks * image).T).T).astype(np.float64)
        if rnd == int(rounds) - 1 or r == 0:
            break
        # the energy each whole-pixel shift of each outline holds, all shifts in one product
        energy = (np.abs(np.exp(1j * phi).astype(np.complex64) @ flat[:, reach]) ** 2).astype(np.float64)
        for k, mask in enumerate(base):
            rows = slice(k * per, (k + 1) * per)
            held = energy[rows] @ shifted[k].T  # (S, shifts)
            # the last of equal maxima, as max() over (energy, dy, dx) in this order would pick
            best = len(offsets) - 1 - np.argmax(held[:, ::-1], axis=1)
            for i, j in zip(range(rows.start, rows.stop), best):
                shifts[i] = offsets[j]
                masks[i] = _shift_mask(mask, *offsets[j]).reshape(-1)
    energy = (np.abs(np.exp(1j * phi).astype(np.complex64) @ flat) ** 2).astype(np.float64)
    inside = (masks * energy).sum(axis=1) / np.maximum(energy.sum(axis=1), 1e-300)
    contrast = speckle_contrast(energy, masks)
    out = []
    for k in range(len(base)):
        rows = slice(k * per, (k + 1) * per)
        chosen = int(np.argmax(inside[rows]))
        rule = "energy"
        if choose == "speckle" or (choose == "auto" and contrast[rows][chosen] > PILED_CONTRAST):
            chosen, rule = int(np.argmin(contrast[rows])), "speckle"
        out.append(
            (
                phi[rows][chosen].copy(),
                {
                    "energy_inside": [round(float(v), 4) for v in inside[rows]],
                    "contrast": [round(float(v), 3) for v in contrast[rows]],
                    "chosen": chosen,
                    "chosen_by": rule,
                    "support_shift_px": [int(v) for v in shifts[k * per + chosen]],
                },
            )
        )
    return out


#: the outlines :func:`grown_outlines` draws from an estimate's image (docs/digital_twin.md): closings
#: of these radii (px), kept to the bright pixels ...
OUTLINE_CLOSING_RADII_PX = (3, 6)
#: ... and growth into the pixels brighter than these fractions of the median inside the outline ...
OUTLINE_GROW_FRACTIONS = (0.2, 0.3)
#: ... reachable from the outline within this many pixels (4-connected steps)
OUTLINE_GROW_REACH_PX = 6
#: "bright" for the closings: above this fraction of the median energy inside the outline
OUTLINE_BRIGHT_FRACTION = 0.2


def _disk(radius_px: int) -> np.ndarray:
    y, x = np.mgrid[-radius_px : radius_px + 1, -radius_px : radius_px + 1]
    return np.hypot(y, x) <= radius_px


def grown_outlines(
    support: np.ndarray,
    energy: np.ndarray,
    shift_px: tuple[int, int] | list[int] = (0, 0),
    closing_radii_px: tuple[int, ...] = OUTLINE_CLOSING_RADII_PX,
    grow_fractions: tuple[float, ...] = OUTLINE_GROW_FRACTIONS,
    reach_px: int = OUTLINE_GROW_REACH_PX,
    bright_fraction: float = OUTLINE_BRIGHT_FRACTION,
) -> list[np.ndarray]:
    """Outlines grown into the pixels that an estimate's image lights up.

    A camera cloud with holes gives an outline 20-30 % short of the reference; where the first
    estimate's image is bright next to the outline, the reference is likely there too. With the
    outline moved where the estimate put it (``shift_px``, :func:`outline_phase`'s
    ``support_shift_px``) and "bright" meaning above a fraction of the median energy inside it:

    * for each radius r in ``closing_radii_px``: the outline closed by a disk of radius r (its gaps
      and notches up to ~2 r filled), keeping only the filled pixels that are bright;
    * for each fraction f in ``grow_fractions``: the outline grown into the connected pixels above
      f of the median, no farther than ``reach_px`` pixels from it.

    Each is moved back by -``shift_px`` and joined with ``support``, so it never loses a pixel of
    the cloud's outline. No single growth is reliably better (a change of 1-2 % of the outline can
    move the estimate to another maximum); :func:`averaged_outline_phase` averages over them.

    support : bool (H, W) the outline; energy : float (H, W) |image|^2 of the estimate on the same
    grid; shift_px : (dy, dx) whole pixels. Returns a list of bool (H, W), closings first.
    """
    from scipy import ndimage  # heavy: only the outline paths load it

    mask = np.asarray(support, dtype=bool)
    e = np.asarray(energy, dtype=np.float64)
    if e.shape != mask.shape:
        raise TwinFocusError(f"energy is {e.shape} but the outline is {mask.shape}")
    if not np.isfinite(e).all() or (e < 0).any():
        raise TwinFocusError("energy must be finite and >= 0 (|image|^2)")
    dy, dx = (int(v) for v in shift_px)
    moved = _shift_mask(mask, dy, dx)
    if not moved.any():
        raise TwinFocusError(f"the outline moved by ({dy}, {dx}) px leaves the region")
    level = float(np.median(e[moved]))
    out = []
    for r in closing_radii_px:
        r = int(r)
        if r < 1:
            raise TwinFocusError(f"closing radii must be >= 1 px, got {r}")
        # padded so the closing does not stick to the region's border
        closed = ndimage.binary_closing(np.pad(moved, r + 1), structure=_disk(r))[r + 1 : -r - 1, r + 1 : -r - 1]
        kept = (closed & (e > bright_fraction * level)) | moved
        out.append(_shift_mask(kept, -dy, -dx) | mask)
    for f in grow_fractions:
        within = ((e > float(f) * level) | moved) & ndimage.binary_dilation(moved, iterations=int(reach_px))
        out.append(_shift_mask(ndimage.binary_propagation(moved, mask=within), -dy, -dx) | mask)
    return out


#: rounds of :func:`grown_outline` before the averaged estimate (docs/digital_twin_autofocus.md, "Growing the
#: outline first"): field bench B placed by the truth 0.925 with none, 0.969 with two
OUTLINE_GROWTH_ROUNDS = 2


def grown_outline(
    basis: np.ndarray, support: np.ndarray, growth_rounds: int = OUTLINE_GROWTH_ROUNDS, **outline_options
) -> tuple[np.ndarray, list[int]]:
    """The cloud's outline grown round by round into the pixels its estimates light up.

    Each round runs :func:`outline_phase` on the current outline and joins it with all of
    :func:`grown_outlines` from that estimate's image. A hole a camera left at the reference's
    edge is wider than one growth reaches (6 px); the estimate from a fuller outline lights up
    more of it, so the next round reaches farther (field bench, the reference's outline 1266 px:
    the cloud's covers 990-1010 of it, two rounds 1110-1220). The outline never loses a pixel.

    basis : complex (M, H, W); support : bool (H, W); growth_rounds >= 0; outline_options : passed
    to :func:`outline_phase` (its own ``rounds`` among them). Returns (bool (H, W) outline, its pixel
    count before and after each growth round).
    """
    if int(growth_rounds) < 0:
        raise TwinFocusError(f"outline growth rounds must be >= 0, got {growth_rounds}")
    mask = np.asarray(support, dtype=bool)
    sizes = [int(mask.sum())]
    for _ in range(int(growth_rounds)):
        phi, info = outline_phase(basis, mask, **outline_options)
        energy = np.abs(form_image(basis, phi)) ** 2
        mask = np.logical_or.reduce(grown_outlines(mask, energy, info["support_shift_px"]))
        sizes.append(int(mask.sum()))
    return mask, sizes


def averaged_outline_phase(
    basis: np.ndarray,
    support: np.ndarray,
    aperture_m: np.ndarray,
    growth_rounds: int = OUTLINE_GROWTH_ROUNDS,
    **outline_options,
) -> tuple[np.ndarray, dict]:
    """:func:`outline_phase` with the cloud's outline, first grown by ``growth_rounds`` of
    :func:`grown_outline`, and with the outlines grown from its estimate's image
    (:func:`grown_outlines`; their runs as one batch, :func:`outline_phases`), the estimates
    averaged.

    Each outline puts the estimate in a maximum of the energy criterion; for outlines that differ
    by a few pixels these maxima differ, and the criterion cannot tell which is right (on camera
    clouds each outline alone gains on some draws and loses up to 0.08 SSIM on others). Their
    average keeps most of the gains and seldom loses (docs/digital_twin.md). The estimates are
    first lined up: a constant + linear-in-aperture phase only moves the image, and each outline
    sits where it pulls its estimate, so the ramp of each one's difference from the first
    (:func:`~twinfocus.focus.phase_ramp.fit_linear_phase`) is taken out; the average is then that of
    unit phasors (a circular mean: wrapped phases average right).

    basis : complex (M, H, W); support : bool (H, W) the reference's outline; aperture_m : float
    (M, 2) each position's (x, y) in the aperture plane, metres; outline_options : passed to every
    :func:`outline_phase` run.

    Returns (float64 (M,) radians, info: ``first`` (the grown outline's run, :func:`outline_phase`'s
    info), ``outlines_px`` (pixels in each outline, the grown one first), ``growth_px`` (the cloud's
    outline's pixels before and after each growth round), ``energy_inside`` (each run's
    chosen start's F), ``support_shift_px`` (each run's (dy, dx)), ``agreement`` (mean over positions
    of |sum of the aligned phasors| / their number: 1 when all agree)).
    """
    b = np.asarray(basis)
    ap = np.asarray(aperture_m, dtype=np.float64)
    if b.ndim != 3 or ap.shape != (b.shape[0], 2):
        raise TwinFocusError(
            f"aperture_m must be (M, 2), one (x, y) in metres per radar position of the basis {b.shape}, got {ap.shape}"
        )
    if not np.isfinite(ap).all():
        raise TwinFocusError("aperture_m holds NaN or inf")
    support, growth = grown_outline(b, support, growth_rounds, **outline_options)
    first, info = outline_phase(b, support, **outline_options)
    energy = np.abs(form_image(b, first)) ** 2
    outlines = [support, *grown_outlines(support, energy, info["support_shift_px"])]
    runs = [(first, info), *outline_phases(b, outlines[1:], **outline_options)]
    acc = np.zeros(b.shape[0], np.complex128)
    for phi, _ in runs:
        ramp, _ = fit_linear_phase(phi - first, ap)
        acc += np.exp(1j * (phi - ramp))
    return np.angle(acc), {
        "first": info,
        "outlines_px": [int(m.sum()) for m in outlines],
        "growth_px": growth,
        "energy_inside": [r[1]["energy_inside"][r[1]["chosen"]] for r in runs],
        "support_shift_px": [r[1]["support_shift_px"] for r in runs],
        "agreement": round(float(np.abs(acc).mean() / len(runs)), 4),
    }
