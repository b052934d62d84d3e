"""Numerics never open files (docs/architecture.md section 3): outside the packages whose job is
files (``io``), pictures (``outputs``), orchestration (``evaluation``, ``jobs``) and the command
(``cli``), no module of the library calls a file primitive (``open``, ``np.load``/``np.save``,
``Path.read_text``/``write_text``/``read_bytes``/``write_bytes``, ``json.load``/``dump``,
``yaml.safe_load``, ``cv2.imread``/``imwrite``, ``savefig``, ...). It calls ``twinfocus.io``'s
readers and writers, or takes arrays and objects from a caller that did.

A module whose whole job is one file format but whose objects live above ``io`` (a reader that
builds a :class:`~twinfocus.sensors.frames.RadarFrame` or a :class:`~twinfocus.motion.trajectory.Poses`)
stays in its layer, named as a format module (``*_files.py``), or is listed below with why."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIBRARY = ROOT / "twinfocus"
#: packages whose job is files or that orchestrate runs, so they may open them
FILE_PACKAGES = {"io", "outputs", "evaluation", "jobs", "cli"}
#: modules beside the numerics that read a device's own files, and the device emulators that write
#: them; their formats are the devices' (a TI config, a ZED .conf, a capture's raw .bin files)
DEVICE_FILES = {
    "twinfocus/sensors/ti_cli.py": "reads the TI mmWave CLI config file it sends to the board",
    "twinfocus/sensors/ti_mmwcas.py": "reads the MMWCAS capture's raw .bin files, mmwave.json and its logs",
    "twinfocus/sensors/zed.py": "reads the ZED camera's factory calibration .conf",
    "twinfocus/sensors/emulators/__main__.py": "the emulated rig writes its scatterers for the emulated camera",
    "twinfocus/sensors/emulators/mmwcas_capture.py": "writes a capture as the MMWCAS board's files",
    "twinfocus/sensors/emulators/rig.py": "the emulated devices share a start time through a file",
    "twinfocus/sensors/emulators/zed_bag.py": "reads the emulated rig's scatterers",
}
ATTRIBUTES = {
    "read_text", "write_text", "read_bytes", "write_bytes", "open", "savefig", "imread", "imwrite",
    "fromfile", "tofile", "loadtxt", "savetxt", "savez", "savez_compressed", "safe_load", "safe_dump_all",
}  # fmt: skip
MODULE_CALLS = {("np", "load"), ("np", "save"), ("json", "load"), ("json", "dump"), ("pickle", "load"),
                ("pickle", "dump"), ("yaml", "load"), ("yaml", "dump")}  # fmt: skip


def file_calls(source: str) -> list[tuple[int, str]]:
    """(line, call) of each file primitive that ``source`` calls."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Call):
            continue
        fn = node.func
        if isinstance(fn, ast.Name) and fn.id == "open":
            found.append((node.lineno, node.col_offset, "open"))
        elif isinstance(fn, ast.Attribute):
            owner = fn.value.id if isinstance(fn.value, ast.Name) else ""
            if fn.attr in ATTRIBUTES or (owner, fn.attr) in MODULE_CALLS:
                found.append((node.lineno, node.col_offset, f"{owner + '.' if owner else ''}{fn.attr}"))
    return [(line, call) for line, _, call in sorted(found)]


def _checked_modules() -> list[Path]:
    out = []
    for f in sorted(LIBRARY.rglob("*.py")):
        rel = f.relative_to(LIBRARY)
        if len(rel.parts) > 1 and rel.parts[0] in FILE_PACKAGES:
            continue
        if f.stem.endswith("_files"):
            continue
        out.append(f)
    return out


def test_the_check_finds_each_kind_of_file_call():
    src = (
        "import json, numpy as np\nfrom pathlib import Path\n"
        "def f(p):\n    with open(p) as h:\n        pass\n    np.load(p); np.save(p, 1); json.load(h)\n"
        "    Path(p).read_text(); Path(p).write_bytes(b''); fig.savefig(p)\n"
        "def g(x):\n    return np.loads(x) if x else json.loads(x)\n"
    )
    assert [c for _, c in file_calls(src)] == [
        "open", "np.load", "np.save", "json.load", "read_text", "write_bytes", "fig.savefig"
    ]  # fmt: skip


def test_numeric_modules_open_no_files():
    opened = []
    for f in _checked_modules():
        rel = f.relative_to(ROOT).as_posix()
        if rel in DEVICE_FILES:
            continue
        opened += [f"{rel}:{line}: {call}" for line, call in file_calls(f.read_text())]
    assert not opened, "numerics open files; read them with twinfocus.io, or in the caller:\n" + "\n".join(opened)


def test_every_listed_device_module_still_opens_files():
    # an entry whose module no longer opens files would let a new file call in unnoticed
    stale = [m for m in DEVICE_FILES if not (ROOT / m).is_file() or not file_calls((ROOT / m).read_text())]
    assert not stale, f"DEVICE_FILES lists modules that open no files: {stale}"
