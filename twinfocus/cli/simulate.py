"""``twinfocus simulate``: a simulated handheld scan of the paper's scene, and the reference's
motion-stage template scan."""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from twinfocus.errors import TwinFocusError
from twinfocus.io.arrays import save_npy_atomic
from twinfocus.io.atomic import output_files
from twinfocus.jobs.machine import available_memory_bytes, require_memory
from twinfocus.jobs.progress import Progress
from twinfocus.motion.tracking_errors import ERROR_MODELS
from twinfocus.option_types import (
    DISPLACEMENT,
    bounded_float,
    finite_float,
    non_negative_float,
    non_negative_int,
    number_or_inf,
    positive_float,
    positive_int,
)
from twinfocus.radar.array_errors import NONE, array_error_levels, array_errors_stream, draw_array_errors
from twinfocus.radar.board import load_board
from twinfocus.radar.fmcw import Chirp, mmwcas_virtual_array


def add_layout_arguments(p: argparse.ArgumentParser) -> None:
    """The scene's layout (letters, distance, angle, sizes, materials, occluder), shared with
    ``twinfocus render`` so that both see the same scene from the same options."""
    p.add_argument("--reference", default="A", help="reference letter (default A)")
    p.add_argument("--target", default="F", help="target letter (default F)")
    p.add_argument(
        "--distance",
        type=bounded_float(0, 10, low_open=True, unit="m"),
        default=0.6,
        help="object distance, metres (default 0.6)",
    )
    p.add_argument("--separation-deg", type=finite_float, default=10.0, help="reference-target angle (default 10)")
    p.add_argument(
        "--height",
        type=bounded_float(0, 5, low_open=True, unit="m"),
        default=0.127,
        help="letter height, metres (default 0.127 = 5 in)",
    )
    p.add_argument(
        "--target-height",
        type=bounded_float(0, 5, low_open=True, unit="m"),
        default=None,
        help="target letter height if different",
    )
    p.add_argument("--reference-material", default="metal")
    p.add_argument("--target-material", default="metal")
    p.add_argument("--occluder", default=None, help="sheet in front of the target: polyester, paper, plastic, ...")


def layout_kwargs(args: argparse.Namespace) -> dict:
    """:class:`twinfocus.simulation.scenario.Scenario` keywords from :func:`add_layout_arguments`' options."""
    return dict(
        reference=args.reference,
        target=args.target,
        distance_m=args.distance,
        separation_deg=args.separation_deg,
        height_m=args.height,
        target_height_m=args.target_height,
        reference_material=args.reference_material,
        target_material=args.target_material,
        occluder=args.occluder,
    )


def add_arguments(p: argparse.ArgumentParser) -> None:
    _add_scan_arguments(p)
    _add_field_arguments(p)
    _add_cloud_arguments(p)
    _add_array_arguments(p)
    p.add_argument("--quiet", action="store_true")


def _add_scan_arguments(p: argparse.ArgumentParser) -> None:
    """The outputs, the scene, the trajectory and its tracking error, the noise."""
    p.add_argument(
        "--out", required=True, help="scan file to write (.npz; an existing one is refused without --overwrite)"
    )
    p.add_argument("--template-out", help="also write the reference's motion-stage scan here (.npz)")
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace existing output files (--out, --template-out, --reference-cloud-out)",
    )
    add_layout_arguments(p)
    p.add_argument("--clutter", action="store_true", help="add room clutter (weak and a few strong scatterers)")
    p.add_argument(
        "--board",
        help="board file (YAML) of the radar's antenna layout (default: TI's MMWCAS-RF-EVM; docs/real_array.md)",
    )
    p.add_argument("--trajectory", choices=["raster", "zigzag"], default="raster")
    p.add_argument(
        "--error-model",
        choices=[m for m in ERROR_MODELS if m != "none"],
        default="gaussian",
        help="tracking error: gaussian (the paper), drift, vio, hand (drift + jitter + array rotation)",
    )
    p.add_argument(
        "--error-sigma-mm",
        type=non_negative_float,
        default=0.5,
        help="z (range) tracking error sigma, mm (default 0.5)",
    )
    p.add_argument(
        "--xy-error-sigma-mm",
        type=non_negative_float,
        default=0.5,
        help="x and y tracking error sigma, mm (default 0.5)",
    )
    p.add_argument(
        "--snr-db", type=number_or_inf, default=10.0, help="per-sample SNR in dB (default 10); 'inf' for none"
    )
    p.add_argument("--no-speckle", action="store_true", help="all scatterers in phase")
    p.add_argument(
        "--template-offset-mm",
        **DISPLACEMENT,
        default=[1.0, 0.0, 0.0],
        help="placement error of the reference in the template scan, mm (default 1 0 0)",
    )
    p.add_argument(
        "--range-step-mm", type=positive_float, default=None, help="simulator range grid step (fidelity knob)"
    )
    p.add_argument("--columns", type=positive_int, default=6, help="raster columns (default 6)")
    p.add_argument("--rows", type=positive_int, default=130, help="raster rows per column (default 130)")
    p.add_argument("--seed", type=non_negative_int, default=0)


