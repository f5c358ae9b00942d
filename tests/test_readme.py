"""The README and docs stay honest: short README, links that resolve, commands that exist, results that match the reports."""
from __future__ import annotations

import argparse
import json
import re
import shlex
from pathlib import Path

import pytest

from benchmarks import results_page

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"
PAGES = [README, *sorted((REPO / "docs").glob("*.md"))]
FENCE = re.compile(r"^ *```.*?^ *```", re.S | re.M)
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def slug(heading: str) -> str:
    """A markdown heading's anchor as GitHub makes it: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    return {slug(line.lstrip("#")) for line in FENCE.sub("", page.read_text()).splitlines() if line.startswith("#")}


def relative_links(page: Path) -> list[str]:
    """The targets of a page's markdown links and images, outside code blocks, that are not web addresses."""
    return [t for t in LINK.findall(FENCE.sub("", page.read_text())) if not re.match(r"[a-z]+:", t)]


def subcommands(parser: argparse.ArgumentParser) -> set[str]:
    return {name for action in parser._actions if isinstance(action, argparse._SubParsersAction)
            for name in action.choices}


def shown_commands(text: str) -> list[tuple[str, str]]:
    """(program, subcommand) for every console command in a page's code: fenced blocks and inline spans."""
    code = FENCE.findall(text) + re.findall(r"`([^`\n]+)`", FENCE.sub("", text))
    return [(m.group(1), m.group(2)) for block in code
            for m in re.finditer(r"(?:^|(?<=[\s;&|(]))(datagen|label-tool|panolam) +([a-z][\w-]*)", block, re.M)]


def test_readme_is_short():
    lines = README.read_text().count("\n")
    assert lines <= 400, f"README.md has {lines} lines; move detail to docs/"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_relative_links_resolve(page):
    broken = []
    for target in relative_links(page):
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.is_file():
            broken.append(f"{target}: no such file")
        elif anchor and file.suffix == ".md" and anchor not in anchors(file):
            broken.append(f"{target}: no heading with that anchor in {file.name}")
    assert not broken, f"{page.relative_to(REPO)}: " + "; ".join(broken)


def test_link_checker_sees_a_broken_link(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("# Top\n\n[ok](#top) [gone](missing.md) ![img](x.png) [web](https://example.org)\n"
                    "```\n[not a link](inside-code.md)\n```\n")
    assert relative_links(page) == ["#top", "missing.md", "x.png"]
    assert anchors(page) == {"top"}


def test_readme_commands_exist():
    from datagen.cli import build_parser as datagen
    from labeling_tool.cli import build_parser as label_tool
    from panolam.cli import build_parser as panolam
    known = {"datagen": subcommands(datagen()), "label-tool": subcommands(label_tool()),
             "panolam": subcommands(panolam())}
    shown = shown_commands(README.read_text())
    assert {program for program, _ in shown} == set(known), "the README should show every program"
    unknown = sorted({f"{program} {sub}" for program, sub in shown if sub not in known[program]})
    assert not unknown, f"README.md shows commands that do not exist: {unknown}"
    assert shown_commands("`datagen sampel DIR`, `label-tool`, x.panolam train") == [("datagen", "sampel")]


def bash_command_lines(text: str) -> list[list[str]]:
    """The words of every datagen, label-tool and panolam line in a page's bash blocks (comments dropped)."""
    lines = [shlex.split(line, comments=True) for block in re.findall(r"^ *```bash\n(.*?)^ *```", text, re.S | re.M)
             for line in block.splitlines()]
    return [words for words in lines if words and words[0] in ("datagen", "label-tool", "panolam")]


def test_readme_command_lines_parse_with_full_option_names():
    """Every command the README runs parses, and names each option in full (no abbreviation argparse happens to accept)."""
    from datagen.cli import build_parser as datagen
    from labeling_tool.cli import build_parser as label_tool
    from panolam.cli import build_parser as panolam
    parsers = {"datagen": datagen(), "label-tool": label_tool(), "panolam": panolam()}
    lines = bash_command_lines(README.read_text())
    assert len(lines) >= 10
    for words in lines:
        parser = parsers[words[0]]
        parser.parse_args(words[1:])
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[words[1]]
        options = {o for action in sub._actions for o in action.option_strings}
        abbreviated = [w.split("=")[0] for w in words[2:] if w.startswith("--") and w.split("=")[0] not in options]
        assert not abbreviated, f"{' '.join(words)}: not an option of {words[0]} {words[1]}: {abbreviated}"


def test_results_page_is_up_to_date():
    assert results_page.PAGE.read_text() == results_page.build(), \
        "docs/results.md is out of date: run python -m benchmarks.results_page"


def test_results_page_links_every_report():
    page = results_page.PAGE.read_text()
    reports = sorted(results_page.REPORTS.glob("*.md")) + sorted(results_page.REPORTS.glob("*.json"))
    missing = [p.name for p in reports if f"]({results_page.LINK}/{p.name})" not in page]
    assert reports and not missing, f"docs/results.md does not link {missing}"


def test_results_page_names_a_broken_report(tmp_path, monkeypatch):
    (tmp_path / "broken.json").write_text("{not json")
    (tmp_path / "good.json").write_text(json.dumps({"machine": {"cpu_model": "X", "usable_cpus": 3}, "seed": 5}))
    monkeypatch.setattr(results_page, "REPORTS", tmp_path)
    assert "Machine: X, 3 usable CPUs" in "\n".join(results_page.section("good"))
    assert "Seeds: 5." in "\n".join(results_page.section("good"))
    with pytest.raises(SystemExit, match="broken.json: not valid JSON"):
        results_page.build()


def test_reports_tell_hosts_of_one_cpu_name_apart():
    import torch

    from benchmarks.common import machine_info
    m = machine_info()
    assert m["cpu_capability"] and m["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    line = results_page.machine_line({"machine": {"cpu_model": "AMD EPYC", "usable_cpus": 2, "cpu_capability": "AVX2",
                                                  "cpu_family_model": "family 23 model 1"}})
    assert line.startswith("Machine: AMD EPYC (family 23 model 1, AVX2), 2 usable CPUs")
