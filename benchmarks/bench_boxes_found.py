"""Boxes found against boxes typed: ``twinfocus focus`` with neither ``--reference-roi`` nor
``--target-roi`` (twinfocus/focus/boxes.py), on the demo scene and a few others of its family.

For each scene: ``twinfocus simulate`` (the full 6 x 130 raster), then ``twinfocus focus
--template-scan`` twice at ``--size 100``, once with the boxes typed (the demo's: the paper's
regions, the Makefile's; the others: :meth:`twinfocus.simulation.scenario.Scenario.reference_roi` /
``target_roi``, each letter's extent grown by 1.5 cm) and once with both left out. Recorded:
each found region's edges and depth less the letter's (the truth: the scene's object corners,
:meth:`twinfocus.scene.PlanarObject.corners_m`, and its centre's depth), whether the two found
regions overlap, the target's SSIM against the truth image both ways, and the run's time.

Writes ``boxes_found.json`` (with the machine and its load) to the output folder.
Run: ``python -m benchmarks.bench_boxes_found --out benchmarks/results`` (about 4 min on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from twinfocus.cli import main as cli
from twinfocus.focus.boxes import overlap
from twinfocus.io.atomic import write_text_atomic
from twinfocus.jobs.machine import machine_info
from twinfocus.simulation.scenario import Scenario, planar_object

SIZE = 100
#: Scenario field -> the ``twinfocus simulate`` option that sets it (the fields SCENES set)
SIMULATE_OPTIONS = {
    "reference": "--reference",
    "target": "--target",
    "distance_m": "--distance",
    "separation_deg": "--separation-deg",
    "seed": "--seed",
    "target_depth_offset_m": "--target-depth-offset",
}


def _scene(label: str, **kw) -> tuple[str, list[str], Scenario]:
    """(what it is, simulate's options, the Scenario they make) from the Scenario keywords ``kw``
    alone, so that the options and the Scenario cannot tell different scenes."""
    return label, [w for k, v in kw.items() for w in (SIMULATE_OPTIONS[k], str(v))], Scenario(**kw)


#: key -> (what it is, simulate's options, the Scenario they make); the demo first. Keys without
#: spaces or dots: docs quote the file's figures by key (tests/test_docs_figures.py)
SCENES = {
    "demo": _scene("demo (A, F at 0.6 m, 10 deg)"),
    "c_x_near": _scene("C, X at 0.5 m, 14 deg, seed 1",
                       reference="C", target="X", distance_m=0.5, separation_deg=14.0, seed=1),
    "r_z_far_deeper": _scene("R, Z at 0.7 m, 12 deg, target 8 cm deeper, seed 2",
                             reference="R", target="Z", distance_m=0.7, separation_deg=12.0, seed=2,
                             target_depth_offset_m=0.08),
    "k_t_near": _scene("K, T at 0.55 m, 12 deg, seed 11",
                       reference="K", target="T", distance_m=0.55, separation_deg=12.0, seed=11),
    "e_h_far": _scene("E, H at 0.65 m, 11 deg, seed 12",
                      reference="E", target="H", distance_m=0.65, separation_deg=11.0, seed=12),
    # held out: never looked at while the edge rule (twinfocus.focus.boxes.EDGE_DB) was chosen
    "heldout_p_l": _scene("P, L at 0.6 m, 13 deg, seed 21 (held out)",
                          reference="P", target="L", distance_m=0.6, separation_deg=13.0, seed=21),
    "heldout_b_n_deeper": _scene("B, N at 0.55 m, 10 deg, target 5 cm deeper, seed 22 (held out)",
                                 reference="B", target="N", distance_m=0.55, separation_deg=10.0, seed=22,
                                 target_depth_offset_m=0.05),
}  # fmt: skip
#: the scenes not used while the edge rule was chosen
HELD_OUT = ("heldout_p_l", "heldout_b_n_deeper")


def truth_extent(sc: Scenario, name: str) -> list[float]:
    """The letter's x/y extent and depth [X0, X1, Y0, Y1, Z] (metres) from the scene itself."""
    obj = planar_object(sc.scene(), name)
    c = obj.corners_m()
    return [float(c[:, 0].min()), float(c[:, 0].max()), float(c[:, 1].min()), float(c[:, 1].max()),
            float(obj.centre_m[2])]  # fmt: skip


def _roi_args(roi) -> list[str]:
    return [f"{v:.6g}" for v in roi]


def run_scene(d: Path, sim: list[str], sc: Scenario) -> dict:
    assert cli(["simulate", "--out", str(d / "scan.npz"), "--template-out", str(d / "tpl.npz"), "--quiet", *sim]) == 0
    common = [str(d / "scan.npz"), "--template-scan", str(d / "tpl.npz"), "--size", str(SIZE), "--quiet", "--no-cache"]
    typed_args = ["--reference-roi", *_roi_args(sc.reference_roi()), "--target-roi", *_roi_args(sc.target_roi())]
    t = time.perf_counter()
    assert cli(["focus", *common, *typed_args, "--out", str(d / "typed")]) == 0
    typed_s = time.perf_counter() - t
    t = time.perf_counter()
    assert cli(["focus", *common, "--out", str(d / "found")]) == 0
    found_s = time.perf_counter() - t
    typed = json.loads((d / "typed" / "metrics.json").read_text())
    found = json.loads((d / "found" / "metrics.json").read_text())
    row: dict = {}
    for role, name in (("reference", "reference"), ("target", "target")):
        truth = truth_extent(sc, name)
        roi = found[f"{role}_roi"]
        extent = found["boxes"][role]["extent_m"]
        # region edge less the letter's edge, outward positive: the margin left on each side
        out = [truth[0] - roi[0], roi[1] - truth[1], truth[2] - roi[2], roi[3] - truth[3]]
        row[role] = {
            "truth_m": truth,
            "found_roi_m": roi,
            "found_extent_m": extent,
            "region_edge_out_m": [round(v, 4) for v in out],
            "extent_edge_error_m": [round(extent[i] - truth[i], 4) for i in range(4)],
            "depth_error_m": round(roi[4] - truth[4], 4),
            "holds_letter": bool(min(out) >= 0),
            "within_2cm": bool(max(abs(v) for v in out) <= 0.02 and abs(roi[4] - truth[4]) <= 0.02),
        }
    row["regions_overlap"] = overlap(found["reference_roi"][:4], found["target_roi"][:4]) > 0
    row["sure"] = found["boxes"]["sure"]
    row["target_ssim_typed"] = typed["target_ssim_corrected"]
    row["target_ssim_found"] = found["target_ssim_corrected"]
    row["target_ssim_found_less_typed"] = round(found["target_ssim_corrected"] - typed["target_ssim_corrected"], 4)
    row["seconds"] = {"typed": round(typed_s, 1), "found": round(found_s, 1),
                      "boxes": round(found["timings_s"].get("boxes", 0.0), 1)}  # fmt: skip
    return row


def look_scene(d: Path, sim: list[str], sc: Scenario) -> dict:
    """The boxes' edges alone, without the two focus runs (``--looks-only``): the reference's region
    as ``focus`` finds it from the stage scan (:func:`twinfocus.focus.reference_search.region_from_scan`,
    the same call), the target's from the look at the scan on its true positions (a stand-in for
    ``focus``'s look through the reference's correction), the brightest object other than the
    reference's, grown as ``focus`` grows it. Edges less the letter's, outward positive."""
    from twinfocus.focus.boxes import REGION_MARGIN_M, grow, look
    from twinfocus.focus.reference_search import region_from_scan
    from twinfocus.radar.scan import Scan

    assert cli(["simulate", "--out", str(d / "scan.npz"), "--template-out", str(d / "tpl.npz"), "--quiet", *sim]) == 0
    tpl, scan = Scan.load(d / "tpl.npz"), Scan.load(d / "scan.npz")
    ref_roi, _ = region_from_scan(tpl.data, tpl.positions, tpl.chirp)
    seen = look(scan.data, scan.positions_true, scan.chirp)
    others = [o for o in seen.objects if overlap(o.extent_m, ref_roi[:4]) < 0.3]
    rois = {"reference": list(ref_roi), "target": [*grow(others[0].extent_m, REGION_MARGIN_M), others[0].depth_m]}
    row: dict = {}
    for role in ("reference", "target"):
        truth, roi = truth_extent(sc, role), rois[role]
        out = [truth[0] - roi[0], roi[1] - truth[1], truth[2] - roi[2], roi[3] - truth[3]]
        row[role] = {
            "truth_m": truth,
            "found_roi_m": roi,
            "region_edge_out_m": [round(v, 4) for v in out],
            "extent_edge_out_m": [round(v - REGION_MARGIN_M, 4) for v in out],
            "holds_letter": bool(min(out) >= 0),
            "within_2cm": bool(max(abs(v) for v in out) <= 0.02),
        }
    return row


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="benchmarks/results")
    p.add_argument("--name", default="boxes_found.json", help="the result file's name in --out")
    p.add_argument("--scenes", nargs="+", choices=list(SCENES), help="only these scenes (default: all)")
    p.add_argument("--looks-only", action="store_true", help="only the boxes' edges, no focus (look_scene)")
    args = p.parse_args(argv)
    if args.looks_only:
        return _looks_only(args)
    shown = ("target_ssim_typed", "target_ssim_found", "regions_overlap")
    rows = _each_scene(args, run_scene, lambda row: {k: row[k] for k in shown})
    worst = max(abs(r["target_ssim_found_less_typed"]) for r in rows.values())
    roles = ("reference", "target")
    doc = {
        "command": "python -m benchmarks.bench_boxes_found --out benchmarks/results"
        + (f" --name {args.name}" if args.name != "boxes_found.json" else "")
        + (f" --scenes {' '.join(args.scenes)}" if args.scenes else ""),
        "size": SIZE,
        "scenes": rows,
        "summary": {
            "largest_target_ssim_difference": worst,
            "all_within_2cm": all(r[k]["within_2cm"] for r in rows.values() for k in ("reference", "target")),
            "any_overlap": any(r["regions_overlap"] for r in rows.values()),
            "all_hold_their_letter": all(r[k]["holds_letter"] for r in rows.values() for k in roles),
            "largest_extent_error_m": max(
                abs(v) for r in rows.values() for k in roles for v in r[k]["extent_edge_error_m"]
            ),
            "largest_edge_out_demo_m": max(max(rows["demo"][k]["region_edge_out_m"]) for k in roles)
            if "demo" in rows
            else None,
            "largest_edge_out_m": max(max(r[k]["region_edge_out_m"]) for r in rows.values() for k in roles),
            "largest_region_edge_error_m": max(
                abs(v) for r in rows.values() for k in roles for v in r[k]["region_edge_out_m"]
            ),
            "largest_region_edge_error_held_out_m": max(
                (
                    abs(v)
                    for key, r in rows.items()
                    if key in HELD_OUT
                    for k in roles
                    for v in r[k]["region_edge_out_m"]
                ),
                default=None,
            ),
        },
        "machine": machine_info(),
    }
    return _write(args, doc)


