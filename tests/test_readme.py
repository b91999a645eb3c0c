"""The README and the pages of docs/ show what works: every ```python block runs as written, the
claims the own-system examples make in words hold, and every ``lfm-*`` command line of a
```bash block is a valid invocation of the current command.

Every python block runs alone, as a reader would paste it: in a namespace of its own (its
imports in the block), from an empty temporary folder (presets by name, not ``configs/...``
paths; the files the examples write stay under ``tmp_path``). A block that imports an optional
extra (:data:`OPTIONAL`) is skipped through ``pytest.importorskip`` when the extra is missing.
"""

from __future__ import annotations

import math
import re
import shlex
from collections.abc import Callable
from pathlib import Path

import gymnasium as gym
import pytest

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
OPTIONAL = ("stable_baselines3",)  # extras a block may need (the rl and test extras)


def fenced_blocks(page: Path, language: str) -> list[str]:
    """The bodies of the page's fenced blocks of ``language``, in order."""
    return re.findall(rf"^```{language}\n(.*?)^```", page.read_text(), flags=re.S | re.M)


def page_id(page: Path) -> str:
    return page.relative_to(REPO).as_posix()


# --- the claims the examples make in words, checked right after the block that makes them ---


def own_system_claims(namespace: dict) -> None:
    """The point mass ends near the goal with no constraint excess."""
    env, info = namespace["env"], namespace["info"]
    assert abs(info["true_state"][0] - 3.0) < 0.3 and abs(info["true_state"][1] - 0.3) < 0.3
    assert max(info["constraint_excess"]) < 0.05
    assert env.model.system.nw == 2


def own_agent_claims(namespace: dict) -> None:
    """No solver: no solver failures, n/a solve times and RMSE; it follows the track."""
    rows = namespace["rows"]
    assert [(r["agent"], r["seed"], r["error"]) for r in rows] == [
        (a, s, "") for a in ("nominal", "track_follower") for s in (0, 1)
    ]
    mine = [r for r in rows if r["agent"] == "track_follower"]
    assert all(r["solver_failures"] == 0 and r["fallback_steps"] == 0 for r in mine)
    assert all(math.isnan(r["solve_time_median"]) and math.isnan(r["latent_rmse"]) for r in mine)
    assert all(r["success"] for r in mine)  # it does follow the track to the goal


def sb3_claims(namespace: dict) -> None:
    assert math.isfinite(namespace["mean_reward"]) and namespace["mean_reward"] < 0.0


def own_world_claims(namespace: dict) -> None:
    """The registered world is the quadrotor in a lower tunnel, and it evaluates."""
    env, rows = namespace["env"], namespace["rows"]
    assert env.unwrapped.config.corridor_half_height == 0.25
    assert env.spec.max_episode_steps == 120
    assert [(r["agent"], r["error"]) for r in rows] == [("nominal", "")]


def tour_claims(namespace: dict) -> None:
    """The tour's report is written, and its table holds both agents on both seeds."""
    assert Path("results/tour/report.md").is_file() and Path("results/tour/report.html").is_file()
    rows = namespace["rows"]
    assert sorted((r["agent"], r["seed"]) for r in rows) == [
        (a, s) for a in ("nominal", "scenario") for s in (0, 1)
    ]
    assert all(r["error"] == "" for r in rows)


def export_claims(namespace: dict) -> None:
    """The exported robust agent drives the paper's episode to the goal; example solves the
    last step's problem and prints a plan of N rows."""
    import numpy as np

    assert namespace["terminated"] and namespace["info"]["is_success"]
    assert namespace["result"].step_available and namespace["done"].returncode == 0
    plan = namespace["plan"]
    assert plan.shape == (namespace["result"].dimensions["N"], 2) and np.isfinite(plan).all()


# (page, a text that names the block) -> the check run after that block
CLAIMS: dict[tuple[str, str], Callable[[dict], None]] = {
    ("README.md", "write_report("): tour_claims,
    ("docs/own-system.md", 'name="point_mass"'): own_system_claims,
    ("docs/own-system.md", "class TrackFollower"): own_agent_claims,
    ("docs/own-system.md", "evaluate_policy("): sb3_claims,
    ("docs/own-system.md", "register_world("): own_world_claims,
    ("docs/export.md", "ExportedController("): export_claims,
}


def optional_extra(block: str) -> str | None:
    """The optional package a block imports, if any."""
    return next((name for name in OPTIONAL if re.search(rf"\b{name}\b", block)), None)


