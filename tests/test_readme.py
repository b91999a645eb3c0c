"""The README's "Your own system" example runs as written."""

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
