"""The README is for users: short, the scan command early, and every command it names exists.

Its examples are parsed by the real CLI parser (nothing runs), and every
relative link of the README and docs/ leads to a file and heading that exist.
"""

import contextlib
import io
import re
import shlex

import pytest

from pipeline.cli import build_parser
from tests.conftest import ROOT

README = ROOT / "README.md"
DOCS = [README, *sorted((ROOT / "docs").glob("*.md"))]


def _fenced(text, lang="sh"):
    """The lines of every ```LANG block, continuation lines joined."""
    blocks = re.findall(rf"^```{lang}\n(.*?)^```", text, flags=re.S | re.M)
    return [line for block in blocks for line in block.replace("\\\n", " ").splitlines()]


def _commands(text):
    """Each ``pointmark ...`` named in the README: code spans and shell blocks, as argument lists."""
    spans = re.findall(r"`(pointmark [^`]+)`", re.sub(r"^```.*?^```", "", text, flags=re.S | re.M))
    lines = [line.strip() for line in _fenced(text)]
    return [shlex.split(c, comments=True)[1:] for c in spans + lines if c.startswith("pointmark ")]


def _choices(words):
    """The subcommands ``pointmark WORDS`` offers (empty for a leaf); fails if it is no command."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()), \
            pytest.raises(SystemExit) as stop:
        build_parser().parse_args([*words, "--help"])
    assert stop.value.code == 0, f"`pointmark {' '.join(words)}` is not a command of the CLI"
    found = re.search(r"\{([a-z,-]+)\}", out.getvalue().split("\n\n")[0])
    return set(found.group(1).split(",")) if found else set()


def _slug(heading):
    """GitHub's anchor of a Markdown heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_at_most_250_lines_with_the_scan_command_in_the_first_100():
    lines = README.read_text().splitlines()
    assert len(lines) <= 250
    first = next(i for i, line in enumerate(lines) if re.match(r"\s*pointmark scan \S", line))
    assert first < 100, f"the scan command is on line {first + 1}"


def test_every_command_it_names_exists():
    named = _commands(README.read_text())
    assert {argv[0] for argv in named} >= {"embed", "detect", "attack", "catalog", "run", "scan", "evaluate",
                                         "validate", "schema", "ledger"}
    for argv in named:
        words, offered = [], _choices([])
        for word in argv:
            if not offered or not re.fullmatch(r"[a-z][a-z-]*", word):
                break
            assert word in offered, f"`pointmark {' '.join(words + [word])}`: no such command ({sorted(offered)})"
            words.append(word)
            offered = _choices(words)


def test_every_example_parses():
    block = README.read_text()
    variables = dict(re.findall(r'^(\w+)="([^"]*)"', "\n".join(_fenced(block)), flags=re.M))
    examples = [line.strip() for line in _fenced(block) if line.strip().startswith("pointmark ")]
    assert len(examples) >= 10
    for line in examples:
        line = re.sub(r"\$(\w+)", lambda m: variables[m.group(1)], line)
        argv = shlex.split(line.split(" > ")[0], comments=True)[1:]
        with contextlib.redirect_stderr(io.StringIO()) as err:
            try:
                build_parser().parse_args(argv)
            except SystemExit:
                pytest.fail(f"{line}: {err.getvalue().strip()}")


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_relative_link_leads_to_a_file_and_heading(doc):
    text = doc.read_text()
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+://", target):
            continue
        path, _, anchor = target.partition("#")
        dest = (doc.parent / path).resolve() if path else doc
        assert dest.exists(), f"{doc.name}: link to {target}: no such file"
        if anchor:
            headings = re.findall(r"^#+ (.+)$", dest.read_text(), flags=re.M)
            assert anchor in {_slug(h) for h in headings}, f"{doc.name}: link to {target}: no such heading"
