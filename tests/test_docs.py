"""The documentation resolves: relative Markdown links and their anchors, "SPEC §N" citations in
code, configs and docs, and paths under docs/ named in code; README.md stays short.

Anchors follow GitHub's heading slugs: lower case, everything but letters, digits, spaces,
hyphens and underscores removed, spaces turned into hyphens, repeated headings numbered -1, -2.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README_MAX_LINES = 250
CODE_DIRS = ("policy", "ros2_ws", "tests", "benchmarks", "docker")
CODE_SUFFIXES = {".py", ".yaml", ".yml", ".toml", ".cfg", ".xml", ".json", ".sh"}
CODE_FILES = ("Makefile", "Dockerfile")
SKIP_PARTS = {".venv", "__pycache__", "build", "install", "log", ".git", "node_modules"}

FENCE = re.compile(r"^\s*(```|~~~)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
# [text](target) and ![alt](target); the target ends at whitespace (an optional "title" follows)
LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
INLINE_CODE = re.compile(r"(`+)(.+?)\1")
SPEC_CITE = re.compile(r"SPEC\s*\[?§\s*(\d+(?:\.\d+)*)")
SPEC_SECTION = re.compile(r"^#{2,6}\s+(\d+(?:\.\d+)*)\.?\s")
DOCS_PATH = re.compile(r"(?<![\w./-])docs/[\w./<>{}*,-]*")


# ---- helpers ---------------------------------------------------------------------------------
def _files(root: Path, dirs, suffixes, names=()) -> list[Path]:
    out = []
    for d in dirs:
        base = root / d
        if not base.exists():
            continue
        for p in sorted(base.rglob("*")):
            if p.is_file() and not SKIP_PARTS & set(p.relative_to(root).parts) and (
                    p.suffix in suffixes or p.name in names):
                out.append(p)
    return out


def markdown_files(root: Path) -> list[Path]:
    files = [root / "README.md"] if (root / "README.md").exists() else []
    return files + _files(root, ["docs"], {".md"})


def code_files(root: Path) -> list[Path]:
    files = [root / n for n in CODE_FILES if (root / n).is_file()]
    return files + _files(root, CODE_DIRS, CODE_SUFFIXES, CODE_FILES)


def prose_lines(text: str):
    """(line number, line) of Markdown outside fenced code blocks, inline code removed."""
    fenced = False
    for i, line in enumerate(text.splitlines(), 1):
        if FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            yield i, line


def slug(heading: str) -> str:
    """GitHub's anchor for a heading text (before de-duplication)."""
    text = INLINE_CODE.sub(lambda m: m.group(2), heading)
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", text)  # links: their text
    text = re.sub(r"<[^>]+>", "", text)  # inline HTML tags
    text = re.sub(r"[^\w\- ]", "", text.strip().lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for _, line in prose_lines(path.read_text(encoding="utf-8")):
        m = HEADING.match(line)
        if not m:
            continue
        s = slug(m.group(2))
        n = seen.get(s, 0)
        seen[s] = n + 1
        out.add(s if n == 0 else f"{s}-{n}")
    return out


def link_problems(root: Path) -> list[str]:
    problems = []
    cache: dict[Path, set[str]] = {}
    for md in markdown_files(root):
        text = md.read_text(encoding="utf-8")
        for no, line in prose_lines(text):
            for m in LINK.finditer(INLINE_CODE.sub("", line)):
                target = m.group(1)
                if re.match(r"[a-z][a-z0-9+.-]*:", target, re.I):  # http:, https:, mailto:, ...
                    continue
                where = f"{md.relative_to(root)}:{no}: ({target})"
                path_part, _, anchor = target.partition("#")
                dest = (md.parent / path_part).resolve() if path_part else md
                if not dest.exists():
                    problems.append(f"{where}: no such file {path_part}")
                    continue
                if anchor:
                    if dest.is_dir() or dest.suffix != ".md":
                        problems.append(f"{where}: anchor on a non-Markdown target")
                        continue
                    if dest not in cache:
                        cache[dest] = anchors(dest)
                    if anchor not in cache[dest]:
                        problems.append(f"{where}: no heading #{anchor} in {dest.relative_to(root)}")
    return problems


def spec_sections(root: Path) -> set[str]:
    spec = root / "docs" / "SPEC.md"
    return {m.group(1) for _, line in prose_lines(spec.read_text(encoding="utf-8"))
            if (m := SPEC_SECTION.match(line))}


def spec_problems(root: Path, skip: tuple[Path, ...] = ()) -> list[str]:
    sections = spec_sections(root)
    problems = []
    for f in code_files(root) + markdown_files(root):
        if f in skip:
            continue
        text = f.read_text(encoding="utf-8", errors="replace")
        for m in SPEC_CITE.finditer(text):
            if m.group(1) not in sections:
                no = text.count("\n", 0, m.start()) + 1
                problems.append(f"{f.relative_to(root)}:{no}: SPEC §{m.group(1)} is no section of docs/SPEC.md "
                                f"(sections: {', '.join(sorted(sections, key=lambda s: [int(x) for x in s.split('.')]))})")
    return problems


def docs_path_problems(root: Path, skip: tuple[Path, ...] = ()) -> list[str]:
    """Paths under docs/ named in code must exist; a templated path (<name>, {x}, *) must have its
    fixed prefix."""
    problems = []
    for f in code_files(root):
        if f in skip:
            continue
        text = f.read_text(encoding="utf-8", errors="replace")
        for m in DOCS_PATH.finditer(text):
            ref = m.group(0).rstrip(".,")
            cut = min([i for i in (ref.find(c) for c in "<{*") if i >= 0], default=len(ref))
            path = ref[:cut]
            if cut < len(ref):
                path = path[:path.rfind("/") + 1]  # the folder that holds the templated part
            if not (root / path).exists():
                no = text.count("\n", 0, m.start()) + 1
                problems.append(f"{f.relative_to(root)}:{no}: {ref} does not exist")
    return problems


# ---- the repository --------------------------------------------------------------------------
def test_markdown_links_resolve():
    problems = link_problems(ROOT)
    assert not problems, "broken links:\n" + "\n".join(problems)


def test_spec_citations_resolve():
    assert spec_sections(ROOT) >= {"1", "2", "3", "4", "5", "6"}
    problems = spec_problems(ROOT, skip=(Path(__file__).resolve(),))  # its fixtures cite on purpose
    assert not problems, "\n".join(problems)


def test_docs_paths_in_code_exist():
    problems = docs_path_problems(ROOT, skip=(Path(__file__).resolve(),))  # its fixtures name missing paths
    assert not problems, "\n".join(problems)


def test_readme_is_short():
    n = len((ROOT / "README.md").read_text(encoding="utf-8").splitlines())
    assert n <= README_MAX_LINES, f"README.md has {n} lines (at most {README_MAX_LINES}); move detail to docs/"


def test_mission_examples_in_the_docs_load():
    """Every ``hmrta-instance/1`` YAML block in README.md and docs/ is a mission hmrta accepts
    (a feasible team, every field right)."""
    import yaml

    from hmrta.instance import instance_from_dict

    found = 0
    for f in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for block in re.findall(r"```yaml\n(.*?)```", f.read_text(encoding="utf-8"), flags=re.S):
            if block.startswith("format: hmrta-instance/1"):
                instance_from_dict(yaml.safe_load(block), str(f.relative_to(ROOT)))
                found += 1
    assert found >= 2


# ---- the checkers catch what they should -------------------------------------------------------
@pytest.mark.parametrize("heading, expected", [
    ("1. Problem (species-traits model)", "1-problem-species-traits-model"),
    ("4. Metrics (per instance; mean ± std)", "4-metrics-per-instance-mean--std"),
    ("Team-scaled cap (`max_open: team`)", "team-scaled-cap-max_open-team"),
    ("Alternative checkpoint `coalition-open.pt`", "alternative-checkpoint-coalition-openpt"),
    ("See [the spec](SPEC.md) — now", "see-the-spec--now"),
])
def test_slug_follows_github(heading, expected):
    assert slug(heading) == expected


def _tree(tmp_path: Path, readme: str, doc: str, code: str = "") -> Path:
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "SPEC.md").write_text("# Spec\n\n## 1. One\n\n## 2. Two\n\n### 2.1 Sub\n")
    (tmp_path / "docs" / "guide.md").write_text(doc)
    (tmp_path / "README.md").write_text(readme)
    (tmp_path / "policy").mkdir()
    (tmp_path / "policy" / "mod.py").write_text(code)
    return tmp_path


