"""The experiments of the source paper's evaluation (section 6), as data.

An :class:`Experiment` is a list of :class:`Condition` (one point of a sweep), each with the
reference-target pairs it is run on; every pair is one simulated scene and gets ``draws``
tracking-error draws. Conditions that differ only in their tracking error (``errors``) or in the
template's room (``template_env``) share the scene and its draws' sub-image bases.

Every scene carries the impairments of :class:`~twinfocus.simulation.scenario.Scenario`'s defaults:
speckle (random scatterer phases), 10 dB per-sample thermal noise, x/y/z tracking error, a
physical twin captured separately with a 1 mm placement error; the digital twin comes from the
rendered stereo pair. Sweeps beyond the paper's range (for the limits) are marked
``in_paper=False``.

``roi="paper"`` uses the paper's regions of interest (docs/architecture.md section 2, the baseline set); ``roi="object"`` frames
each letter by its extent + 40 mm (about what the paper's regions leave around the default
letters), never past the middle of the gap between the letters, so the conditions of a sweep are
framed alike.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from twinfocus.errors import TwinFocusError

INCH_M = 0.0254
MM = 1e-3
BASELINE_LETTERS = ("A", "C", "F", "R", "X", "Z")
BASELINE_PAIRS = tuple((r, t) for r in BASELINE_LETTERS for t in BASELINE_LETTERS if r != t)
#: Two pairs of the baseline set for the tracking-error sweep (the paper sweeps the whole set).
TRACKING_PAIRS = (("A", "C"), ("R", "X"))
ALL_METHODS = ("none", "sharpness", "physical", "digital")
TWIN_METHODS = ("none", "physical", "digital")


def sigma3(sigma_mm: float) -> tuple:
    """The same standard deviation on x, y and z, metres."""
    return (sigma_mm * MM,) * 3


@dataclass(frozen=True)
class Condition:
    """One point of an experiment.

    scene : :class:`~twinfocus.evaluation.cases.EvalScenario` fields that shape the scene.
    errors : fields of the tracking error (``error_model``, ``error_sigma_m``) for the draws.
    pairs : (reference, target) letters; one scene each.
    methods : overrides the experiment's methods for this condition.
    """

    label: str
    x: float | str
    pairs: tuple
    scene: dict = field(default_factory=dict)
    errors: dict = field(default_factory=dict)
    template_env: str = "open"
    in_paper: bool = True
    methods: tuple | None = None

    def to_dict(self) -> dict:
        return {
            "label": self.label,
            "x": self.x,
            "pairs": [list(p) for p in self.pairs],
            "scene": self.scene,
            "errors": {k: list(v) if isinstance(v, tuple) else v for k, v in self.errors.items()},
            "template_env": self.template_env,
            "in_paper": self.in_paper,
            "methods": list(self.methods) if self.methods else None,
        }


@dataclass
class Experiment:
    name: str
    title: str
    axis: str
    conditions: list
    draws: int
    methods: tuple = TWIN_METHODS
    roi: str = "object"
    numeric: bool = False
    seed: int = 0
    roi_margin_m: float = 0.04

    def n_draws(self) -> int:
        return sum(len(c.pairs) for c in self.conditions) * self.draws

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "title": self.title,
            "axis": self.axis,
            "draws": self.draws,
            "methods": list(self.methods),
            "roi": self.roi if self.roi == "paper" else f"object+{self.roi_margin_m * 1e3:g}mm",
            "numeric": self.numeric,
            "seed": self.seed,
            "conditions": [c.to_dict() for c in self.conditions],
        }


def _full_experiments() -> list[Experiment]:
    return _geometry_experiments() + _object_experiments() + _room_experiments()


def _geometry_experiments() -> list[Experiment]:
    """The baseline set and the sweeps of the scan's geometry: tracking error, separation, distance."""
    kp = (("K", "P"),)
    return [
        Experiment(
            "baseline",
            "Baseline set: six letters, all ordered pairs",
            "set",
            [Condition("60 cm, 10 deg, sigma 0.5 mm", "baseline", BASELINE_PAIRS)],
            draws=1,
            methods=ALL_METHODS,
            roi="paper",
        ),
        Experiment(
            "tracking_error",
            "Tracking error (x, y, z sigma)",
            "tracking error sigma (mm)",
            [
                Condition(f"{s:g} mm", s, TRACKING_PAIRS, errors={"error_sigma_m": sigma3(s)}, in_paper=0.5 <= s <= 2.0)
                for s in (0.5, 1.0, 1.5, 2.0, 3.0)
            ],
            draws=1,
            roi="paper",
            numeric=True,
        ),
        Experiment(
            "separation",
            "Reference-target angular separation",
            "separation (deg)",
            [
                Condition(f"{a} deg", a, kp, scene={"separation_deg": float(a)}, in_paper=a <= 20)
                for a in (10, 15, 20, 30, 40)
            ],
            draws=1,
            numeric=True,
        ),
        Experiment(
            "distance",
            "Object-radar distance",
            "distance (cm)",
            [Condition(f"{d} cm", d, kp, scene={"distance_m": d / 100}) for d in (40, 60, 80)],
            draws=1,
            numeric=True,
        ),
    ]


