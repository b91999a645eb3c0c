"""Every QP call of the fast SQP gets its limits from what is left of the solve.

The recorded problem (``tests/data/hang_feedback_n30.npz``: the paper's scenario agent at
N = 30 with feedback predictions, two consecutive problems) made a solve with a 10 s limit
hang for minutes inside CasADi's qrqp, the last fallback of a failed elastic QP: a real QP
that stalls every solver of the Python loop (the compiled loop, the agents' default, solves
it: its interior point retries with a proximal term). The check runs in a fresh process, so a
hang fails it by its timeout instead of stopping the suite.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np

from controllers.solvers.fast.qp.budget import (
    PLANNED_SHARE,
    SETUP_ITERATIONS,
    QPBudget,
    work_units,
)
from controllers.solvers.fast.qp.slot_qp import SlotQP

REPO = Path(__file__).resolve().parents[4]
LIMIT = 3.0  # [s] the second solve's limit

STALL = f"""
import json
import numpy as np
from controllers.agents import make_agent
from controllers.config import load_config

d = np.load("tests/data/hang_feedback_n30.npz")
cfg = load_config({{"base": "paper", "agents": {{"horizon": 30, "prediction": "feedback",
                                                 "solver": "fast", "max_solve_time": 120}}}})
mpc = make_agent("scenario", cfg).solver
first = mpc.solve(d["x0_first"], d["W_first"])  # converges (1.3 s on a quiet machine)
mpc.set_max_time({LIMIT})
sol = mpc.solve(d["x0"], d["W"])  # stalled for minutes in qrqp before the QP budgets
print(json.dumps({{"first": first.status, "time": sol.solve_time, "status": sol.status,
                  "usable": bool(sol.usable), "retries": sol.extra["qp_retries"]}}))
"""


def test_a_solve_whose_qp_stalls_returns_by_its_limit():
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(STALL)],
        capture_output=True,
        text=True,
        env=env,
        cwd=REPO,
        timeout=300,  # the old code: minutes in one qrqp call, then more
    )
    assert out.returncode == 0, out.stderr[-3000:]
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    assert seen["first"] == "Solve_Succeeded"
    assert seen["retries"] >= 1  # an elastic QP failed and went down the retries
    # By its limit: the QP calls' budgets are estimates, so allow one more limit's worth
    # (the old code took minutes).
    assert seen["time"] <= 2 * LIMIT, seen


def _qp() -> SlotQP:
    """A small elastic QP: two inputs, one shared row, one scenario row."""
    qp = SlotQP(2, 1, 8, 4, "auto", slack_penalty=10.0, slack_reg=1e-6)
    qp.set_problem(
        np.diag([2.0, 1.0]),
        np.array([-2.0, -1.0]),
        np.full(2, -1.0),
        np.full(2, 1.0),
        np.array([[1.0, 1.0]]),
        np.array([-0.5]),
    )
    row, col = qp.assign(np.array([7]), np.array([0]))
    qp.set_position_rows(row, col, np.array([[1.0, -1.0]]), np.array([-0.2]))
    return qp


def test_no_qp_call_is_made_once_the_solve_has_no_time_left():
    qp = _qp()
    z, lam, ok = qp.solve()  # no deadline: solved
    assert ok and np.all(np.isfinite(z))
    t0 = time.perf_counter()
    z, lam, ok = qp.solve(deadline=time.perf_counter() - 1.0)
    assert not ok and np.all(np.isnan(z)) and np.all(lam == 0.0)
    assert qp.budget.refused >= 1  # the calls were refused, not made
    assert time.perf_counter() - t0 < 1.0  # (no solver ran: nothing to wait for)
    z, lam, ok = qp.solve(deadline=time.perf_counter() + 60.0)  # time again: solved again
    assert ok


def test_the_iteration_budget_follows_the_time_left_and_learns_from_calls():
    budget = QPBudget()
    assert budget.iterations("qrqp", 300, 900, 1000) == 1000  # no deadline: the solver's own
    per = budget.seconds_per_iteration("qrqp", 300, 900)
    budget.deadline = time.perf_counter() + 10 * per / PLANNED_SHARE
    n = budget.iterations("qrqp", 300, 900, 1000)
    assert 1 <= n <= 10 - SETUP_ITERATIONS["qrqp"]
    budget.deadline = time.perf_counter() + 0.5 * per  # less than one iteration: refused
    assert budget.iterations("qrqp", 300, 900, 1000) == 0 and budget.refused == 1
    # A call that took 1 s for 9 iterations teaches the object that cost.
    budget.record("piqp", 10, 10, 1.0, 9)
    units = work_units("piqp", 10, 10) * (9 + SETUP_ITERATIONS["piqp"])
    assert math.isclose(
        budget.seconds_per_iteration("piqp", 10, 10), work_units("piqp", 10, 10) / units
    )
