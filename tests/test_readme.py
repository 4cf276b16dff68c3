"""The README stays short and true: every command its code blocks show exists with the options they
name, every `make` target and variable is the Makefile's, and every relative link in README.md and docs/
resolves."""

import re
import shlex
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))  # the manual
NOTEBOOK = sorted((ROOT / "docs" / "lab").glob("*.md"))
SHELL = {"", "bash", "sh", "shell", "console", "zsh"}
RAGSPLAT = re.compile(r"^(?:\$\s+)?(?:\S*/)?ragsplat\s+(.*)$")  # ragsplat, .venv/bin/ragsplat, $ ragsplat
MAKE = re.compile(r"^(?:\$\s+)?make\s+(.*)$")
OPTION = re.compile(r"(?<![\w-])--[a-zA-Z][\w-]*")


def code_blocks(text: str) -> list[tuple[str, list[str]]]:
    """(language, lines) of every fenced block."""
    blocks, lang, lines = [], None, []
    for line in text.splitlines():
        fence = re.match(r"^\s*(```|~~~)\s*([\w+-]*)", line)
        if fence and lang is None:
            lang, lines = fence.group(2).lower(), []
        elif fence:
            blocks.append((lang, lines))
            lang = None
        elif lang is not None:
            lines.append(line)
    return blocks


def commands(text: str) -> list[str]:
    """Shell lines of the fenced blocks, continuations joined, comments dropped."""
    out = []
    for lang, lines in code_blocks(text):
        if lang not in SHELL:
            continue
        joined, pending = [], ""
        for line in lines:
            line = re.sub(r"(^|\s)#.*$", "", line).rstrip()
            if line.endswith("\\"):
                pending += line[:-1] + " "
                continue
            joined.append((pending + line).strip())
            pending = ""
        out += [line for line in joined if line]
    return out


def ragsplat_lines(text: str) -> list[str]:
    return [m.group(1) for line in commands(text) if (m := RAGSPLAT.match(line))]


def make_lines(text: str) -> list[str]:
    return [m.group(1) for line in commands(text) if (m := MAKE.match(line))]


_HELP: dict[tuple[str, ...], str] = {}  # `ragsplat PATH --help`, fetched once per (sub)command