@pytest.fixture
def in_an_empty_folder(tmp_path, monkeypatch):
    """An empty working folder under tmp_path, far from the repository."""
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.fixture
def registries_restored():
    """Worlds an example registers are forgotten afterwards (by the project and Gymnasium)."""
    from lfm_env.worlds.registry import WORLDS

    worlds, envs = dict(WORLDS), dict(gym.envs.registry)
    yield
    WORLDS.clear()
    WORLDS.update(worlds)
    for env_id in set(gym.envs.registry) - set(envs):
        del gym.envs.registry[env_id]


# The export page builds C projects with make (1-2 minutes): with the slow tests (CI runs them).
SLOW_PAGES = ("docs/export.md",)
PYTHON_PAGES = [
    pytest.param(p, marks=pytest.mark.slow) if page_id(p) in SLOW_PAGES else p
    for p in PAGES
    if fenced_blocks(p, "python")
]


@pytest.mark.parametrize("page", PYTHON_PAGES, ids=page_id)
def test_every_python_block_runs(page, in_an_empty_folder, registries_restored):
    blocks = fenced_blocks(page, "python")
    claims = {text: check for (name, text), check in CLAIMS.items() if name == page_id(page)}
    for text in claims:  # every claim belongs to exactly one block of its page
        assert sum(text in b for b in blocks) == 1, f"{page_id(page)}: one block with {text!r}"
    skipped = []
    for number, block in enumerate(blocks, start=1):
        namespace: dict = {"__name__": "__main__"}  # each block alone, as a script of its own
        extra = optional_extra(block)
        if extra is not None:
            try:
                pytest.importorskip(extra)
            except pytest.skip.Exception:
                skipped.append(f"block {number} needs {extra}")
                continue
        code = compile(block, f"{page_id(page)}, python block {number}", "exec", dont_inherit=True)
        exec(code, namespace)  # noqa: S102
        for text, check in claims.items():
            if text in block:
                check(namespace)
    if skipped:
        pytest.skip(f"{page_id(page)}: " + "; ".join(skipped))


def test_the_pages_have_examples():
    """The README's tour and the own-system page's examples are where the claims say."""
    assert len(fenced_blocks(REPO / "README.md", "python")) == 1
    assert len(fenced_blocks(REPO / "docs" / "own-system.md", "python")) == 4


# --- the command lines ---


def command_lines(page: Path) -> list[list[str]]:
    """The ``lfm-*`` command lines of the page's bash blocks, split into words (continued
    lines joined, comments dropped)."""
    lines = []
    for block in fenced_blocks(page, "bash"):
        for line in block.replace("\\\n", " ").splitlines():
            words = shlex.split(line, comments=True)
            if words and words[0].startswith("lfm-"):
                lines.append(words)
    return lines


COMMAND_LINES = [(page, words) for page in PAGES for words in command_lines(page)]


def check_values(words: list[str], args) -> None:
    """What argparse leaves to the command: the config, the seeds and the agents exist."""
    from controllers.agents import AGENT_REGISTRY
    from experiments.cli import config_file
    from experiments.evaluation import parse_seeds

    config = getattr(args, "config", None)
    if config is not None and not str(config).startswith("results/"):  # written by a command
        assert config_file(config).is_file()
        assert "/" not in str(config), f"{config}: a preset by name runs from any folder"
    if isinstance(getattr(args, "seeds", None), str) and words[0] != "lfm-benchmark":
        assert parse_seeds(args.seeds)
    names = getattr(args, "agents", None) or getattr(args, "agent", None)
    for name in names.split(",") if names else ():
        assert name in AGENT_REGISTRY or re.fullmatch(r"[\w.]+:\w+", name), name


@pytest.mark.parametrize(
    ("page", "words"), COMMAND_LINES, ids=[f"{page_id(p)}: {w[0]}" for p, w in COMMAND_LINES]
)
def test_every_command_line_parses(page, words, capsys):
    from experiments.cli import COMMAND_PARSERS

    assert words[0] in COMMAND_PARSERS, f"{page_id(page)}: no command {words[0]}"
    try:
        args = COMMAND_PARSERS[words[0]]().parse_args(words[1:])
    except SystemExit:
        pytest.fail(f"{page_id(page)}: {shlex.join(words)}\n{capsys.readouterr().err}")
    check_values(words, args)


def test_every_script_named_exists():
    """``bash scripts/X.sh`` and ``python scripts/X.py`` of the bash blocks are files."""
    for page in PAGES:
        for block in fenced_blocks(page, "bash"):
            for script in re.findall(r"(?:bash|python) (scripts/\S+)", block):
                assert (REPO / script).is_file(), f"{page_id(page)}: {script}"


