"""The scenario fan of one paper problem at N = 30, open-loop vs feedback prediction.

Records the first problem ``(x0, W)`` the paper's scenario agent meets at ``N = 30`` (env
seed 0, ``Ns = 150``), solves it with the fast solver as the open-loop problem and as the
feedback one (its law along the open-loop plan: the feedback solver's first solve), and
draws every scenario's predicted path on the track and its speed over the horizon.

    python scripts/feedback_fan.py [--seed 0] [--horizon 30] [--out docs/figures/feedback_fan.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from controllers.solvers import make_solver  # noqa: E402
from experiments.benchmark.problems import experiment_config, record_closed_loop  # noqa: E402
from lfm_env.worlds.sine_track.system import track_of  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def solve_both(seed: int, horizon: int) -> tuple:
    """The recorded problem and the open-loop and feedback solutions of it."""
    cfg = experiment_config(ROOT / "configs" / "paper.yaml")
    (rec,), _ = record_closed_loop(cfg, [seed], max_steps=1, horizon=horizon)
    out = {}
    for prediction in ("open_loop", "feedback"):
        problem = experiment_config(cfg, horizon=horizon).make_problem(prediction=prediction)
        sol = make_solver(problem, "fast").solve(rec.x0, rec.W)
        out[prediction] = (problem, sol)
    return rec, out


def draw(rec, out: dict, path: Path) -> None:
    """Paths on the track (top) and speeds (bottom), one column per prediction."""
    fig, axes = plt.subplots(2, 2, figsize=(11, 6.5), sharex="row", sharey="row")
    for col, (prediction, (problem, sol)) in enumerate(out.items()):
        X = sol.predicted  # (Ns, N+1, nx)
        track = track_of(problem.system)
        xs = np.linspace(X[..., 0].min() - 1.0, X[..., 0].max() + 1.0, 400)
        ax = axes[0, col]
        centre = track.centre_y(xs)
        for side in (-1.0, 1.0):
            ax.plot(xs, centre + side * track.half_width, color="k", lw=1.2)
        ax.plot(X[..., 0].T, X[..., 1].T, color="tab:blue", lw=0.4, alpha=0.25)
        ax.set_title(
            f"{prediction.replace('_', '-')}: slack {sol.slack:.3g}, {sol.status}\n"
            f"speed spread at N: {np.ptp(X[:, -1, 2]):.2f} m/s"
        )
        ax.set_xlabel("p_x [m]")
        t = problem.dt * np.arange(problem.horizon + 1)
        axes[1, col].plot(t, X[..., 2].T, color="tab:blue", lw=0.4, alpha=0.25)
        axes[1, col].set_xlabel("time ahead [s]")
    axes[0, 0].set_ylabel("p_y [m]")
    axes[1, 0].set_ylabel("v [m/s]")
    ns, n = rec.W.shape[:2]
    fig.suptitle(f"paper config, env seed {rec.seed}, first problem: N = {n}, Ns = {ns}")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--horizon", type=int, default=30)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "figures" / "feedback_fan.png")
    args = parser.parse_args()
    rec, out = solve_both(args.seed, args.horizon)
    for prediction, (_, sol) in out.items():
        print(f"{prediction}: objective {sol.objective:.6g} slack {sol.slack:.4g} {sol.status}")
    draw(rec, out, args.out)


if __name__ == "__main__":
    main()
