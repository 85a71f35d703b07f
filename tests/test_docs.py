"""The documentation tells the truth: every Python block of README.md and docs/ runs, and the site
builds with warnings as errors."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def _blocks(page: Path) -> list[str]:
    return BLOCK.findall(page.read_text())


def _runs() -> list[tuple[Path, list[str]]]:
    """What runs in one fresh interpreter: each README block on its own (a reader copies one),
    a docs page's blocks in order, in one namespace (a page builds on its earlier blocks)."""
    runs = [(ROOT / "README.md", [b]) for b in _blocks(ROOT / "README.md")]
    return runs + [(p, _blocks(p)) for p in PAGES[1:] if _blocks(p)]


@pytest.mark.parametrize(
    "page, blocks",
    _runs(),
    ids=[f"{p.relative_to(ROOT)}:{i}" for i, (p, _) in enumerate(_runs())],
)
@pytest.mark.slow
def test_python_blocks_run(page, blocks, tmp_path):
    out = subprocess.run(
        [sys.executable, "-c", "\n\n".join(blocks)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert out.returncode == 0, f"{page.name}:\n{out.stdout[-2000:]}\n{out.stderr[-4000:]}"


def test_the_readme_is_a_front_page():
    readme = ROOT / "README.md"
    assert len(readme.read_bytes()) <= 8 * 1024, "README.md over 8 KB: move detail to docs/"
    for link in re.findall(r"\]\((docs/[^)#]+)", readme.read_text()):
        assert (ROOT / link).exists(), f"README links to a missing page: {link}"


@pytest.mark.slow
def test_every_rate_in_the_readme_results_carries_its_interval():
    """A percentage in the results table's `result` column is followed by its 95 % interval
    (`[low, high]` within a few words) or is a tolerance ("within 10 %")."""
    readme = (ROOT / "README.md").read_text()
    table = readme.split("## Results", 1)[1].split("\n## ", 1)[0]
    rows = [line.split(" | ") for line in table.splitlines() if line.startswith("| ")]
    results = [cells[1] for cells in rows[2:]]  # after the header and its rule
    assert len(results) >= 10
    for cell in results:
        for m in re.finditer(r"(\d+(?:\.\d+)?) %", cell):
            after, before = cell[m.end() : m.end() + 30], cell[max(0, m.start() - 7) : m.start()]
            assert "[" in after or before == "within ", f"{m.group(0)} without interval: {cell}"


@pytest.mark.slow  # a docs build
def test_the_site_builds_strictly(tmp_path):
    pytest.importorskip("mkdocs", reason="the [docs] extra is not installed")
    out = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(tmp_path / "site")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert (tmp_path / "site" / "api" / "index.html").exists()


def test_the_reliability_page_prints_the_schemas_bounds():
    from marlmerge.config import ScenarioConfig, bounds_markdown
    from marlmerge.config.cotraining import CoTrainConfig
    from marlmerge.config.training import TrainConfig

    page = (ROOT / "docs" / "reliability.md").read_text()
    table = page.split("<!-- bounds:start -->\n")[1].split("<!-- bounds:end -->")[0]
    assert table.strip() == bounds_markdown(ScenarioConfig, TrainConfig, CoTrainConfig).strip()