def test_every_command_is_shown():
    """Each command appears in a bash block of the README or of docs/."""
    from experiments.cli import COMMAND_PARSERS

    shown = {words[0] for _, words in COMMAND_LINES}
    assert shown == set(COMMAND_PARSERS)


def test_no_block_names_a_file_of_the_clone():
    """Presets by name: a ``configs/...`` path exists only in the clone, so a block that
    names one fails from any other folder."""
    for page in PAGES:
        for language in ("python", "bash"):
            for block in fenced_blocks(page, language):
                code = "\n".join(line.split("#")[0] for line in block.splitlines())
                assert "configs/" not in code, f"{page_id(page)}: {block[:200]}"


def layout_rows() -> list[str]:
    """The rows of the README's layout table (question | where)."""
    text = (REPO / "README.md").read_text()
    section = text.split("\n## Layout\n", 1)[1].split("\n## ", 1)[0]
    return [line for line in section.splitlines() if line.startswith("| ") and "`" in line]


def _existing(name: str, folders: list[Path]) -> list[Path]:
    """The paths ``name`` may mean: from the root or from ``folders``; a placeholder
    (``<world>``) stands for any one name."""
    pattern = re.sub(r"<\w+>", "*", name.rstrip("/"))
    return [p for base in [REPO, *folders] for p in base.glob(pattern)]


def test_the_layout_table_matches_the_tree():
    """Every path of the README's layout table exists: from the repository's root, or in a
    folder the same row names (``kernels/`` beside ``lfm_env/gp/``)."""
    rows = layout_rows()
    assert len(rows) >= 20
    missing = []
    for row in rows:
        names = [n for n in re.findall(r"`([^`\s]+)`", row) if re.fullmatch(r"[\w./<>-]+", n)]
        paths = [n for n in names if re.search(r"/|\.(py|c|h|yaml|md)$", n)]
        folders = [f for n in paths if "/" in n for f in _existing(n, [])]
        folders = [f if f.is_dir() else f.parent for f in folders]
        missing += [f"{n} ({row[:60]}...)" for n in paths if not _existing(n, folders)]
    assert missing == []


# --- the links between the pages, and no development record in the manual or the code ---


def heading_anchors(text: str) -> set[str]:
    """The anchors GitHub gives a page's headings: lower case, punctuation dropped, spaces
    as hyphens, a repeated anchor numbered (``-1``, ``-2``)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)  # not in code blocks
    anchors: set[str] = set()
    for title in re.findall(r"^#{1,6} +(.+?) *#*$", text, flags=re.M):
        slug = re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")
        n, anchor = 0, slug
        while anchor in anchors:
            n += 1
            anchor = f"{slug}-{n}"
        anchors.add(anchor)
    return anchors


def relative_links(page: Path) -> list[str]:
    """The targets of the page's Markdown links and images that are not web addresses."""
    text = re.sub(r"^```.*?^```", "", page.read_text(), flags=re.S | re.M)
    text = re.sub(r"`[^`\n]*`", "", text)  # code spans are not links
    targets = re.findall(r"\]\(([^)\s]+)\)", text)
    return [t for t in targets if not re.match(r"[a-z][a-z0-9+.-]*:", t)]


def anchors_of(page: Path) -> set[str]:
    return heading_anchors(page.read_text())


def test_every_relative_link_resolves():
    """Each link of the README and of docs/ to a file names an existing file, and each
    ``#anchor`` a heading of its page."""
    broken = []
    for page in PAGES:
        for target in relative_links(page):
            path, _, anchor = target.partition("#")
            goal = (page.parent / path).resolve() if path else page
            if not goal.exists():
                broken.append(f"{page_id(page)}: {target} (no such file)")
            elif anchor and goal.suffix == ".md" and anchor not in anchors_of(goal):
                broken.append(f"{page_id(page)}: {target} (no such heading)")
    assert broken == []


def test_heading_anchors_follow_github():
    text = "# A page\n## Real time: `agents.deadline`\n```\n# not a heading\n```\n"
    assert heading_anchors(text + "## Real time: `agents.deadline`\n") == {
        "a-page",
        "real-time-agentsdeadline",
        "real-time-agentsdeadline-1",
    }


# What the manual and the code must not hold: tracker issues, development phases and branches,
# machine paths; and in the manual, commit hashes (the history of a figure goes to
# docs/history.md or CHANGELOG.md, told by change and version).
RECORD = re.compile(r"\bissue #?[0-9]+|ISSUE_[0-9]|\bphase [12]\b|development branch|/work/", re.I)
COMMIT = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
CODE_FOLDERS = ("lfm_env", "controllers", "experiments", "configs", "scripts", "docs")
CODE_SUFFIXES = (".py", ".md", ".c", ".h", ".yaml", ".sh")


