"""The README's examples ("Your own system", "Your own agent") run as written."""

from __future__ import annotations

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def section_code(title: str) -> str:
    text = README.read_text()
    start = text.index(f"## {title}\n")
    end = text.find("\n## ", start + 1)
    blocks = re.findall(r"```python\n(.*?)```", text[start:end], flags=re.S)
    assert blocks, f"no python block under '## {title}'"
    return "\n".join(blocks)


def test_the_own_system_example_runs(capsys):
    namespace: dict = {"__name__": "readme_example"}
    exec(compile(section_code("Your own system"), "README.md", "exec"), namespace)  # noqa: S102
    env, info = namespace["env"], namespace["info"]
    # The example's claims: the mass ends near the goal with no constraint excess.
    assert abs(info["true_state"][0] - 3.0) < 0.3 and abs(info["true_state"][1] - 0.3) < 0.3
    assert max(info["constraint_excess"]) < 0.05
    assert env.model.system.nw == 2


def section_blocks(title: str) -> list[str]:
    """The python blocks under ``## title``, each on its own."""
    text = README.read_text()
    start = text.index(f"## {title}\n")
    end = text.find("\n## ", start + 1)
    return re.findall(r"```python\n(.*?)```", text[start:end], flags=re.S)


def test_the_own_agent_example_runs(monkeypatch):
    import math

    import pytest

    evaluation_example, sb3_example = section_blocks("Your own agent")
    monkeypatch.chdir(README.parent)  # the examples read configs/quick.yaml
    namespace: dict = {"__name__": "readme_example"}
    exec(compile(evaluation_example, "README.md", "exec"), namespace)  # noqa: S102
    rows = namespace["rows"]
    assert [(r["agent"], r["seed"], r["error"]) for r in rows] == [
        (a, s, "") for a in ("nominal", "track_follower") for s in (0, 1)
    ]
    # The example's claims: no solver, so no solver failures and n/a solve times and RMSE.
    mine = [r for r in rows if r["agent"] == "track_follower"]
    assert all(r["solver_failures"] == 0 and r["fallback_steps"] == 0 for r in mine)
    assert all(math.isnan(r["solve_time_median"]) and math.isnan(r["latent_rmse"]) for r in mine)
    assert all(r["success"] for r in mine)  # it does follow the track to the goal

    pytest.importorskip("stable_baselines3")  # the section's SB3 example needs it
    exec(compile(sb3_example, "README.md", "exec"), namespace)  # noqa: S102
    assert math.isfinite(namespace["mean_reward"]) and namespace["mean_reward"] < 0.0
