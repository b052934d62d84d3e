"""Materials of scene objects and occluders: radar reflectivity, two-way attenuation of a sheet,
camera colour."""

from __future__ import annotations

from dataclasses import dataclass

from twinfocus.errors import TwinFocusError


@dataclass(frozen=True)
class Material:
    """Radar and camera properties of a material.

    reflectivity : backscatter amplitude relative to metal (metal = 1).
    two_way_attenuation_db : loss of a return that crosses a sheet of this material on the way
        in and out, in dB (inf: opaque to the radar).
    colour_bgr : default colour for the camera renderer (OpenCV order).
    """

    name: str
    reflectivity: float
    two_way_attenuation_db: float
    colour_bgr: tuple[int, int, int]


# Nominal values, not measurements. Reflectivities are of the order of the normal-incidence
# Fresnel amplitude |1 - sqrt(er)| / (1 + sqrt(er)) at W-band (plastics er ~ 2.3 -> 0.2; dry wood
# er ~ 2 - 3, raised by moisture and grain -> 0.3) and are used as contrast between materials.
# Attenuations are round two-way numbers for thin sheets (single layer of clothing, a few sheets
# of paper, a 2 - 3 mm plastic panel, corrugated board): mm-wave screening works because these
# pass most of the power; change them per experiment with Occluder(attenuation_db=...).
MATERIALS: dict[str, Material] = {
    m.name: m
    for m in (
        Material("metal", 1.0, float("inf"), (190, 190, 190)),
        Material("wood", 0.3, 10.0, (60, 120, 170)),
        Material("plastic", 0.15, 3.0, (60, 60, 200)),
        Material("polyester", 0.05, 2.0, (170, 110, 60)),
        Material("cloth", 0.05, 2.0, (150, 150, 210)),
        Material("paper", 0.05, 3.0, (235, 240, 245)),
        Material("cardboard", 0.1, 5.0, (100, 150, 190)),
    )
}


def material(name: str) -> Material:
    """The :class:`Material` called ``name`` (TwinFocusError listing the known ones otherwise)."""
    try:
        return MATERIALS[name]
    except (KeyError, TypeError):
        raise TwinFocusError(f"unknown material {name!r}; known: {', '.join(sorted(MATERIALS))}") from None
