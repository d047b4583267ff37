"""The front page and the doc/ pages against the code they describe: the test command
against CI, links and pictures against the files they name (the parameter tables against
the nodes' configuration trees: test/test_parameter_files.py)."""

from __future__ import annotations

import importlib
import os
import re
import subprocess
import unicodedata
from pathlib import Path

import pytest

from h2o_slam.app.cli.demo import PLOTS

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "doc").glob("*.md"))]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
#: Folders that are not the project's own files (when there is no git to list those).
NOT_OURS = {".git", ".venv", "build", "install", "out", "log", "__pycache__",
            ".mypy_cache", ".ruff_cache", ".pytest_cache", ".hypothesis"}
#: What a clone cannot have: a sibling folder of data beside it, this machine's paths. Written
#: so that this file does not match them itself.
OUTSIDE = re.compile(r"\.\./shared\b|\bshared/dat[a]\b|/\s*[\"']shared[\"']|/wor[k]/")


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = heading.strip().lower()
    kept = "".join(c for c in text if c in " -_" or unicodedata.category(c)[0] in "LMN")
    return kept.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    text = re.sub(r"^```.*?^```", "", path.read_text(), flags=re.M | re.S)
    return {slug(m[1]) for m in re.finditer(r"^#+ (.+)$", text, flags=re.M)}


def test_the_front_pages_test_command_is_what_ci_runs() -> None:
    readme = (ROOT / "README.md").read_text()
    commands = re.findall(r"^(make \w+)\s+#", readme, flags=re.M)
    assert commands[:2] == ["make demo", "make test"]
    ci = (ROOT / ".ci/run").read_text()
    assert re.search(r"^make test\b", ci, flags=re.M)
    assert re.search(r"^test:", (ROOT / "Makefile").read_text(), flags=re.M)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_links_name_files_and_headings_that_exist(page: Path) -> None:
    text = re.sub(r"^```.*?^```", "", page.read_text(), flags=re.M | re.S)
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target):
            continue  # a web address: not checked offline
        file, _, anchor = target.partition("#")
        path = (page.parent / file).resolve() if file else page
        assert path.exists(), f"{page.name}: {target}"
        if anchor and path.suffix == ".md":
            assert anchor in anchors(path), f"{page.name}: {target}"


def _resolves(dotted: str) -> bool:
    """Whether ``a.b.c`` names a module, or an attribute path inside one."""
    parts = dotted.split(".")
    for k in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:k]))
        except ImportError:
            continue
        try:
            for name in parts[k:]:
                obj = getattr(obj, name)
        except AttributeError:
            return False
        return True
    return False


@pytest.mark.parametrize("page", [*PAGES, ROOT / "bench" / "README.md"], ids=lambda p: p.name)
def test_module_names_in_the_docs_exist(page: Path) -> None:
    """Every ``h2o_slam.…``, ``hybrid_vo.…`` and ``msg_adapters.…`` name a page mentions
    is a module or something in one: the pages follow the code when it moves."""
    names = set(re.findall(r"\b(?:h2o_slam|hybrid_vo|msg_adapters)(?:\.[A-Za-z_]\w*)+",
                           page.read_text()))
    files = ("yaml", "tum", "xml", "py", "rviz", "png", "json", "csv", "md", "g2o")
    names = {n for n in names if n.rsplit(".", 1)[-1] not in files
             and not n.startswith("h2o_slam.launch")}
    missing = sorted(n for n in names if not _resolves(n))
    assert not missing, f"{page.name} names what does not exist: {missing}"


def test_the_front_page_shows_the_demos_plots_and_make_copies_them() -> None:
    readme = (ROOT / "README.md").read_text()
    shown = re.findall(r"!\[[^\]]*\]\(doc/images/([\w.]+)\)", readme)
    assert sorted(shown) == sorted(PLOTS)
    for name in PLOTS:
        blob = (ROOT / "doc/images" / name).read_bytes()
        assert blob[:8] == PNG_MAGIC and len(blob) > 10_000, name
    makefile = (ROOT / "Makefile").read_text()
    listed = re.search(r"^DOC_IMAGES := (.+)$", makefile, flags=re.M)
    assert listed is not None and sorted(listed[1].split()) == sorted(PLOTS)
    assert re.search(r"^doc-images:", makefile, flags=re.M)


def test_the_front_page_is_short_and_every_doc_page_is_linked_from_it() -> None:
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) < 200
    for page in (ROOT / "doc").glob("*.md"):
        assert f"(doc/{page.name})" in readme, page.name


def project_files() -> list[Path]:
    """The files of the project: what ``git ls-files`` lists, or, without git, every file
    under the root outside :data:`NOT_OURS` and ``*.egg-info``."""
    try:
        listed = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True,
                                check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        files = []
        for folder, dirs, names in os.walk(ROOT):
            dirs[:] = [d for d in dirs if d not in NOT_OURS and not d.endswith(".egg-info")]
            files += [Path(folder) / name for name in names]
        return files
    return [ROOT / name for name in listed.decode().split("\0") if name]


def test_nothing_points_outside_the_repository() -> None:
    """A clone stands alone: no file names a data folder beside the clone or a path of the
    machine it was written on (optional data come from ``--data`` or an environment
    variable, as ``bench/README.md`` and ``doc/install.md`` say)."""
    files = project_files()
    assert any(p.name == "README.md" for p in files)
    found = []
    for path in files:
        try:
            blob = path.read_bytes()
        except (FileNotFoundError, IsADirectoryError):
            continue  # listed by git but deleted (or a submodule) in this working tree
        if b"\0" in blob[:8192]:
            continue  # binary: a picture, a bag
        for number, line in enumerate(blob.decode("utf-8", "replace").splitlines(), 1):
            if OUTSIDE.search(line):
                found.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()[:120]}")
    assert not found, "points outside the repository:\n" + "\n".join(found)
