"""Scenes for the radar simulator and the digital twin's camera renderer.

A :class:`Scene` holds objects (flat masks such as metal letters, or point clouds), occluders
(sheets of cloth, paper, plastic that attenuate what lies behind them and hide it from the
camera) and optional clutter. The radar simulator asks it for point scatterers
(:meth:`Scene.scatterers`); a camera renderer uses the same objects' masks, corners, colours and
textures.

Geometry (docs/architecture.md section 4): scene frame x, y across the aperture, z from the aperture into
the scene. A planar object's own frame has u along its mask's columns, v along its mask's rows
(downwards in the raster) and lies in the plane w = 0; ``rotation`` maps (u, v, w) to the scene,
so the identity puts the mask upright as seen from the radar (u -> +x, v -> +y: x right, y down,
z forward, the camera convention) and the plane faces the radar (normal towards -z).

Modules: ``materials`` (reflectivity, attenuation, colour), ``scatterers`` (scatterer spacing,
rough-surface amplitudes), ``objects`` (:class:`PlanarObject`, :class:`PointCloudObject`),
``letters`` (Hershey-font letters), ``plates`` (rectangle, card, disc), ``tools`` (plates and
tools of a letter's size by name: plate, disc, washer, wrench, key), ``curved`` (cylinder
section, bent plate), ``occluders``, ``clutter``, ``assembly`` (:class:`Scene`), ``paper`` (the
paper's two-letter scene), ``checks`` (argument checks). Import the names from here.
"""

from twinfocus.scene.assembly import Scene
from twinfocus.scene.clutter import Clutter
from twinfocus.scene.curved import SHAPES, bent_plate, cylinder_section, shaped
from twinfocus.scene.letters import FONTS, letter, letter_mask
from twinfocus.scene.materials import MATERIALS, Material, material
from twinfocus.scene.objects import PlanarObject, PointCloudObject, SceneObject, from_points
from twinfocus.scene.occluders import Occluder
from twinfocus.scene.paper import paper_scene
from twinfocus.scene.plates import card, disc, rectangle
from twinfocus.scene.scatterers import DEFAULT_SPACING_M, rough_amplitudes, scatterer_spacing_m
from twinfocus.scene.tools import OBJECT_SHAPES, shape_mask, shaped_object

__all__ = [
    "DEFAULT_SPACING_M",
    "FONTS",
    "MATERIALS",
    "OBJECT_SHAPES",
    "SHAPES",
    "Clutter",
    "Material",
    "Occluder",
    "PlanarObject",
    "PointCloudObject",
    "Scene",
    "SceneObject",
    "bent_plate",
    "card",
    "cylinder_section",
    "disc",
    "from_points",
    "letter",
    "letter_mask",
    "material",
    "paper_scene",
    "rectangle",
    "rough_amplitudes",
    "scatterer_spacing_m",
    "shape_mask",
    "shaped",
    "shaped_object",
]
