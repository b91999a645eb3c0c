"""Write a self-contained C project of one system and agent (``lfm-export``).

:func:`export_controller` builds the agent of a config (:func:`controllers.make_agent`), reads
every number its step needs (the scenario problem, the fast solver's options, the
estimator's model, the back-off) and writes a C project that depends on nothing but the C
library and libm:

* ``lfm_mpc.c``: the system's generated library with the compiled SQP loop
  (:func:`controllers.solvers.fast.compiled.sqp_source`: CasADi's C of the system's
  functions, the driver, the QP solvers, the loop), one translation unit;
* ``lfm_config.h`` (dimensions, names) and ``lfm_config.c`` (the numbers);
* ``lfm_controller.h`` (the documented API), ``lfm_controller.c`` (the agent's step: the
  UKF, the scenarios, the back-off, the solve, the choice of the input), ``lfm_internal.h``,
  ``sqp.h``, ``example.c`` and a ``Makefile`` (``make`` builds ``liblfm_controller.a`` and
  ``example``; ``make shared`` the shared library).

The exported step runs the agent's estimator in C where that is the UKF (or none, the
``nominal`` agent); an agent with a particle filter gets the solve only
(``lfm_controller_step`` returns ``LFM_NO_STEP``). See ``docs/export.md``.
"""

from __future__ import annotations

import math
import os
import shutil
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from controllers.config import ExperimentConfig, load_config
from controllers.solvers.fast.codegen.interface import OPTIONS, c_options
from controllers.solvers.fast.codegen.source import c_source
from controllers.solvers.fast.compiled import problem_arrays, sqp_source
from controllers.solvers.fast.options import FastSolverOptions

# The agents lfm-export writes (the oracle reads the hidden truth, the RL agent is a network).
EXPORTABLE_AGENTS = ("nominal", "pf", "scenario", "scenario_particles", "robust")
# The files copied as they are from controllers/export/c.
STATIC_FILES = ("lfm_controller.h", "lfm_controller.c", "lfm_internal.h", "example.c", "Makefile")


@dataclass
class ExportResult:
    """What :func:`export_controller` wrote."""

    out: Path  # the project folder
    agent: str
    system: str
    files: list[str]  # the files written, relative to out
    step_available: bool  # the agent's whole step is exported (else its solve only)
    notes: list[str] = field(default_factory=list)  # what the export leaves out or changes
    dimensions: dict[str, int] = field(default_factory=dict)  # nx, nu, nw, np, ng, N, Ns


def solver_options(settings: Any) -> FastSolverOptions:
    """The compiled loop's options for an agent's settings (its ``max_iter`` and
    ``max_solve_time``; the C loop's own QP solvers; one thread)."""
    return FastSolverOptions(
        max_iter=settings.max_iter, max_time=settings.max_solve_time, qp_solver="elastic_ipm"
    )


def _c_number(value: float) -> str:
    value = float(value)
    if math.isnan(value):
        raise ValueError("lfm-export: a NaN among the config's numbers")
    if math.isinf(value):
        return "INFINITY" if value > 0 else "-INFINITY"
    return repr(value)


def _array(name: str, values: Any, kind: str = "double") -> str:
    flat = np.asarray(values).ravel()
    if kind == "double":
        items = [_c_number(v) for v in flat]
    elif kind == "long":
        items = [str(int(v)) for v in flat]
    else:
        items = [str(int(v)) for v in flat]
    if not items:
        items = ["0"]  # (no empty arrays in C; the count beside it is 0)
    lines, line = [], "  "
    for item in items:
        if len(line) + len(item) + 2 > 96:
            lines.append(line.rstrip())
            line = "  "
        line += item + ", "
    lines.append(line.rstrip())
    body = "\n".join(lines)
    return f"static const {kind} {name}[{len(items)}] = {{\n{body}\n}};"


def _agent_program(agent: Any) -> tuple[dict[str, Any], list[str]]:
    """How the agent estimates and builds its scenarios, as lfm_internal.h's numbers; and
    notes on what the export leaves out."""
    from controllers.agents import mpc

    notes: list[str] = []
    settings = agent.settings
    if isinstance(agent, mpc.NominalMPCAgent):
        return {"estimator": 0, "forecast": 0, "particles": 0, "backoff": None}, notes
    estimator = 1 if settings.estimator == "ukf" else 2
    if estimator == 2:
        notes.append(
            f"the agent's estimator {settings.estimator!r} is not exported: the library offers "
            "lfm_controller_solve; lfm_controller_step returns LFM_NO_STEP"
        )
    if isinstance(agent, mpc.CertaintyEquivalentMPCAgent):
        forecast, particles = 1, 0
    elif isinstance(agent, mpc.RobustMPCAgent) and settings.robust.forecast == "mean":
        forecast, particles = 1, 0
    else:
        forecast = 2
        particles = int((agent.initial_states or settings.scenario_initial_states) == "particles")
    if forecast == 2:
        notes.append(
            "the scenarios' latent-force noise is drawn by the library's own generator "
            "(xoshiro256**, polar normals): the same distribution as NumPy's, other numbers"
        )
    if agent.system.fallback_law is not None:
        notes.append(
            "the system's fallback law is Python: a failed solve with no plan left applies "
            f"the fallback input {[float(v) for v in agent.system.fallback_input]} itself"
        )
    k = agent._backoff_factors
    return {
        "estimator": estimator,
        "forecast": forecast,
        "particles": particles,
        "backoff": k,
    }, notes