def test_checkers_accept_a_sound_tree(tmp_path):
    root = _tree(tmp_path,
                 "[guide](docs/guide.md#usage-notes) ![spec](docs/SPEC.md#21-sub) [web](https://x.org/a)\n"
                 "```\n[not a link](nowhere.md)\n```\n`[code](nowhere.md)`\n",
                 "## Usage notes\n\n## Usage notes\n\n[again](#usage-notes-1) [up](../README.md)\n",
                 '"""SPEC §2.1 and SPEC §1; see docs/guide.md and docs/<name>/x.md"""\n')
    assert link_problems(root) == []
    assert spec_problems(root) == []
    assert docs_path_problems(root) == []


def test_checkers_report_breakage(tmp_path):
    root = _tree(tmp_path,
                 "[gone](docs/missing.md) [bad anchor](docs/guide.md#nope)\n",
                 "## Title\n\n[self](#title) [self bad](#titles)\n",
                 "# SPEC §3 and SPEC §2.2 and SPEC §1\n# see docs/missing/file.md and docs/guide.md\n")
    links = link_problems(root)
    assert len(links) == 3, links
    assert any("no such file docs/missing.md" in p for p in links)
    assert any("#nope" in p for p in links) and any("#titles" in p for p in links)
    spec = spec_problems(root)
    assert [p.split(": ")[1].split(" is")[0] for p in spec] == ["SPEC §3", "SPEC §2.2"], spec
    paths = docs_path_problems(root)
    assert len(paths) == 1 and "docs/missing/file.md" in paths[0], paths


def test_long_readme_is_reported(tmp_path, monkeypatch):
    (tmp_path / "README.md").write_text("line\n" * (README_MAX_LINES + 1))
    monkeypatch.setitem(globals(), "ROOT", tmp_path)
    with pytest.raises(AssertionError, match="at most 250"):
        test_readme_is_short()