def project_files() -> list[Path]:
    """The project's own source, config and documentation files (not the tests, not the
    changelog, which is the record)."""
    files = [p for p in REPO.glob("*.md") if p.name != "CHANGELOG.md"]
    for folder in CODE_FOLDERS:
        files += [p for p in (REPO / folder).rglob("*") if p.suffix in CODE_SUFFIXES]
    return sorted(p for p in files if p.is_file() and "__pycache__" not in p.parts)


def test_no_development_record_in_code_or_docs():
    hits = [
        f"{p.relative_to(REPO)}:{n}: {line.strip()[:100]}"
        for p in project_files()
        for n, line in enumerate(p.read_text(errors="replace").splitlines(), start=1)
        if RECORD.search(line)
    ]
    assert hits == []


def test_no_commit_hash_in_the_manual():
    hits = [
        f"{page_id(p)}:{n}: {m.group()}"
        for p in PAGES
        for n, line in enumerate(p.read_text().splitlines(), start=1)
        for m in COMMIT.finditer(line)
    ]
    assert hits == []


def test_the_record_patterns_find_a_record():
    """The two patterns catch what they are for, and leave numbers and words alone."""
    assert RECORD.search("tuned for issue 13") and RECORD.search("ISSUE_37_KEYS")
    assert RECORD.search("Phase 2 must explain") and RECORD.search("at /work/main/configs")
    assert not RECORD.search("an issue of the solver, phase [rad]")
    assert COMMIT.search("the run at 632d6c2") and COMMIT.search("44133a1")
    assert not COMMIT.search("1000000 steps, 9007199254740992, deadbeefed, decade")


# --- the README's figures: stated once, and the same wherever a page repeats a table ---


def markdown_tables(text: str) -> list[list[list[str]]]:
    """The page's tables outside code blocks, each as rows of cells (header first, the
    separator row dropped)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    tables, rows = [], []
    for line in [*text.splitlines(), ""]:
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if not all(re.fullmatch(r":?-+:?", c) for c in cells):
                rows.append(cells)
        elif rows:
            tables.append(rows)
            rows = []
    return tables


def _plain(cell: str) -> str:
    """A cell without emphasis, code marks, a trailing count of seeds ``(99)`` and, for a
    header, its numbers (``48 survivor seeds`` is ``survivor seeds``)."""
    cell = re.sub(r"\s*\(\d+\)$", "", cell.replace("**", "").replace("`", ""))
    return " ".join(cell.split())


def _header(cell: str) -> str:
    return " ".join(re.sub(r"\d+", "", _plain(cell)).split())


def agent_tables(page: Path) -> list[dict[str, dict[str, str]]]:
    """The page's tables of agents (first column an agent), as agent -> header -> cell."""
    found = []
    for header, *rows in markdown_tables(page.read_text()):
        if header[0] != "agent" or not rows:
            continue
        heads = [_header(h) for h in header]
        cells = [dict(zip(heads, map(_plain, r), strict=True)) for r in rows]
        found.append({row["agent"].split()[0]: row for row in cells})
    return found


def readme_prose_figures() -> list[str]:
    """The measured figures of the README's prose (not its tables or code): numbers with a
    unit of time or a ratio, and numbers with decimals."""
    text = re.sub(r"^```.*?^```", "", (REPO / "README.md").read_text(), flags=re.S | re.M)
    prose = "\n".join(line for line in text.splitlines() if not line.startswith("|"))
    prose = re.sub(r"`[^`\n]*`|\(https?://[^)]*\)|>= \d+\.\d+", "", prose)
    unit = r"\d+(?:\.\d+)?\s?(?:ms|s|min|x)(?![\w])"
    return re.findall(rf"(?<![\w.])(?:{unit}|\d+\.\d+(?![\w.]))", prose)


def test_the_readme_states_each_figure_once():
    """A figure of the README's prose appears once in the README (a second statement of it,
    in prose or in a table, is what drifts apart when the figures are measured again)."""
    text = (REPO / "README.md").read_text()
    figures = readme_prose_figures()
    assert figures, "the prose states the durations of the main commands"
    counts = {f: len(re.findall(rf"(?<![\w.]){re.escape(f)}(?![\w.])", text)) for f in figures}
    assert {f: n for f, n in counts.items() if n != 1} == {}


