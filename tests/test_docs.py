"""The manual stays a manual: short pages, links that resolve, and run pages that an index lists
and whose recorded commands write them where they are."""

import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
RUNS = DOCS / "runs"

README_LIMIT_BYTES = 10_000
PAGE_LIMIT_BYTES = 40_000

# [text](target) and ![alt](target); the target ends at the first space (a title may follow) or ")".
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.MULTILINE | re.DOTALL)
INLINE_CODE = re.compile(r"`[^`\n]*`")


def markdown_pages() -> list[Path]:
    return [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]


def relative_links(page: Path) -> list[str]:
    """The page's link and image targets that point into the repository (code is not prose)."""
    text = INLINE_CODE.sub("", FENCE.sub("", page.read_text()))
    targets = []
    for target in LINK.findall(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE) or target.startswith("#"):
            continue  # http:, https:, mailto:, or an anchor on the same page
        targets.append(target.split("#", 1)[0])
    return targets


def test_readme_is_short():
    size = (ROOT / "README.md").stat().st_size
    assert size < README_LIMIT_BYTES, f"README.md is {size} bytes; the manual under docs/ is the place for more"


def test_manual_pages_are_short():
    too_big = {str(page.relative_to(ROOT)): page.stat().st_size for page in DOCS.rglob("*.md")
               if RUNS not in page.parents and page.stat().st_size > PAGE_LIMIT_BYTES}
    assert not too_big, f"manual pages over {PAGE_LIMIT_BYTES} bytes (split them, or move a run's log to docs/runs/): {too_big}"


@pytest.mark.parametrize("page", markdown_pages(), ids=lambda page: str(page.relative_to(ROOT)))
def test_relative_links_resolve(page):
    broken = [target for target in relative_links(page) if not (page.parent / target).exists()]
    assert not broken, f"{page.relative_to(ROOT)} links to missing files: {broken}"


def test_link_finder_sees_links_and_images_but_not_code(tmp_path):
    page = tmp_path / "page.md"
    page.write_text('See [a](a.md#part), ![b](img/b.png "title") and [c](https://x.org).\n'
                    "`[d](d.md)`\n```\n[e](e.md)\n```\n[f](#here)\n")
    assert relative_links(page) == ["a.md", "img/b.png"]


def test_runs_index_lists_every_run_page():
    index = RUNS / "index.md"
    listed = {Path(target).name for target in relative_links(index)}
    pages = {page.name for page in RUNS.glob("*.md")} - {"index.md"}
    assert pages, "docs/runs/ holds the generated run pages"
    assert not pages - listed, f"docs/runs/index.md does not list {sorted(pages - listed)}"


def recorded_out(page: Path) -> str | None:
    """The `--out` of the command a run page says made it (the first indented line after "Made by")."""
    lines = page.read_text().splitlines()
    if "Made by" not in lines[:4]:
        return None
    command = next(line for line in lines if line.startswith("    "))
    words = shlex.split(command)
    return words[words.index("--out") + 1] if "--out" in words else None


@pytest.mark.parametrize("page", sorted(RUNS.glob("*.md")), ids=lambda page: page.name)
def test_run_page_command_writes_the_page_where_it_is(page):
    out = recorded_out(page)
    if out is not None:
        assert out == str(page.relative_to(ROOT)), f"{page.name}'s command writes {out}"


def test_paper_experiment_writes_its_run_page():
    from ditch_drake.pipelines.experiment import load_experiment

    report = Path(load_experiment(str(ROOT / "experiments" / "paper.yaml")).report)
    assert (report if report.is_absolute() else ROOT / report) == RUNS / "paper_studies.md"