def _each_scene(args, run, show) -> dict:
    """key -> {"scene", "held_out", **run(folder, simulate's options, Scenario)} of each scene
    --scenes asks for (all by default), each run in a folder of its own; prints ``show(row)`` of
    each row as it goes."""
    rows = {}
    for key, (label, sim, sc) in SCENES.items():
        if args.scenes and key not in args.scenes:
            continue
        with tempfile.TemporaryDirectory() as tmp:
            rows[key] = {"scene": label, "held_out": key in HELD_OUT, **run(Path(tmp), sim, sc)}
        print(label, json.dumps(show(rows[key])), flush=True)
    return rows


def _write(args, doc: dict) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / args.name, json.dumps(doc, indent=2, default=float) + "\n")
    print(f"wrote {out / args.name}")
    return 0


def _looks_only(args) -> int:
    rows = _each_scene(args, look_scene, lambda row: {k: row[k]["region_edge_out_m"] for k in ("reference", "target")})
    edges = lambda keys: [
        abs(v) for k in keys for role in ("reference", "target") for v in rows[k][role]["region_edge_out_m"]
    ]  # noqa: E731
    doc = {
        "command": f"python -m benchmarks.bench_boxes_found --looks-only --out benchmarks/results --name {args.name}"
        + (f" --scenes {' '.join(args.scenes)}" if args.scenes else ""),
        "what": "region edges less the letter's (outward +), metres; reference from the stage scan as focus finds it, "
        "target from the look on the true positions",
        "scenes": rows,
        "summary": {
            "largest_region_edge_error_m": max(edges(rows)),
            "largest_region_edge_error_held_out_m": max(edges([k for k in rows if k in HELD_OUT]), default=None),
            "all_within_2cm": all(r[k]["within_2cm"] for r in rows.values() for k in ("reference", "target")),
            "all_hold_their_letter": all(r[k]["holds_letter"] for r in rows.values() for k in ("reference", "target")),
        },
        "machine": machine_info(),
    }
    return _write(args, doc)


if __name__ == "__main__":
    raise SystemExit(main())