def test_the_pages_repeat_the_readme_tables_as_they_are():
    """docs/evidence.md shows the README's agent tables with more columns, from the same
    runs: every column the two share holds the same cells, agent by agent."""
    readme = agent_tables(REPO / "README.md")
    evidence = agent_tables(REPO / "docs" / "evidence.md")
    assert len(readme) == 2
    for table in readme:
        heads = set(next(iter(table.values()))) - {"agent"}
        twins = [t for t in evidence if set(t) == set(table)]
        assert twins, f"evidence.md has no table of the agents {sorted(table)}"
        twin = max(twins, key=lambda t: len(heads & set(next(iter(t.values())))))
        shared = heads & set(next(iter(twin.values())))
        assert len(shared) >= 4, shared
        differ = [
            (agent, h, table[agent][h], twin[agent][h])
            for agent in table
            for h in sorted(shared)
            if table[agent][h] != twin[agent][h]
        ]
        assert differ == []


def test_the_solver_speed_table_is_the_readmes_alone():
    """The speed table's figures are stated in the README and nowhere else in the manual
    (docs/history.md, the record, excepted): the pages link to it."""
    speed = (REPO / "README.md").read_text().split("\n### Solver speed\n", 1)[1]
    table = markdown_tables(speed.split("\n## ", 1)[0])[0]
    figures = {c for row in table[1:] for c in row[1:] if re.fullmatch(r"\d+\.\d+x?", c)}
    assert len(figures) >= 8
    pages = [p for p in PAGES if p.name not in ("README.md", "history.md")]
    repeated = [
        (page_id(p), f)
        for p in pages
        for f in figures
        if re.search(
            rf"(?<![\w.\[]){re.escape(f)}{'' if f.endswith('x') else ' ?(?:ms|/)'}", p.read_text()
        )
    ]
    assert repeated == []


def test_the_layout_table_covers_the_tree():
    """Every module and folder at the top of the three packages is in the layout table (by its
    path, or by its name in a row that names its package), and so are configs/ and scripts/."""
    rows = "\n".join(layout_rows())
    tops = {
        "/".join(p.relative_to(REPO).parts[:2])
        for package in ("lfm_env", "controllers", "experiments")
        for p in (REPO / package).rglob("*")
        if p.is_file() and p.suffix in (".py", ".c", ".h") and "__pycache__" not in p.parts
    }
    tops -= {f"{package}/__init__.py" for package in ("lfm_env", "controllers", "experiments")}
    missing = [
        top
        for top in sorted(tops)
        if f"`{top}" not in rows
        and not re.search(rf"`{top.split('/')[0]}/[^`]*`[^|]*`{top.split('/')[1]}", rows)
    ]
    assert missing == []
    assert "`configs/`" in rows and "`scripts/`" in rows


def _resolves(dotted: str) -> bool:
    """``package.module.attribute...`` imports and its attributes exist."""
    import importlib

    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for name in parts[i:]:
            if not hasattr(obj, name):
                return False
            obj = getattr(obj, name)
        return True
    return False


def test_the_names_in_the_manual_exist():
    """Every dotted name of the packages (`controllers.solvers.make_solver`) the manual shows
    in code marks imports, and every path of the repository it shows exists."""
    missing = []
    for page in PAGES:
        text = page.read_text()
        for name in set(re.findall(r"`((?:lfm_env|controllers|experiments)(?:\.\w+)+)", text)):
            if not _resolves(name):
                missing.append(f"{page_id(page)}: {name}")
        folders = r"(?:lfm_env|controllers|experiments|tests|scripts|configs)"
        for path in set(re.findall(rf"`({folders}/[\w/.-]*)`", text)):
            if not re.search(r"-v\d$", path) and not (REPO / path.rstrip("/")).exists():
                missing.append(f"{page_id(page)}: {path}")
    assert sorted(missing) == []


def test_every_agents_key_is_in_the_configuration_manual():
    """The key-by-key table of docs/configuration.md names every field of the ``agents:``
    section, and no field that does not exist."""
    import dataclasses

    from controllers.config import AgentConfig

    page = (REPO / "docs" / "configuration.md").read_text()
    section = page.split("## The `agents:` section, key by key\n", 1)[1].split("\n## ", 1)[0]
    table = markdown_tables(section)[0]
    named = {k for row in table[1:] for k in re.findall(r"`(\w+)`", row[0])}
    assert named == {f.name for f in dataclasses.fields(AgentConfig)}


def test_every_registered_agent_is_described():
    """docs/agents.md's list of the registered agents names every agent of the registry."""
    from controllers.agents import AGENT_REGISTRY

    page = (REPO / "docs" / "agents.md").read_text()
    section = page.split("## The registered agents\n", 1)[1].split("\n## ", 1)[0]
    listed = set(re.findall(r"^\* `(\w+)`", section, flags=re.M))
    assert listed == set(AGENT_REGISTRY)
