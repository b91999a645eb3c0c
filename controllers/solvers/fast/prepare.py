"""The fast solvers' C libraries compiled ahead of their first use (:func:`compile_ahead`):
the evaluation calls it before the first episode's clock starts, so a compile never counts
against an episode's time limit."""

from __future__ import annotations

from controllers.solvers.fast.codegen.build import CodegenUnavailable, build_library, notice
from controllers.solvers.fast.compiled import sqp_library
from controllers.solvers.fast.qp.elastic_ipm import _library as elastic_library


def compile_ahead(system, dt: float, compiled_loop: bool = False) -> list[str]:
    """Compile (or find in the cache) the C libraries the fast solvers load for ``system`` at
    ``dt`` [s]: the system's library, the elastic QP solver's and, with ``compiled_loop``
    (``fast_c``), the compiled SQP loop's; each as :func:`load_library`, so later builds in
    this process, and in processes started later, find them loaded or cached.

    Returns:
        Why each library that is not available is not (the fast solvers fall back as
        they would in an episode, announced once).
    """
    missing = []
    builds = [lambda: build_library(system, dt)]
    if compiled_loop:
        builds.append(lambda: sqp_library(system, dt))
    for make in builds:
        try:
            make()
        except CodegenUnavailable as err:
            missing.append(str(err))
    if missing:
        notice(
            f"the fast solver's C library is not available ({missing[0]}); the fast solver "
            "uses its NumPy backend in this process (slower)"
        )
    elastic_library()  # (None without a compiler: the QP solvers in Python are used)
    return missing


__all__ = ["compile_ahead"]