def _add_field_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("field-like scenes (rough, curved references; deeper targets)")
    g.add_argument(
        "--reference-roughness-deg",
        type=finite_float,
        default=None,
        metavar="DEG",
        help="rough reference: each scatterer's phase uniform in +-DEG (about 90 for a real surface); "
        "replaces speckle for the reference",
    )
    g.add_argument(
        "--reference-amplitude-spread",
        type=finite_float,
        default=0.3,
        metavar="FRAC",
        help="with --reference-roughness-deg: each scatterer's amplitude x (1 +- FRAC) (default 0.3)",
    )
    g.add_argument(
        "--reference-shape",
        choices=["plane", "cylinder", "bent"],
        default="plane",
        help="reference surface: flat, wrapped on a cylinder (axis vertical) or bent along its centre line",
    )
    g.add_argument(
        "--reference-shape-parameter",
        type=finite_float,
        default=None,
        metavar="P",
        help="cylinder radius in metres (default 0.15) or bend angle in degrees (default 30)",
    )
    g.add_argument(
        "--target-depth-offset",
        type=finite_float,
        default=0.0,
        metavar="M",
        help="put the target this many metres further than the reference, along its ray (default 0)",
    )


#: add_argument keywords of a cloud impairment given as one number or as three (x y z): finite
#: numbers, held to one or three by :func:`run`
_ONE_OR_THREE: dict = {"nargs": "+", "type": finite_float}


def _add_cloud_arguments(p: argparse.ArgumentParser) -> None:
    c = p.add_argument_group("camera cloud of the reference (for focus --digital-twin)")
    c.add_argument(
        "--reference-cloud-out",
        default=None,
        metavar="CLOUD.npy",
        help="write the reference's surface as a depth camera delivers it (.npy, (N, 3) metres)",
    )
    c.add_argument(
        "--cloud-spacing-mm", type=positive_float, default=1.0, help="camera sampling of the surface, mm (default 1)"
    )
    c.add_argument(
        "--cloud-noise-mm",
        **_ONE_OR_THREE,
        default=[1.0],
        metavar="SD",
        help="noise sd, mm: one for every axis or three (x y z) (default 1)",
    )
    c.add_argument(
        "--cloud-holes",
        type=finite_float,
        default=0.25,
        metavar="FRAC",
        help="fraction of the surface missing, in patches (default 0.25)",
    )
    c.add_argument(
        "--cloud-outliers",
        type=finite_float,
        default=0.02,
        metavar="FRAC",
        help="fraction of the cloud's points that are outliers around the object (default 0.02)",
    )
    c.add_argument(
        "--cloud-offset-mm",
        **_ONE_OR_THREE,
        default=[2.0],
        metavar="MM",
        help="rigid offset of the cloud: a length (random direction) or three (x y z), mm (default 2)",
    )


