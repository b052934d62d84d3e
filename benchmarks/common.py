"""What several benchmarks do alike: the ``twinfocus focus`` command line they run on a scan and
its template scan, and the result JSON they write."""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path


def focus_argv(
    scan: Path | str,
    template_scan: Path | str,
    reference_roi: Iterable,
    target_roi: Iterable,
    size: int | str,
    *options: str,
) -> list[str]:
    """``focus SCAN --template-scan TEMPLATE --reference-roi ... --target-roi ... --size N`` and then
    ``options``, as the argv of :func:`twinfocus.cli.main` (or after ``python -m twinfocus``).

    The ROIs are (x0, x1, y0, y1[, z]) in metres, numbers or strings (each is written with
    ``str``); ``size`` is the image's pixels a side."""
    return [
        "focus",
        str(scan),
        "--template-scan",
        str(template_scan),
        "--reference-roi",
        *map(str, reference_roi),
        "--target-roi",
        *map(str, target_roi),
        "--size",
        str(size),
        *options,
    ]


def write_result(out_dir: Path | str, name: str, doc: dict) -> dict:
    """Write ``doc`` as indented JSON to ``out_dir/name`` (the folder made if missing); returns ``doc``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / name).write_text(json.dumps(doc, indent=2))
    return doc
