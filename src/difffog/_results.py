"""Result codes of light solves, in optimistix' style: a code per outcome, a message per code.

A light solve returns its code (an int32 array, so that it can live inside ``jit`` and
``vmap``) in ``light.result``.  ``render`` and ``model.images`` raise by default when it is not
``successful`` (``throw=True``); ``throw=False`` returns the images and the code for the caller
to inspect.  Inside ``jit`` the raise is :func:`equinox.branched_error_if`, whose message is
the static one below; outside (``difffog.render``, the command line) the message also names
the estimated error and the iterations.
"""

from __future__ import annotations

import enum

import equinox as eqx
import jax.numpy as jnp


class RESULTS(enum.IntEnum):
    """How a light solve ended.  ``RESULTS(code).message`` says what it means and what to do."""

    successful = 0
    max_iterations_reached = 1
    stagnated = 2
    nonfinite = 3
    tangent_unconverged = 4
    no_steady_state = 5
    terms_dropped = 6

    @property
    def message(self) -> str:
        return _MESSAGES[self]


_MESSAGES = {
    RESULTS.successful: "",
    RESULTS.max_iterations_reached: (
        "the light solve reached its iteration cap before its tolerance; raise max_iterations "
        "(--max-iterations), loosen tol, or check the lattice step's optical depth "
        "(difffog info)"),
    RESULTS.stagnated: (
        "the light solve stagnated: its iteration stopped making progress (a region that keeps "
        "its light, such as conservative fog enclosed by albedo-1 walls, has no steady state); "
        "add absorption or lower an albedo"),
    RESULTS.nonfinite: (
        "the light solve produced non-finite values; check the scene's numbers (very large "
        "coefficients or intensities) and use float64 (jax_enable_x64) if they are legitimate"),
    RESULTS.tangent_unconverged: (
        "a tangent light solve of the fit's Jacobian (the derivative of the light) did not "
        "converge, or the Jacobian was not finite, so the Jacobian and the standard errors "
        "from it are not reliable; raise the solver's max_iterations or adjoint_rtol"),
    RESULTS.no_steady_state: (
        "no steady state: an enclosed region whose surfaces reflect everything (albedo 1), "
        "with fog (if any) that does not absorb, contains emission, so its light grows without "
        "bound; lower an albedo below 1, add fog absorption, or open the enclosure"),
    RESULTS.terms_dropped: (
        "a parameter is non-zero whose term the solver's terms dropped because the scene had "
        "none of it (fog, fog scattering, the sky or surface reflection), so the light leaves "
        "it out; build the solver with terms='all' (SweepSolver(terms='all')) to keep every "
        "term, or set it non-zero in the scene"),
}


def combine(*codes):
    """The first failure among several codes (int32 arrays of one shape), else successful."""
    out = jnp.asarray(codes[0], jnp.int32)
    for c in codes[1:]:
        out = jnp.where(out == RESULTS.successful, jnp.asarray(c, jnp.int32), out)
    return out


def error_if_failed(x, result):
    """``x``, raising at run time (inside ``jit``) with the code's message if ``result`` (an
    int32 scalar or array) is not successful."""
    result = jnp.asarray(result, jnp.int32)
    msgs = tuple(f"difffog: {m}" if m else "" for m in (r.message for r in RESULTS))
    pred = jnp.any(result != RESULTS.successful)
    index = jnp.max(result)
    return eqx.branched_error_if(x, pred, index, msgs)


def check(result, what: str = "light solve", details: str = "") -> None:
    """Raise a one-line :class:`SolverError` on the host if a concrete ``result`` failed."""
    from ._errors import SolverError

    code = int(jnp.max(jnp.asarray(result)))
    if code != RESULTS.successful:
        r = RESULTS(code)
        extra = f" ({details})" if details else ""
        raise SolverError(f"{what}: {r.name}{extra}: {r.message}")