def _config_header(agent: Any, name: str, program: dict[str, Any], dims: dict[str, int]) -> str:
    system = agent.system
    lines = [
        "/* lfm_config.h: the exported controller's dimensions (written by lfm-export). */",
        "#ifndef LFM_CONFIG_H",
        "#define LFM_CONFIG_H",
        "",
        f'#define LFM_SYSTEM "{system.name}"',
        f'#define LFM_AGENT "{agent.name}"',
        f'#define LFM_CONFIG "{name}"',
        f"#define LFM_NX {dims['nx']} /* states: {', '.join(system.state_labels)} */",
        f"#define LFM_NU {dims['nu']} /* inputs: {', '.join(system.input_names)} */",
        f"#define LFM_NW {dims['nw']} /* latent force components */",
        f"#define LFM_NP {dims['np']} /* latent state of the force's GP */",
        f"#define LFM_NG {dims['ng']} /* state constraints */",
        f"#define LFM_N {dims['N']} /* horizon */",
        f"#define LFM_NS {dims['Ns']} /* scenarios */",
        f"#define LFM_DT {_c_number(agent.model.dt)} /* [s] sampling time */",
        f"#define LFM_STEP_AVAILABLE {int(program['estimator'] != 2)}",
        "/* 1: the feedback prediction (the plan kept is the nominal inputs) */",
        f"#define LFM_FEEDBACK_PREDICTION {int(agent.problem.prediction == 'feedback')}",
        "",
        "#endif",
        "",
    ]
    return "\n".join(lines)


def _config_source(agent: Any, problem: Any, options: FastSolverOptions, program: dict) -> str:
    """lfm_config.c: every number of the agent's step."""
    model, system = agent.model, agent.system
    a = problem_arrays(problem)
    c_opts = c_options(options)
    parts = [
        "/* lfm_config.c: the exported agent's numbers (written by lfm-export). */",
        "#include <math.h>",
        "#include <stddef.h>",
        "",
        '#include "lfm_internal.h"',
        "",
    ]
    for key in ("input_lower", "input_upper", "goal", "Q", "Qf", "R", "shared_rows"):
        parts.append(_array(key, a[key]))
    for key in ("shared", "screened", "mirror"):
        parts.append(_array(key, a[key], "long"))
    parts.append(_array("depends", a["depends"], "unsigned char"))
    estimator = agent.estimator if program["estimator"] == 1 else None
    latent_prior = (
        estimator.latent_prior_cov
        if estimator is not None
        else model.stationary_latent_covariance()
    )
    parts += [
        _array("latent_A", model.A),
        _array("latent_Q", model.Q),
        _array("latent_Q_factor", model.Q_factor),
        _array("latent_H", model.H),
        _array("process_std", model.process_std),
        _array("measurement_std", agent.measurement_std),
        _array("latent_prior", latent_prior),
        _array("fallback_input", system.fallback_input),
        _array("weights", np.zeros((system.nx, system.nx))),
    ]
    if program["backoff"] is not None:
        parts.append(_array("backoff_k", program["backoff"]))
    fields = []
    for option in OPTIONS:
        value = getattr(c_opts, option.name)
        text = _c_number(value) if option.kind == "double" else str(value)
        fields.append(f"    .{option.name} = {text},")
    divergence = getattr(agent, "_divergence_nis", math.inf)
    parts += [
        "",
        "const lfm_config lfm_exported_config = {",
        "  .problem = {",
        f"    .n = {problem.horizon},",
        f"    .ns = {problem.n_scenarios},",
        f"    .slack_penalty = {_c_number(problem.slack_penalty)},",
        "    .input_lower = input_lower,",
        "    .input_upper = input_upper,",
        "    .goal = goal,",
        "    .Q = Q,",
        "    .Qf = Qf,",
        "    .R = R,",
        f"    .n_shared = {a['shared'].size},",
        "    .shared = shared,",
        "    .shared_rows = shared_rows,",
        f"    .n_screened = {a['screened'].size},",
        "    .screened = screened,",
        "    .depends = depends,",
        f"    .n_mirror = {a['mirror'].size},",
        "    .mirror = mirror,",
        "  },",
        "  .options = {",
        *fields,
        "  },",
        f"  .estimator = {program['estimator']},",
        f"  .forecast = {program['forecast']},",
        f"  .particles = {program['particles']},",
        f"  .backoff_k = {'backoff_k' if program['backoff'] is not None else 'NULL'},",
        "  .A = latent_A,",
        "  .Q = latent_Q,",
        "  .Q_factor = latent_Q_factor,",
        "  .H = latent_H,",
        "  .process_std = process_std,",
        "  .measurement_std = measurement_std,",
        "  .P_inf = latent_prior,",
        f"  .divergence_nis = {_c_number(divergence)},",
        "  .fallback_input = fallback_input,",
        "  .goal = goal,",
        "  .weights = weights,",
        "};",
        "",
    ]
    return "\n".join(parts)