def _add_array_arguments(p: argparse.ArgumentParser) -> None:
    a = p.add_argument_group(
        "the array as hardware is (docs/calibration.md): a level, then any knob replaces its value"
    )
    a.add_argument(
        "--array-errors",
        choices=["none", "typical"],
        default="none",
        help="'none' (default): the perfect array; 'typical': published magnitudes (twinfocus.radar.array_errors)",
    )
    a.add_argument("--array-seed", type=non_negative_int, help="draw of the array's errors (default: from --seed)")
    a.add_argument("--channel-phase-deg", type=finite_float, help="per-TX/RX phase spread (180: uniform; typical 180)")
    a.add_argument("--channel-amplitude-db", type=finite_float, help="per-TX/RX gain sd, dB (typical 1)")
    a.add_argument("--channel-delay-mm", type=finite_float, help="per-TX/RX range offset sd, mm (typical 3)")
    a.add_argument("--leakage-db", type=finite_float, help="TX-to-RX leakage re the mean return, dB (typical 0)")
    a.add_argument("--dc-offset-db", type=finite_float, help="receiver DC offset re the mean return, dB (typical -20)")
    a.add_argument("--iq-gain-db", type=finite_float, help="I/Q gain mismatch bound, dB (typical 1)")
    a.add_argument("--iq-phase-deg", type=finite_float, help="I/Q phase mismatch bound, degrees (typical 2)")
    a.add_argument("--beamwidth-deg", type=finite_float, help="antenna half-power beam width, degrees (typical 60)")


_ARRAY_KNOBS = (
    "channel_phase_deg",
    "channel_amplitude_db",
    "channel_delay_mm",
    "leakage_db",
    "dc_offset_db",
    "iq_gain_db",
    "iq_phase_deg",
    "beamwidth_deg",
)


def array_errors_from_args(args: argparse.Namespace):
    """The :class:`~twinfocus.radar.array_errors.ArrayErrors` draw the options ask for (None: the perfect array)."""

    levels = array_error_levels(args.array_errors, **{k: getattr(args, k) for k in _ARRAY_KNOBS})
    if levels == NONE:
        return None, levels
    seed = args.seed if args.array_seed is None else args.array_seed
    return draw_array_errors(levels, array_errors_stream(seed)), levels


def run(args: argparse.Namespace) -> int:
    if not str(args.out).endswith(".npz"):
        raise TwinFocusError(f"--out must name a .npz file, got {args.out}")
    if args.error_sigma_mm < 0 or args.xy_error_sigma_mm < 0:
        raise TwinFocusError("error sigmas must be non-negative")
    if args.reference_cloud_out is not None and not str(args.reference_cloud_out).endswith(".npy"):
        raise TwinFocusError(f"--reference-cloud-out must name a .npy file, got {args.reference_cloud_out}")
    for name in ("cloud_noise_mm", "cloud_offset_mm"):
        if len(getattr(args, name)) not in (1, 3):
            raise TwinFocusError(f"--{name.replace('_', '-')} takes one number or three (x y z)")
    outputs = {
        "--out": args.out,
        "--template-out": args.template_out,
        "--reference-cloud-out": args.reference_cloud_out,
    }
    with output_files(outputs, args.overwrite):  # refused or locked before the (long) simulation
        return _simulate(args)


