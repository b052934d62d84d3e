"""The shape of the code: no function of the library, the messages or the nodes takes more than
12 parameters or runs over 100 lines. A function past either limit is split into named steps, its
parameters grouped into a settings object. Numba kernels are excepted from the parameter limit:
they take arrays, grouped as far as numba allows, not objects."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("twinfocus", "msgs", "nodes")
MAX_PARAMETERS = 12
MAX_LINES = 100
NUMBA_DECORATORS = {"njit", "jit", "vectorize", "guvectorize", "stencil"}

# Functions over the limits not yet reshaped, "file:function": public keyword signatures whose many
# callers (tests among them) would change with a settings object, and the evaluation's long
# drivers. THIS LIST MUST EMPTY too; nothing may be added to it.
NOT_YET_RESHAPED: set[str] = set()


def _is_numba_kernel(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    for d in fn.decorator_list:
        target = d.func if isinstance(d, ast.Call) else d
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name in NUMBA_DECORATORS:
            return True
    return False


def _parameters(fn: ast.FunctionDef | ast.AsyncFunctionDef, is_method: bool) -> int:
    """Named parameters, *args and **kwargs each counting one; a method's self / cls not counted."""
    a = fn.args
    names = [*a.posonlyargs, *a.args]
    if is_method and names and names[0].arg in ("self", "cls"):
        names = names[1:]
    return len(names) + len(a.kwonlyargs) + (a.vararg is not None) + (a.kwarg is not None)


def shape_offences(source: str, where: str) -> list[str]:
    """One line per function of ``source`` over the limits: ``where:line name: what``."""
    out = []

    def visit(node: ast.AST, in_class: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = child.end_lineno - child.lineno + 1
                n = _parameters(child, in_class)
                if lines > MAX_LINES:
                    out.append(f"{where}:{child.lineno} {child.name}: {lines} lines (at most {MAX_LINES})")
                if n > MAX_PARAMETERS and not _is_numba_kernel(child):
                    out.append(f"{where}:{child.lineno} {child.name}: {n} parameters (at most {MAX_PARAMETERS})")
                visit(child, False)
            else:  # a class's body holds methods; an if / try block keeps what it is inside
                visit(child, isinstance(child, ast.ClassDef) or in_class)

    visit(ast.parse(source), False)
    return out


def test_no_function_over_the_limits():
    offences = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            offences += shape_offences(path.read_text(encoding="utf-8"), rel)
    offences = [o for o in offences if _key(o) not in NOT_YET_RESHAPED]
    assert not offences, "functions over the limits:\n" + "\n".join(offences)


def _key(offence: str) -> str:
    """``file:function`` of an offence line ``file:line function: what``."""
    where, name = offence.split(": ", 1)[0].split(" ")
    return f"{where.rsplit(':', 1)[0]}:{name}"


def test_the_not_yet_reshaped_functions_are_still_over_the_limits():
    """An entry whose function was reshaped (or renamed) goes from the list."""
    over = set()
    for rel in {k.split(":")[0] for k in NOT_YET_RESHAPED}:
        over |= {_key(o) for o in shape_offences((ROOT / rel).read_text(encoding="utf-8"), rel)}
    assert sorted(NOT_YET_RESHAPED - over) == []


def test_the_checker_finds_long_and_wide_functions_and_spares_kernels_and_self():
    wide = ", ".join(f"a{i}" for i in range(13))
    body = "\n".join(f"    x{i} = {i}" for i in range(100))
    source = (
        f"def wide({wide}):\n    pass\n\n"
        f"def long():\n{body}\n\n"
        f"def fine({', '.join(f'a{i}' for i in range(12))}):\n    pass\n\n"
        f"@numba.njit(cache=True)\ndef kernel({wide}):\n    pass\n\n"
        f"class C:\n    def method(self, {', '.join(f'a{i}' for i in range(12))}):\n        pass\n"
    )
    got = shape_offences(source, "m.py")
    assert got == ["m.py:1 wide: 13 parameters (at most 12)", "m.py:4 long: 101 lines (at most 100)"]
