"""Write the tables that docs pages quote from result files, and read the figures they mark.

    python -m benchmarks.page_tables                  # rewrite every generated table of docs/ and README.md
    python -m benchmarks.page_tables --check          # exit 1 when a committed table is stale

A page's figure marker ``0.953<!-- figure: FILE.json#WHERE -->`` and a generated table's cells read
their values the same way (:func:`lookup`). ``WHERE`` is dotted keys; ``[k=v,...]`` picks the one
row of a list whose fields have those values; over a list of records ``where(COND,...)`` keeps the
rows that meet each COND (``k=v``, ``k!=v``; ``k<x``, ``k<=x``, ``k>x``, ``k>=x`` with x a number or another
field plus or minus one, ``default>before+0.005``; ``k``: has k), and ``mean(KEY)``, ``sd(KEY)``
(ddof 0), ``min``, ``max``, ``median``, ``p90`` (90th percentile), ``absmean``, ``absmedian``,
``absp90``, ``absmax`` and ``n(KEY)`` (how many records have it) summarise KEY, a dotted path inside
each record, over the records that hold it; over a dict of lists ``all()`` is every list's records.
Keys and values holding a space, dot, bracket, comma, parenthesis or ``=`` are percent-encoded as
in a URL (``summary.depth%205%20cm%20off.mean_ssim`` reads the key ``"depth 5 cm off"``).

A generated table is a block::

    <!-- table: benchmarks/results/handheld.json
    H/S, hand (10 draws) = #hand%200%2E8%20mm%20%2B%200%2E15%20deg
    {} = : 0.5 mm z jitter (paper protocol); demo scene, 0.5 mm x/y/z jitter
    | {label} | {uncorrected|msd} | **{default|msd}** | {mean(default):.2f} |
    -->
    | condition | uncorrected | default | default, 2 decimals |
    |---|---|---|---|
    | H/S, hand (10 draws) | 0.522 ± 0.030 | **0.953 ± 0.021** | 0.95 |
    ...

    <!-- /table -->

The comment's first line names the default file. A line ``LABEL = [FILE]#WHERE`` is one row (its
records: WHERE in FILE); ``LABEL = [FILE]: KEY; KEY; ...`` is one row per KEY (written as it is),
labelled LABEL with ``{}`` the key; a FILE without a folder is beside the default file, none is the
default file. A ``|`` line is the template of the rows below it (and of rows above every template).
The table's first two lines (its header, written by hand) are kept; below them each row fills its
template: ``{label}`` the row's label, ``{WHERE}`` the value at WHERE in the row's records (3
decimals for a float), ``{WHERE:SPEC}`` in a Python format spec, ``{KEY|STYLE}`` a summary of KEY
over the records (``msd`` "mean ± sd", ``msdw`` "mean ± sd (worst min)", ``msdl`` "mean ± sd
(min)", ``mw`` "mean (worst min)", ``ml`` "mean (min)", ``mnw`` "mean (n, min)"), ``{FILE>...}`` the
same row's WHERE read in another file, ``{FILE#...}`` another file read from its top (``$`` in a
template is the row's WHERE: ``{field_twin.json#$%2C%20camera%20cloud.where().default|msd}``), and
``{...?TEXT}`` TEXT where no record holds what it reads.
tests/test_generated_pages.py fails when a committed table is not what its files render to.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import quote, unquote

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: one step of a WHERE: a key or a function of the list so far, then an optional ``[k=v,...]``
_STEP = re.compile(r"([^.\[\]()]+)(\([^)]*\))?((?:\[[^\]]*\])?)(?:\.|$)")
_BLOCK = re.compile(r"^<!-- table: (?P<spec>.*?)-->\n(?P<body>.*?)^<!-- /table -->$", re.S | re.M)
_CELL = re.compile(r"\{([^{}]+)\}")
_FILE = re.compile(r"([^#(){}|>]+\.json)#(.*)")


def _pairs(text: str) -> dict[str, str]:
    pairs = (pair.split("=", 1) for pair in text.split(","))
    return {unquote(k.strip()): unquote(v.strip()) for k, v in pairs}


_COND = re.compile(r"([^=<>!]+)(?:(=|!=|<=|>=|<|>)(.*))?")
_BOUND = re.compile(r"(.*?)([+-]\d+(?:\.\d+)?)?")
_COMPARE: dict[str, Callable[[float, float], bool]] = {
    "<": lambda a, b: a < b,
    "<=": lambda a, b: a <= b,
    ">": lambda a, b: a > b,
    ">=": lambda a, b: a >= b,
}


def _bound(record: dict, text: str) -> float | None:
    """A condition's right side: a number, or another field of the record plus or minus one."""
    try:
        return float(text)
    except ValueError:
        m = _BOUND.fullmatch(text)
        assert m is not None  # the pattern matches any text
        v = record.get(m.group(1))
        return None if v is None else float(v) + float(m.group(2) or 0)


