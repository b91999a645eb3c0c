"""How many scenarios: the scenario count of Campi & Garatti (2008).

:func:`campi_garatti_scenarios` gives the smallest number of scenarios ``Ns`` for which the
solution of a convex scenario program with ``d`` decision variables violates its constraints
with probability above ``epsilon`` only with probability at most ``beta``. The agents use it
when a config asks for ``n_scenarios: campi_garatti`` (:mod:`controllers.config`); for the
nonlinear MPC it is a heuristic (the paper's Remark 2).
"""

from __future__ import annotations

from numbers import Integral, Real

from scipy import special


def _binomial_tail(n_scenarios: int, epsilon: float, n_decision: int) -> float:
    """``sum_{i<d} C(Ns, i) eps^i (1 - eps)^(Ns - i)``, the Campi-Garatti confidence bound."""
    return float(special.bdtr(n_decision - 1, n_scenarios, epsilon))


def campi_garatti_scenarios(epsilon: float, beta: float, n_decision: int) -> int:
    """Smallest scenario count ``Ns`` meeting the Campi & Garatti (2008) bound.

    For a convex scenario program with ``d`` decision variables, ``Ns`` scenarios give a
    solution whose violation probability exceeds ``epsilon`` with probability at most
    ``beta`` when ``sum_{i=0}^{d-1} C(Ns, i) eps^i (1-eps)^(Ns-i) <= beta``.

    Args:
        epsilon: admissible violation probability, in (0, 1).
        beta: confidence parameter, in (0, 1).
        n_decision: number ``d`` of decision variables, an integer >= 1.

    Returns:
        The smallest ``Ns`` satisfying the bound. The guarantee is for convex programs; the
        nonlinear MPC is in general not convex, so for it this is a heuristic (paper, Remark 2).

    Raises:
        ValueError: when an argument is out of range.
    """
    if isinstance(epsilon, bool) or not isinstance(epsilon, Real) or not 0.0 < epsilon < 1.0:
        raise ValueError(f"epsilon={epsilon!r}: must be a number in (0, 1)")
    if isinstance(beta, bool) or not isinstance(beta, Real) or not 0.0 < beta < 1.0:
        raise ValueError(f"beta={beta!r}: must be a number in (0, 1)")
    if isinstance(n_decision, bool) or not isinstance(n_decision, Integral) or n_decision < 1:
        raise ValueError(f"n_decision={n_decision!r}: must be an integer >= 1")
    d = int(n_decision)
    # The tail equals 1 for Ns < d and decreases strictly in Ns, so bracket by doubling and
    # then bisect: lo always fails the bound, hi always meets it.
    lo, hi = d - 1, d
    while _binomial_tail(hi, epsilon, d) > beta:
        lo, hi = hi, 2 * hi
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if _binomial_tail(mid, epsilon, d) <= beta:
            hi = mid
        else:
            lo = mid
    return hi


__all__ = ["campi_garatti_scenarios"]