def _run_help(path: tuple[str, ...]) -> str:
    done = subprocess.run([sys.executable, "-m", "ragsplat.cli.main", *path, "--help"], check=False,
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, f"`ragsplat {' '.join(path)} --help` failed:\n{done.stderr}"
    return done.stdout


def prefetch(paths) -> None:
    """The help texts of `paths` not fetched yet, in parallel (each starts a Python process)."""
    todo = sorted(set(paths) - set(_HELP))
    with ThreadPoolExecutor(max(1, min(8, len(todo)))) as pool:
        _HELP.update(zip(todo, pool.map(_run_help, todo)))


def help_text(path: tuple[str, ...]) -> str:
    if path not in _HELP:
        _HELP[path] = _run_help(path)
    return _HELP[path]


def subcommands(help_out: str) -> list[str]:
    """The choices of a parser's subcommands, as argparse prints them under "positional arguments":
    `{a,b,c}`, or (with a metavar such as COMMAND) one per line, four spaces in under the metavar's two."""
    m = re.search(r"^\s*\{([\w,-]+)\}", help_out, re.MULTILINE)
    if m:
        return m.group(1).split(",")
    section = re.search(r"^positional arguments:\n(.*?)(?:\n\S|\Z)", help_out, re.MULTILINE | re.DOTALL)
    return re.findall(r"^    ([\w-]+)", section.group(1), re.MULTILINE) if section else []


def command_path(words: list[str]) -> tuple[str, ...]:
    """The (sub)command a README line runs: ("bench", "train-step") for `ragsplat bench train-step
    --counts 0`; ("export",) for `ragsplat export runs/x --dem bed.tif` (a positional is no subcommand)."""
    path: tuple[str, ...] = ()
    for word in words:
        if word.startswith(("-", "[")) or word not in subcommands(help_text(path)):
            break
        path += (word,)
    return path


def makefile() -> str:
    return (ROOT / "Makefile").read_text()


def test_readme_is_short():
    lines = README.read_text().splitlines()
    assert len(lines) <= 300, f"README.md has {len(lines)} lines (at most 300: the rest belongs in docs/)"


def test_readme_shows_commands():
    text = README.read_text()
    assert ragsplat_lines(text) and make_lines(text)
    assert {"install", "test", "ablation"} <= {line.split()[0] for line in make_lines(text)}


def test_every_ragsplat_command_and_option_exists():
    lines = [shlex.split(line) for line in ragsplat_lines(README.read_text())]
    known_commands = subcommands(help_text(()))
    prefetch([(words[0],) for words in lines if words and words[0] in known_commands])
    prefetch([command_path(words) for words in lines])  # nested ones: `bench TARGET`
    problems = []
    for words in lines:
        line = " ".join(words)
        path = command_path(words)
        where, text = " ".join(("ragsplat",) + path), help_text(path)
        if words and not words[0].startswith("-") and not path:
            problems.append(f"`ragsplat {line}`: no command {words[0]!r}")
            continue
        if path and subcommands(text):  # a command of commands, e.g. `ragsplat bench TARGET`
            problems.append(f"`ragsplat {line}`: {where} needs one of {subcommands(text)}")
            continue
        known = set(OPTION.findall(text)) | {"--help"}
        problems += [f"`ragsplat {line}`: {where} has no {opt}"
                     for opt in OPTION.findall(line) if opt not in known]
    assert not problems, "\n".join(problems)


def test_every_make_target_and_variable_exists():
    mk = makefile()
    targets = set(re.findall(r"^([\w.-]+)\s*:(?!=)", mk, re.MULTILINE))
    problems = []
    for line in make_lines(README.read_text()):
        for word in shlex.split(line):
            if "=" in word:
                var = word.split("=", 1)[0]
                name = re.escape(var)  # used: $(VAR), ${VAR}, ifdef VAR, ifndef VAR, export VAR
                used = re.search(rf"\$[({{]{name}[)}}]|^\s*(ifn?def|export)\s+{name}\b", mk, re.MULTILINE)
                if not used:
                    problems.append(f"`make {line}`: the Makefile uses no {var}")
            elif word.startswith("-"):
                continue
            elif word not in targets:
                problems.append(f"`make {line}`: no target {word!r} in the Makefile")
    assert not problems, "\n".join(problems)


def slug(heading: str) -> str:
    """GitHub's anchor of a heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def prose(path: Path) -> str:
    """The text of a Markdown file without its fenced code blocks."""
    return re.sub(r"^\s*(```|~~~).*?^\s*\1", "", path.read_text(), flags=re.MULTILINE | re.DOTALL)


def anchors(path: Path) -> set[str]:
    text = prose(path)
    seen: dict[str, int] = {}
    out = set()
    for heading in re.findall(r"^#{1,6}\s+(.*?)\s*#*\s*$", text, re.MULTILINE):
        base = slug(heading)
        n = seen.get(base, 0)
        out.add(base if n == 0 else f"{base}-{n}")
        seen[base] = n + 1
    return out


def links(path: Path) -> list[str]:
    text = re.sub(r"`[^`\n]*`", "", prose(path))  # no inline code either
    return re.findall(r"!?\[[^\]\n]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)", text)


@pytest.mark.parametrize("path", [README, *DOCS, *NOTEBOOK], ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_resolve(path):
    problems = []
    for target in links(path):
        if re.match(r"^[a-z][\w+.-]*:", target):  # http:, https:, mailto:
            continue
        file, _, anchor = target.partition("#")
        dest = (path.parent / file).resolve() if file else path
        if not dest.exists():
            problems.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            problems.append(f"{target}: no heading #{anchor} in {dest.relative_to(ROOT)}")
    assert not problems, f"{path.relative_to(ROOT)}:\n" + "\n".join(problems)


def test_docs_are_a_manual_beside_a_notebook():
    names = {p.name for p in DOCS}
    assert {p.name for p in NOTEBOOK} >= {"history.md", "performance.md"}
    lines = sum(len(p.read_text().splitlines()) for p in DOCS)
    assert lines < 3000, f"docs/*.md: {lines} lines (the manual stays under 3 000; the notebook is docs/lab/)"
    readme = README.read_text()
    for name in names:  # the README's "More" links every docs file
        assert f"](docs/{name})" in readme, f"README.md does not link docs/{name}"
