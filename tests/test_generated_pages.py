"""The generated pages are what their renderers make of the committed raw results.

docs/results.md (``twinfocus bench paper``) and docs/beyond.md (``twinfocus bench beyond``) are
written from the raw JSON files beside them; every figure on them is the renderer's reading of
those files. Each page is re-rendered here from copies of its committed raw files into a scratch
folder (no experiment runs) and compared with the committed page, so a hand edit, a renderer
change without a regenerated page, or a raw file changed without one fails.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

from twinfocus.evaluation.beyond import write_beyond_report
from twinfocus.evaluation.report import write_report

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
_IMAGE = re.compile(r"!\[[^\]]*\]\(([^)]+\.png)\)")


def _copy_inputs(name: str, tmp: Path, extra: tuple[str, ...] = ()) -> Path:
    """A scratch ``tmp/NAME/`` holding copies of docs/NAME/raw/ and of the named files beside it,
    so that links from ``tmp/NAME.md`` read as those from docs/NAME.md."""
    out = tmp / name
    shutil.copytree(DOCS / name / "raw", out / "raw")
    for f in extra:
        shutil.copy(DOCS / name / f, out / f)
    return out


def _stale(page: Path) -> str:
    cmd = {"results": "paper", "beyond": "beyond"}[page.stem]
    return (
        f"{page.relative_to(ROOT)} is not what its raw results render to: run twinfocus bench {cmd} "
        f"--report-only --out docs/{page.stem} --markdown {page.relative_to(ROOT)}"
    )


def test_results_page_is_its_raw_results(tmp_path: Path) -> None:
    page = DOCS / "results.md"
    out = _copy_inputs("results", tmp_path, ("field_handheld.json", "field_twin.json"))
    md = write_report(out, tmp_path / "results.md")
    assert md.read_text(encoding="utf-8") == page.read_text(encoding="utf-8"), _stale(page)
    assert json.loads((out / "summary.json").read_text()) == json.loads((DOCS / "results" / "summary.json").read_text())
    # every figure the page shows is one the renderer draws, and is committed beside it
    linked = set(_IMAGE.findall(page.read_text(encoding="utf-8")))
    assert linked and linked == {f"results/{p.name}" for p in out.glob("*.png")}
    assert all((DOCS / rel).is_file() for rel in linked)


def test_beyond_page_is_its_raw_results(tmp_path: Path) -> None:
    page = DOCS / "beyond.md"
    out = _copy_inputs("beyond", tmp_path)
    md = write_beyond_report(out, tmp_path / "beyond.md")
    assert md.read_text(encoding="utf-8") == page.read_text(encoding="utf-8"), _stale(page)
    assert json.loads((out / "summary.json").read_text()) == json.loads((DOCS / "beyond" / "summary.json").read_text())


def test_generated_pages_say_so_first() -> None:
    for name, suite in (("results", "paper"), ("beyond", "beyond")):
        head = "\n".join((DOCS / f"{name}.md").read_text(encoding="utf-8").splitlines()[:3])
        assert f"generated from the raw results in docs/{name}/raw/ by `twinfocus bench {suite} --report-only" in head


def test_a_changed_raw_figure_makes_the_page_stale(tmp_path: Path) -> None:
    out = _copy_inputs("beyond", tmp_path)
    raw = out / "raw" / "beyond_error.json"
    doc = json.loads(raw.read_text())
    doc["records"][0]["ssim"] = 0.0  # one draw of "no correction", in the page's first table
    raw.write_text(json.dumps(doc))
    page = (DOCS / "beyond.md").read_text(encoding="utf-8")
    assert write_beyond_report(out, tmp_path / "beyond.md").read_text(encoding="utf-8") != page
