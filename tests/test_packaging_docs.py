"""Packaging and documentation that a clone of the repository stands on: the declared
Python is the one the pinned stack needs, the Wan stack is an extra, compressed TIFF is
readable, and the docs the README and the code cite ship in the repository."""

from __future__ import annotations

import re
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _project() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def test_requires_python_matches_the_stack():
    spec = _project()["requires-python"]
    assert spec == ">=3.11"  # numpy 2.4, pandas 3 and snakemake 9 need 3.11
    assert sys.version_info >= (3, 11)


def test_wan_stack_is_an_extra_and_imagecodecs_is_installed():
    proj = _project()
    base = " ".join(proj["dependencies"])
    for pkg in ("diffusers", "peft", "transformers", "accelerate"):
        assert pkg not in base
        assert any(d.startswith(pkg) for d in proj["optional-dependencies"]["wan"])
    assert "imagecodecs" in base
    import imagecodecs  # LZW / Deflate TIFF (ImageJ/Fiji's default)

    assert imagecodecs.lzw_decode(imagecodecs.lzw_encode(b"surfphase")) == b"surfphase"


def test_docs_ship_and_every_link_resolves():
    for name in ("method.md", "campaign.md", "conventions.md", "outputs.md"):
        assert (ROOT / "docs" / name).is_file()
    for doc in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", doc.read_text()):
            if "://" in target:
                continue
            assert (doc.parent / target).exists(), f"{doc.name} links to missing {target}"
    outputs = (ROOT / "docs" / "outputs.md").read_text()
    assert "format version" in outputs.lower()
    campaign = (ROOT / "docs" / "campaign.md").read_text().lower()
    assert "refraction" in campaign  # where to photograph the board


def test_nothing_cites_the_design_brief_outside_the_repository():
    for path in [*ROOT.joinpath("surfphase").rglob("*.py"), ROOT / "README.md",
                 *ROOT.joinpath("workflow").rglob("*.smk")]:  # fmt: skip
        assert "DESIGN.md" not in path.read_text(), path


def _benchmark_sections() -> tuple[list[str], set[str]]:
    """BENCHMARKS.md's headings (lower case) and their GitHub anchors."""
    text = (ROOT / "BENCHMARKS.md").read_text()
    heads = [h.strip().lower() for h in re.findall(r"^#{2,3} (.+)$", text, flags=re.M)]
    anchors = {re.sub(r"[^\w\- ]", "", h).replace(" ", "-") for h in heads}
    return heads, anchors


def test_citations_of_benchmarks_name_sections_that_exist():
    # A default or comment that gives BENCHMARKS.md as its reason must name a section
    # that is still there: "(BENCHMARKS.md, fit)", '"prior"', or a link's #anchor.
    heads, anchors = _benchmark_sections()
    files = [*ROOT.joinpath("surfphase").rglob("*.py"), ROOT / "config" / "config.yaml",
             ROOT / "README.md", *ROOT.joinpath("docs").glob("*.md"),
             *ROOT.joinpath("workflow").rglob("*.smk")]  # fmt: skip
    named = 0
    for path in files:
        text = path.read_text()
        for anchor in re.findall(r"BENCHMARKS\.md#([\w-]+)", text):
            assert anchor in anchors, f"{path.name} links to BENCHMARKS.md#{anchor}"
            named += 1
        pattern = r"BENCHMARKS\.md`?(?:\]\([^)]*\))?, \"?([a-z][\w -]*?)\"?[,)]"
        for section in re.findall(pattern, text):
            assert any(h.startswith(section.lower()) for h in heads), (
                f"{path.name} cites BENCHMARKS.md, {section}: no such section"
            )
            named += 1
    assert named >= 5  # the pattern still finds the citations
