"""The source paper's scene: a reference letter and a target letter side by side, optionally
behind a sheet and in a cluttered room."""

from __future__ import annotations

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.scene.assembly import Scene
from twinfocus.scene.checks import positive
from twinfocus.scene.clutter import Clutter
from twinfocus.scene.letters import LetterStyle, letter
from twinfocus.scene.occluders import Occluder
from twinfocus.scene.tools import OBJECT_SHAPES, shaped_object


def paper_scene(
    reference: str = "A",
    target: str = "F",
    distance_m: float = 0.6,
    separation_deg: float = 10.0,
    height_m: float = 0.127,
    reference_distance_m: float | None = None,
    reference_material: str = "metal",
    target_material: str = "metal",
    occluder: str | Occluder | None = None,
    occluder_distance_m: float | None = None,
    clutter: bool | Clutter = False,
    style: LetterStyle | None = None,
) -> Scene:
    """The paper's two-letter scene: a reference letter on the -x side, the target on +x.
    ``reference`` and ``target`` are letters, or plates and tools by their names in
    :data:`twinfocus.scene.tools.OBJECT_SHAPES` ("plate", "disc", "washer", "wrench", "key"),
    ``height_m`` tall like a letter.

    Both letters face the radar, centred at y = 0 on the planes z = ``reference_distance_m``
    (default ``distance_m``) and z = ``distance_m``; seen from the aperture centre (the origin)
    their centres lie at -separation/2 and +separation/2 from boresight, so they are
    ``separation_deg`` apart. For the defaults (A and F, 127 mm, 0.6 m, 10 degrees) the reference
    lies inside x [-0.15, 0], the target inside x [0.02, 0.13], both inside y [-0.11, 0.12] (the
    regions of interest of docs/architecture.md section 2).

    occluder : None, a material name (a sheet of it is put ``occluder_distance_m`` from the
        aperture, default 10 cm in front of the target, covering the target with a 2 cm margin
        as seen from the aperture centre) or an :class:`Occluder`.
    clutter : False, True (:meth:`Clutter.room`) or a :class:`Clutter`.
    style : how the letters are drawn (:class:`~twinfocus.scene.letters.LetterStyle`; None: its defaults).

    Objects are named ``"reference"`` and ``"target"``.
    """
    style = style or LetterStyle()
    distance_m = positive("distance_m", distance_m)
    ref_z = distance_m if reference_distance_m is None else positive("reference_distance_m", reference_distance_m)
    sep = float(separation_deg)
    if not (np.isfinite(sep) and 0 <= sep < 170):
        raise TwinFocusError(f"separation_deg must lie in [0, 170), got {separation_deg!r}")
    half = np.deg2rad(sep / 2.0)

    def cut_out(what: str, centre: tuple, material: str, name: str):
        if what in OBJECT_SHAPES:
            return shaped_object(what, height_m, centre, material, name=name)
        return letter(what, height_m, centre, material, style.font, style.stroke_m, style.width_scale, name=name)

    ref = cut_out(reference, (-ref_z * np.tan(half), 0.0, ref_z), reference_material, "reference")
    tgt = cut_out(target, (distance_m * np.tan(half), 0.0, distance_m), target_material, "target")
    occluders = []
    if isinstance(occluder, Occluder):
        occluders.append(occluder)
    elif occluder is not None:
        z_occ = (
            distance_m - 0.1 if occluder_distance_m is None else positive("occluder_distance_m", occluder_distance_m)
        )
        if not z_occ < distance_m:
            raise TwinFocusError(
                f"occluder_distance_m ({z_occ}) must be less than the target's distance ({distance_m})"
            )
        corners = tgt.corners_m()
        scaled = corners * (z_occ / corners[:, 2:3])  # project the target's outline onto the sheet's plane
        lo, hi = scaled[:, :2].min(axis=0), scaled[:, :2].max(axis=0)
        margin = 0.02
        centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, z_occ])
        occluders.append(Occluder(centre, (hi[0] - lo[0] + 2 * margin, hi[1] - lo[1] + 2 * margin), material=occluder))
    room: Clutter | None
    if clutter is True:
        room = Clutter.room(max(distance_m, ref_z))
    elif clutter is False or clutter is None:
        room = None
    elif isinstance(clutter, Clutter):
        room = clutter
    else:
        raise TwinFocusError(f"clutter must be True, False or a Clutter, got {clutter!r}")
    return Scene([ref, tgt], occluders, room)
