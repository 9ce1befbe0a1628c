"""The documentation stays usable: a short README for users, and every relative link in it and in docs/ resolves."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def _docs() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")), *sorted((ROOT / "examples").rglob("*.md"))]


def broken_links(path: Path, root: Path = ROOT) -> list[str]:
    """Relative links of a Markdown file whose target file (or #anchor's heading) does not exist."""
    out = []
    text = path.read_text()
    for target in LINK.findall(re.sub(r"```.*?```", "", text, flags=re.S)):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto: ...
            continue
        file, _, anchor = target.partition("#")
        dest = (path.parent / file).resolve() if file else path
        if not dest.exists():
            out.append(f"{path.relative_to(root)}: {target} (no such file)")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            out.append(f"{path.relative_to(root)}: {target} (no such heading)")
    return out


def _anchors(path: Path) -> set[str]:
    """GitHub's heading anchors: lower case, punctuation dropped, spaces to hyphens."""
    heads = re.findall(r"^#+\s+(.*?)\s*$", path.read_text(), flags=re.M)
    return {re.sub(r"[^\w\- ]", "", h.lower()).replace(" ", "-") for h in heads}


def test_every_relative_link_resolves():
    assert [b for p in _docs() for b in broken_links(p)] == []


def test_a_broken_link_is_found(tmp_path):
    md = tmp_path / "x.md"
    (tmp_path / "there.md").write_text("# A heading\n")
    md.write_text("[ok](there.md) [ok](there.md#a-heading) [web](https://example.org) [bad](missing.md) "
                  "[bad anchor](there.md#nope)\n")
    assert broken_links(md, tmp_path) == ["x.md: missing.md (no such file)", "x.md: there.md#nope (no such heading)"]


def test_the_readme_is_short_and_current():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 250
    assert [n for n, line in enumerate(lines, 1) if len(line) > 200] == []
    assert not [line for line in lines if re.search(r"\bissues? \d+|#\d+\b", line, flags=re.I)]


def test_the_readme_test_command_is_what_ci_runs():
    """.ci/run calls exactly the README's test command."""
    readme = (ROOT / "README.md").read_text()
    ci = [line for line in (ROOT / ".ci" / "run").read_text().splitlines() if line and not line.startswith(("#", "set ",
                                                                                                            "cd "))]
    assert len(ci) == 1 and ci[0].strip() in readme