def _holds(record: dict, cond: str) -> bool:
    """Whether ``record`` meets ``k=v`` (its field as text is v; ``k!=v`` not), ``k<x`` (``<=``, ``>``, ``>=``; x a
    number or another field, ``before+0.005``), or ``k`` (it has the field, not None)."""
    m = _COND.fullmatch(cond.strip())
    if m is None:
        raise KeyError(f"not a condition: {cond}")
    key, op, value = unquote(m.group(1)), m.group(2), unquote(m.group(3) or "")
    if op is None:
        return record.get(key) is not None
    if op in ("=", "!="):
        return (str(record.get(key)) == value) == (op == "=")
    v, bound = record.get(key), _bound(record, value)
    return v is not None and bound is not None and _COMPARE[op](float(v), bound)


def _values(records: list, key: str) -> np.ndarray:
    """KEY (a WHERE) of every record that has it and where it is not None, as float64."""
    out = []
    for r in records:
        try:
            v = lookup(r, key)
        except (KeyError, IndexError, TypeError):
            continue
        if v is not None:
            out.append(float(v))
    return np.array(out, float)


def _need(v: np.ndarray, key: str = "the key") -> np.ndarray:
    if not v.size:
        raise KeyError(f"no record holds {key}")
    return v


#: the functions of a list of records: name -> (records, KEY) -> value
AGGREGATES: dict[str, Callable[[list, str], Any]] = {
    "mean": lambda rs, k: float(_need(_values(rs, k), k).mean()),
    "sd": lambda rs, k: float(_need(_values(rs, k), k).std()),
    "min": lambda rs, k: float(_need(_values(rs, k), k).min()),
    "max": lambda rs, k: float(_need(_values(rs, k), k).max()),
    "median": lambda rs, k: float(np.median(_need(_values(rs, k), k))),
    "p90": lambda rs, k: float(np.percentile(_need(_values(rs, k), k), 90)),
    "absmax": lambda rs, k: float(np.abs(_need(_values(rs, k), k)).max()),
    "absmean": lambda rs, k: float(np.abs(_need(_values(rs, k), k)).mean()),
    "absmedian": lambda rs, k: float(np.median(np.abs(_need(_values(rs, k), k)))),
    "absp90": lambda rs, k: float(np.percentile(np.abs(_need(_values(rs, k), k)), 90)),
    "n": lambda rs, k: int(_values(rs, k).size),
}


def lookup(data: Any, where: str) -> Any:
    """The value at ``where`` (see the module's docstring: ``a.b[k=v,j=w].c``, ``a.where(k=v).mean(c)``,
    each key and value percent-encoded) in parsed JSON ``data``."""
    for key, args, selector in _STEP.findall(where):
        if args:
            inner = args[1:-1]
            if key == "all":
                data = [r for rows in data.values() if isinstance(rows, list) for r in rows]
            elif key == "where":
                conds = [c for c in inner.split(",") if c.strip()]  # where(): every row
                data = [r for r in data if all(_holds(r, cond) for cond in conds)]
            elif key in AGGREGATES:
                data = AGGREGATES[key](data, inner)
            else:
                raise KeyError(f"no function {key}()")
        else:
            data = data[unquote(key)] if not isinstance(data, list) else data[int(key)]
        if selector:
            wanted = _pairs(selector[1:-1])
            rows = [r for r in data if all(str(r.get(k)) == v for k, v in wanted.items())]
            if len(rows) != 1:
                raise KeyError(f"{selector} picks {len(rows)} rows, not one")
            data = rows[0]
    return data


def _style(records: list, key: str, style: str) -> str:
    v = _need(_values(records, key), key)
    mean, sd, worst = f"{v.mean():.3f}", f"{v.std():.3f}", f"{v.min():.3f}"
    styles = {
        "msd": f"{mean} ± {sd}",
        "msdw": f"{mean} ± {sd} (worst {worst})",
        "msdl": f"{mean} ± {sd} ({worst})",
        "mw": f"{mean} (worst {worst})",
        "ml": f"{mean} ({worst})",
        "mnw": f"{mean} ({v.size}, {worst})",
    }
    if style not in styles:
        raise KeyError(f"no style {style}")
    return styles[style]