def export_controller(
    config: ExperimentConfig | str | os.PathLike | dict,
    agent_name: str,
    out: str | Path,
    overwrite: bool = False,
    config_name: str | None = None,
) -> ExportResult:
    """Write the C project of ``agent_name`` on ``config`` into ``out`` (see the module
    docstring).

    Args:
        config: a config (:func:`controllers.config.load_config`'s argument: a preset's name,
            a YAML path, a dict or a loaded config).
        agent_name: one of :data:`EXPORTABLE_AGENTS`.
        out: the folder (created; must be empty unless ``overwrite``).
        overwrite: replace the files of an existing export.
        config_name: the config's name in lfm_config.h (default: the file's stem).

    Raises:
        ValueError: for an agent that cannot be exported, or a folder that is not empty.
    """
    from controllers.agents import make_agent

    if agent_name not in EXPORTABLE_AGENTS:
        raise ValueError(
            f"lfm-export: agent {agent_name!r} cannot be exported; choose one of "
            f"{EXPORTABLE_AGENTS}"
        )
    out = Path(out)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise ValueError(f"lfm-export: {out} is not empty (pass overwrite / --force)")
    if config_name is None:
        config_name = Path(config).stem if isinstance(config, (str, Path)) else "config"
    resolved = load_config(config)
    agent = make_agent(agent_name, resolved)
    problem, settings = agent.problem, agent.settings
    options = solver_options(settings)
    program, notes = _agent_program(agent)
    model = agent.model
    dims = {
        "nx": problem.nx,
        "nu": problem.nu,
        "nw": problem.nw,
        "np": model.latent_dim,
        "ng": problem.ng,
        "N": problem.horizon,
        "Ns": problem.n_scenarios,
    }
    if settings.solver not in ("fast", "fast_c"):
        notes.append(
            f"the config's solver {settings.solver!r} is replaced by the compiled fast SQP"
        )
    out.mkdir(parents=True, exist_ok=True)
    texts = {
        "lfm_mpc.c": sqp_source(problem.system, problem.dt, problem.prediction == "feedback"),
        "sqp.h": c_source("sqp.h"),
        "lfm_config.h": _config_header(agent, config_name, program, dims),
        "lfm_config.c": _config_source(agent, problem, options, program),
    }
    for file_name, text in texts.items():
        (out / file_name).write_text(text, encoding="utf-8")
    folder = resources.files(__package__) / "c"
    for file_name in STATIC_FILES:
        with resources.as_file(folder / file_name) as src:
            shutil.copyfile(src, out / file_name)
    return ExportResult(
        out=out,
        agent=agent_name,
        system=problem.system.name,
        files=sorted([*texts, *STATIC_FILES]),
        step_available=program["estimator"] != 2,
        notes=notes,
        dimensions=dims,
    )


def write_problem(path: str | Path, x0: Any, W: Any) -> None:
    """Write a scenario problem for the exported ``example``: whitespace-separated numbers,
    ``x0`` ``(nx,)`` on the first line, then ``W`` ``(Ns, N, nw)`` (or ``(Ns, N)`` for one
    force component), one line per scenario (its steps, each step's components)."""
    x0 = np.asarray(x0, dtype=float).ravel()
    W = np.asarray(W, dtype=float)
    if W.ndim == 2:
        W = W[:, :, None]
    if W.ndim != 3:
        raise ValueError(f"W: expected (Ns, N, nw) or (Ns, N), got shape {W.shape}")
    if not (np.all(np.isfinite(x0)) and np.all(np.isfinite(W))):
        raise ValueError("x0 and W must be finite")
    lines = [" ".join(repr(float(v)) for v in x0)]
    lines += [" ".join(repr(float(v)) for v in row.ravel()) for row in W]
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


def read_plan(text: str, horizon: int, nu: int) -> np.ndarray:
    """The plan ``(N, nu)`` that ``example`` printed."""
    values = np.array(text.split(), dtype=float)
    if values.size != horizon * nu:
        raise ValueError(f"expected {horizon} x {nu} numbers, got {values.size}")
    return values.reshape(horizon, nu)


__all__ = [
    "EXPORTABLE_AGENTS",
    "ExportResult",
    "export_controller",
    "read_plan",
    "solver_options",
    "write_problem",
]
