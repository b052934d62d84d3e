"""A module's imports sit at its top (docs/architecture.md section 3): an import of the project's
own modules inside a function is there because it was measured to matter, and says so on its line
(``# lazy: numba (+2.1 s at import)``, ``# lazy: ... (+0.1 s on twinfocus focus --help)``)."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("twinfocus", "nodes", "msgs")
# Modules under other work when the rest was hoisted: their lazy imports are still to sort (hoist or
# say why). THIS LIST MUST EMPTY; nothing may be added to it.
NOT_YET_SORTED: set[str] = set()


def unexplained_lazy_imports(source: str) -> list[int]:
    """Lines of function-level imports of twinfocus/nodes/msgs modules without a ``# lazy:`` comment."""
    lines = source.splitlines()
    found = []
    for fn in ast.walk(ast.parse(source)):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(fn):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            said = any("# lazy:" in lines[i - 1] for i in range(node.lineno, node.end_lineno + 1))
            if any(n.split(".")[0] in PACKAGES for n in names) and not said:
                found.append(node.lineno)
    return sorted(set(found))


def test_the_check_sees_an_unexplained_import():
    src = (
        "def f():\n    from twinfocus.radar.scan import Scan\n    import numpy\n"
        "    from twinfocus.imaging import volume  # lazy: numba (+2.1 s at import)\n    return Scan, numpy, volume\n"
    )
    assert unexplained_lazy_imports(src) == [2]


def test_every_lazy_import_says_why():
    bad = [
        f"{f.relative_to(ROOT)}:{line}"
        for pkg in PACKAGES
        for f in sorted((ROOT / pkg).rglob("*.py"))
        if f.relative_to(ROOT).as_posix() not in NOT_YET_SORTED
        for line in unexplained_lazy_imports(f.read_text())
    ]
    assert not bad, "imports inside functions without '# lazy: why': hoist them or say why:\n" + "\n".join(bad)
