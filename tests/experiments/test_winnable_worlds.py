"""A world can be won: the oracle (certainty-equivalent MPC that reads the true state and the
true future force) survives every seed of 0..199 on the quadrotor. At the gust of
``QuadrotorGust-v0`` (std 2.5 m/s^2) a gust held beyond the hovering vehicle's horizontal
authority blew it out of the back of the safety box on seeds 26, 33, 41, 72 and 79."""

from __future__ import annotations

import pytest

from experiments.evaluation import evaluate


@pytest.mark.slow
def test_the_oracle_survives_every_quadrotor_seed_of_0_to_199(tmp_path):
    rows = evaluate(
        ["oracle"], range(200), config="quadrotor", out=tmp_path, jobs=2, progress=False
    )
    assert len(rows) == 200
    assert [r["seed"] for r in rows if r["error"]] == []
    assert [r["seed"] for r in rows if r["failure"]] == []