def _cell(records: Any, label: str, expr: str, beside: Callable[[str, bool], Any]) -> str:
    if expr == "label":
        return label
    if "?" in expr:  # EXPR?TEXT: TEXT where no record holds what EXPR reads
        expr, _, text = expr.partition("?")
        try:
            return _cell(records, label, expr, beside)
        except KeyError:
            return text
    if (whole := _FILE.match(expr)) is not None:  # FILE#WHERE: another file, from its top
        records, expr = beside(whole.group(1), True), whole.group(2)
    elif ">" in expr.split("(", 1)[0]:  # FILE>...: the same row's records in another file
        file, expr = expr.split(">", 1)
        records = beside(file, False)
    if "|" in expr:
        where, style = expr.rsplit("|", 1)
        prefix, _, key = where.rpartition(").")  # where(...).KEY: KEY over the records that meet it
        return _style(lookup(records, prefix + ")") if prefix else records, key or where, style)
    where, _, spec = expr.partition(":")
    value = lookup(records, where)
    if spec:
        return format(value, spec)
    return f"{value:.3f}" if isinstance(value, float) else str(value)


def _rows(label: str, ref: str) -> list[tuple[str, str, str]]:
    """(label, file, WHERE) of each row a row line makes: ``LABEL = [FILE]#WHERE`` one, ``LABEL =
    [FILE]: KEY; KEY; ...`` one per key (as written, not encoded), its label LABEL with ``{}`` the key."""
    if "#" in ref:
        file, _, where = ref.partition("#")
        return [(label, file, where)]
    file, _, keys = ref.partition(":")
    keys_ = [k.strip() for k in keys.split(";") if k.strip()]
    return [
        (label.replace("{}", k) if "{}" in label else k, file.strip(), quote(k, safe="").replace(".", "%2E"))
        for k in keys_
    ]


def render_block(spec: str, body: str, root: Path = ROOT) -> str:
    """The body of one table block: the header lines of ``body`` kept, then the template of
    ``spec`` filled in for each of its rows."""
    lines = [s.strip() for s in spec.strip().splitlines() if s.strip()]
    default_file, template = lines[0], next(s for s in lines if s.startswith("|"))
    cache: dict[str, Any] = {}

    def load(file: str) -> Any:
        # a file without a folder sits beside the default file
        path = default_file if not file else file if "/" in file else str(Path(default_file).parent / file)
        if path not in cache:
            cache[path] = json.loads((root / path).read_text(encoding="utf-8"))
        return cache[path]

    out = [s for s in body.splitlines() if s.startswith("|")][:2]
    for line in lines[1:]:
        if line.startswith("|"):
            template = line  # the rows below this line fill this template
            continue
        label, _, ref = (s.strip() for s in line.partition(" = "))
        for row_label, file, where in _rows(label, ref):
            try:
                records = lookup(load(file), where) if where else load(file)
            except KeyError:  # a row whose cells read other files only (its WHERE as their $)
                records = None

            def beside(other: str, whole: bool, where: str = where) -> Any:
                return lookup(load(other), where) if where and not whole else load(other)

            filled = template.replace("$", where)  # $: the row's WHERE, in cells that read another file
            out.append(_CELL.sub(lambda m, r=records, lab=row_label, b=beside: _cell(r, lab, m.group(1), b), filled))
    return "\n".join(out) + "\n\n"  # the blank line ends the table before the closing comment


def render_page(text: str, root: Path = ROOT) -> str:
    """``text`` with every table block's body rendered anew from its files."""
    return _BLOCK.sub(
        lambda m: (
            f"<!-- table: {m.group('spec')}-->\n{render_block(m.group('spec'), m.group('body'), root)}<!-- /table -->"
        ),
        text,
    )


def pages(root: Path = ROOT) -> list[Path]:
    """The pages with a table block."""
    found = sorted([root / "README.md", *(root / "docs").rglob("*.md")])
    return [p for p in found if "<!-- table: " in p.read_text(encoding="utf-8")]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.page_tables", description=__doc__.split("\n")[0])
    p.add_argument("--check", action="store_true", help="only compare; exit 1 when a table differs")
    args = p.parse_args(argv)
    stale = []
    for page in pages():
        text = page.read_text(encoding="utf-8")
        new = render_page(text)
        if new != text:
            stale.append(str(page.relative_to(ROOT)))
            if not args.check:
                page.write_text(new, encoding="utf-8")
    if args.check:
        print(f"stale: {', '.join(stale)}; run python -m benchmarks.page_tables" if stale else "up to date")
        return 1 if stale else 0
    print(f"rewrote {', '.join(stale)}" if stale else "every table up to date")
    return 0


if __name__ == "__main__":
    sys.exit(main())