def _object_experiments() -> list[Experiment]:
    """The sweeps of the objects: size, size ratio, material, a sheet in front."""
    return [
        Experiment(
            "size",
            "Target size (3 in reference N)",
            "target",
            [
                Condition(
                    f"{h} in ({t})",
                    f"{h} in",
                    (("N", t),),
                    scene={"height_m": 3 * INCH_M, "target_height_m": h * INCH_M},
                )
                for h, t in ((4, "B"), (5, "X"), (6, "H"))
            ],
            draws=1,
        ),
        Experiment(
            "size_ratio",
            "Target/reference size ratio (target H, 3 in reference N)",
            "size ratio",
            [
                Condition(
                    f"{h:g} in (x{h / 3:.2f})",
                    round(h / 3, 3),
                    (("N", "H"),),
                    scene={"height_m": 3 * INCH_M, "target_height_m": h * INCH_M},
                    in_paper=False,
                )
                for h in (3, 6, 8)
            ],
            draws=1,
            numeric=True,
        ),
        Experiment(
            "material",
            "Target material (metal reference M, target K)",
            "target material",
            [Condition(m, m, (("M", "K"),), scene={"target_material": m}) for m in ("metal", "wood", "plastic")],
            draws=1,
        ),
        Experiment(
            "nlos",
            "Target hidden behind a sheet (reference in line of sight at 76 cm)",
            "occluder",
            [
                Condition(
                    m, m, (("M", "K"),), scene={"occluder": m, "height_m": 4 * INCH_M, "reference_distance_m": 0.76}
                )
                for m in ("polyester", "paper", "plastic")
            ],
            draws=1,
        ),
    ]


def _room_experiments() -> list[Experiment]:
    """The room around the objects (open or cluttered, templates swapped) and the handheld sweep."""
    return [
        Experiment(
            "environment",
            "Open vs cluttered room, templates swapped across rooms",
            "room / template",
            [
                Condition(
                    "open room, open template",
                    "open/open",
                    (("U", "G"),),
                    scene={"clutter": False, "clutter_near_m": 0.03},
                ),
                Condition(
                    "open room, cluttered-room template",
                    "open/cluttered",
                    (("U", "G"),),
                    scene={"clutter": False, "clutter_near_m": 0.03},
                    template_env="cluttered",
                    methods=("none", "physical"),
                ),
                Condition(
                    "cluttered room, cluttered-room template",
                    "cluttered/cluttered",
                    (("U", "G"),),
                    scene={"clutter": True, "clutter_near_m": 0.03},
                    template_env="cluttered",
                ),
                Condition(
                    "cluttered room, open template",
                    "cluttered/open",
                    (("U", "G"),),
                    scene={"clutter": True, "clutter_near_m": 0.03},
                    methods=("none", "physical"),
                ),
            ],
            draws=1,
        ),
        Experiment(
            "handheld",
            "Handheld zig-zag sweep with VIO-like drift",
            "trajectory",
            [
                Condition(
                    "zig-zag, VIO drift + jitter",
                    "zigzag/vio",
                    (("K", "P"), ("K", "M")),
                    scene={"trajectory": "zigzag"},
                    errors={"error_model": "vio"},
                )
            ],
            draws=1,
        ),
    ]


EXPERIMENT_NAMES = tuple(e.name for e in _full_experiments())
#: Experiments that show where the methods stop helping, with the sweep variable.
LIMIT_SWEEPS = {"tracking_error": "tracking error", "separation": "angular separation", "size_ratio": "size ratio"}


def paper_experiments(quick: bool = False, draws: int | None = None, only=None) -> list[Experiment]:
    """The experiment list.

    quick : the smoke set (two baseline pairs, two tracking errors on one pair) unless ``only``
        names others, which then run on their first pair with one draw.
    draws : error draws per pair and condition for every experiment (default 1; the paper used 5,
        as ``make bench-paper`` does: docs/performance.md, "Evaluation time", has how long).
    only : names to keep (``trade`` is handled by the runner).
    """
    exps = _full_experiments()
    wanted = None if not only else [n for n in only if n != "trade"]
    if wanted is not None:
        unknown = sorted(set(wanted) - set(EXPERIMENT_NAMES))
        if unknown:
            raise TwinFocusError(
                f"unknown experiment(s) {', '.join(unknown)}; choose from {', '.join(EXPERIMENT_NAMES + ('trade',))}"
            )
        exps = [e for e in exps if e.name in wanted]
    if quick:
        out = []
        for e in exps:
            if e.name == "baseline":
                e.conditions = [replace(e.conditions[0], pairs=(("A", "F"), ("F", "A")))]
            elif e.name == "tracking_error":
                e.conditions = [replace(c, pairs=(("A", "F"),)) for c in e.conditions if c.x in (0.5, 2.0)]
            elif wanted is None:
                continue
            else:
                e.conditions = [replace(c, pairs=c.pairs[:1]) for c in e.conditions]
            e.draws = 1
            out.append(e)
        exps = out
    if draws is not None:
        if int(draws) < 1:
            raise TwinFocusError(f"--draws must be at least 1, got {draws}")
        for e in exps:
            e.draws = int(draws)
    return exps