def _simulate(args: argparse.Namespace) -> int:

    from twinfocus.simulation.scenario import Scenario, simulate_scenario  # lazy: numba, cv2 (+2.1 s at import)

    snr = None if np.isinf(args.snr_db) else args.snr_db
    sc = Scenario(
        **layout_kwargs(args),
        clutter=args.clutter,
        trajectory=args.trajectory,
        error_model=args.error_model,
        error_sigma_m=(args.xy_error_sigma_mm * 1e-3, args.xy_error_sigma_mm * 1e-3, args.error_sigma_mm * 1e-3),
        snr_db=snr,
        speckle=not args.no_speckle,
        template_offset_m=tuple(v * 1e-3 for v in args.template_offset_mm),
        range_step_m=None if args.range_step_mm is None else args.range_step_mm * 1e-3,
        seed=args.seed,
        n_columns=args.columns,
        n_rows=args.rows,
        reference_roughness_deg=args.reference_roughness_deg,
        reference_amplitude_spread=args.reference_amplitude_spread,
        reference_shape=args.reference_shape,
        reference_shape_parameter=args.reference_shape_parameter,
        target_depth_offset_m=args.target_depth_offset,
        board=args.board,
    )
    if args.board:
        load_board(args.board)  # a bad board file is refused before the (long) simulation
    _check_cost(sc, args)
    array_errors, levels = array_errors_from_args(args)
    cloud = None
    if args.reference_cloud_out is not None:
        # Made before the (long) simulation so a bad impairment option fails at once.
        from twinfocus.twins.digital_twin.camera_cloud import camera_cloud  # lazy: scipy.spatial (+1.0 s at import)

        mm = lambda v: v[0] * 1e-3 if len(v) == 1 else np.asarray(v) * 1e-3
        surface = sc.scene().object("reference").surface_points(args.cloud_spacing_mm * 1e-3)
        cloud = camera_cloud(
            surface,
            mm(args.cloud_noise_mm),
            args.cloud_holes,
            args.cloud_outliers,
            mm(args.cloud_offset_mm),
            rng=np.random.default_rng([args.seed, 14]),
        )
    t0 = time.perf_counter()
    scan, template_scan = simulate_scenario(
        sc, progress=Progress("simulate", enabled=not args.quiet), array_errors=array_errors
    )
    scan.save(args.out)
    if args.template_out:
        template_scan.save(args.template_out)
    if cloud is not None:
        save_npy_atomic(args.reference_cloud_out, np.asarray(cloud, dtype=np.float64))
    info = {
        "scan": str(args.out),
        "template_scan": args.template_out,
        "seconds": round(time.perf_counter() - t0, 2),
        "reference_roi": sc.reference_roi(),
        "target_roi": sc.target_roi(),
        "positions": scan.n_positions,
        "channels": scan.n_channels,
        "reference_cloud": args.reference_cloud_out,
        "reference_cloud_points": None if cloud is None else int(cloud.shape[0]),
        "array_errors": None if array_errors is None else levels.to_dict(),
    }
    print(json.dumps(info), file=sys.stderr)
    return 0


def _check_cost(sc, args) -> None:
    """Refuse, before any work, a simulation that cannot fit in memory (``--rows
    100000`` would run for minutes and die); say how long a large one will take."""
    from twinfocus.scene import scatterer_spacing_m  # lazy: cv2 (+0.4 s at import)
    from twinfocus.simulation.if_simulator import (  # lazy: numba (+2.1 s at import)
        BYTES_PER_SCATTERER_CELL,
        scatterer_cells,
        simulation_cost,
    )

    if args.columns < 1 or args.rows < 2:
        raise TwinFocusError(f"--columns must be >= 1 and --rows >= 2, got {args.columns} and {args.rows}")
    spacing = sc.spacing_m or scatterer_spacing_m(sc.distance_m)
    scene = sc.scene()
    avail = available_memory_bytes()
    # counted before any scatterer is made: drawing them is itself the allocation to refuse
    cells = scatterer_cells(scene, spacing)
    require_memory(
        int(cells * BYTES_PER_SCATTERER_CELL),
        f"placing this scene's {cells:.3g} scatterers ({spacing * 1e3:.2g} mm apart over objects up to {max(args.height, args.target_height or 0):g} m high)",
        "use a smaller --height / --target-height",
        available=avail,
    )
    n_pts = scene.scatterers(spacing, 0)[0].shape[0]
    n_scans = 2 if args.template_out else 1
    peak, cpu_s = simulation_cost(
        args.columns * args.rows, mmwcas_virtual_array().n_channels, Chirp().n_samples, n_pts, n_scans
    )
    require_memory(
        int(peak),
        f"this simulation ({args.columns} x {args.rows} positions, about {cpu_s / 60:.0f} min of CPU)",
        "use fewer --rows/--columns",
        available=avail,
    )
    if cpu_s > 60 and not args.quiet:
        print(f"simulate: about {peak / 2**30:.1f} GiB and {cpu_s / 60:.1f} min of CPU", file=sys.stderr)
