"""The README and docs/ are what users get: the README short and in a newcomer's order, both diagrams
naming every role the command line can start, every document and stored run they cite present, and
docs/benchmarks.md opening with every benchmark's current figure."""

from __future__ import annotations

import argparse
import re
import subprocess
from pathlib import Path

from dynqos.bench.suite import HEADLINES
from dynqos.cli.main import build_parser

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
TEST_COMMAND = ".venv/bin/pytest -n 2"  # the README's, and the last line of .ci/run
# the roles started as processes of their own, with the words a diagram names them by
ROLE_GROUPS = ("edge", "sim")
ROLE_COMMANDS = ("onboard", "view", "record")
FOREIGN = {"docs/design.md"}  # rmw_zenoh's own design document, cited by docs/ros2.md


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def roles() -> set[str]:
    """Every long-running role the command line starts: `dynqos edge X`, `dynqos sim X`, and the rest."""
    commands = _subcommands(build_parser())
    found = {name for group in ROLE_GROUPS for name in _subcommands(commands[group])}
    return found | {name for name in ROLE_COMMANDS if name in commands}


def first_diagram(path: Path) -> str:
    """The first fenced block that is not a shell command."""
    for block in re.findall(r"```(\w*)\n(.*?)```", path.read_text(), flags=re.S):
        if block[0] == "":
            return str(block[1])
    raise AssertionError(f"{path.name} has no diagram")


def test_the_role_list_is_the_command_lines() -> None:
    found = roles()
    assert {"router", "mpc", "planner", "fleet-planner", "detector", "qos", "ros2"} <= found
    assert {"cell", "vehicle", "px4", "onboard", "view", "record"} <= found


def test_the_readme_says_what_it_is_then_the_two_commands_within_120_lines() -> None:
    lines = README.read_text().splitlines()
    assert len(lines) <= 120, len(lines)
    head = "\n".join(lines[:10])
    assert "offload" in head
    assert "Environmental Awareness Dynamic 5G QoS" in head
    before_sections = "\n".join(lines[: next(i for i, line in enumerate(lines) if line.startswith("## "))])
    demo = '.venv/bin/pip install -e ".[dev]" && .venv/bin/dynqos demo'
    assert demo in before_sections
    assert f"\n{TEST_COMMAND}\n" in before_sections


def test_ci_runs_exactly_the_readmes_test_command() -> None:
    lines = (ROOT / ".ci" / "run").read_text().splitlines()
    assert [line for line in lines if line and not line.startswith("#")][-1] == TEST_COMMAND


def test_both_diagrams_name_every_role() -> None:
    for path in (README, DOCS / "architecture.md"):
        diagram = first_diagram(path)
        missing = {role for role in roles() if not re.search(rf"(?<![\w-]){role}(?![\w-])", diagram)}
        assert not missing, (path.name, missing)


def in_history(commit: str, path: str) -> bool | None:
    """Whether git has `path` at `commit`; None where this checkout cannot tell (no git, a shallow
    clone without that commit)."""
    try:
        known = subprocess.run(
            ["git", "-C", str(ROOT), "cat-file", "-e", f"{commit}^{{commit}}"],
            capture_output=True,
            timeout=30,
        )
        if known.returncode != 0:
            return None
        found = subprocess.run(
            ["git", "-C", str(ROOT), "cat-file", "-e", f"{commit}:{path.rstrip('/')}"],
            capture_output=True,
            timeout=30,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return found.returncode == 0


def test_every_document_and_stored_run_cited_is_there() -> None:
    """A stored run is cited as `docs/results/<run>/`, or, once it left the tree, as git names it at a
    commit: `f3b971e:docs/results/<run>/` (docs/development.md, "Storing a run")."""
    cited = re.compile(
        r"(?:\b([0-9a-f]{7,40}):)?(docs/(?:results/[\w.-]+|bench/[\w.-]+|[\w-]+\.md))|\]\((docs/[^)#]+)"
    )
    readmes = sorted(DOCS.glob("results/*/README.md")) + sorted(DOCS.glob("bench/*/README.md"))
    missing = []
    for path in [README, *sorted(DOCS.glob("*.md")), *readmes]:
        for match in cited.finditer(path.read_text()):
            commit, target = match.group(1), match.group(2) or match.group(3)
            if target in FOREIGN:
                continue
            there = in_history(commit, target) if commit else (ROOT / target).exists()
            if there is False:
                missing.append(f"{path.relative_to(ROOT)}: {match.group(0)}")
    assert not missing, missing


def test_docs_stay_under_10_mb() -> None:
    """What a clone carries: stored runs are thinned (`dynqos store`) and superseded ones leave the tree."""
    size = sum(path.stat().st_size for path in DOCS.rglob("*") if path.is_file())
    assert size <= 10_000_000, f"docs/ holds {size / 1e6:.2f} MB; see docs/development.md, 'Storing a run'"


def test_benchmarks_open_with_every_benchmarks_current_figure() -> None:
    text = (DOCS / "benchmarks.md").read_text()
    first = text[text.index("\n|") : text.index("\n\n", text.index("\n|"))]
    named = set(re.findall(r"^\| `(\w+)` \|", first, flags=re.M))
    assert set(HEADLINES) | {"vehicle_compare"} <= named, set(HEADLINES) - named
    for stored in re.findall(r"`([\w.-]+\.json)`", first):
        assert (DOCS / "bench" / stored).exists(), stored
