"""Differentiating a converged fixed point x* = F(x*, θ) by the implicit function theorem.

With G(x, θ) = x − F(x, θ) = 0 at the root, its tangent is
    ẋ = −(∂G/∂x)⁻¹ (∂G/∂θ) θ̇,
one linear solve with the operator I − ∂F/∂x (matrix-free: a Jacobian–vector product of one
Jacobi step, or for an F affine in x, as the sweep's is, that step itself with its sources
zeroed: :class:`AffineJacobian`), whatever the number of iterations the forward solve took.
Reverse mode transposes that linear solve (``lineax`` transposes ``linear_solve``), so a
gradient costs one adjoint solve with (I − ∂F/∂x)ᵀ and its memory does not grow with the
iterations.

Written on the public APIs of equinox (``filter_custom_jvp``) and lineax (``linear_solve``,
``JacobianLinearOperator``), so that difffog does not depend on optimistix' internals.

:class:`KrylovSolver` solves those systems by the sweep's own restarted GMRES
(``_krylov.gmres``), which stops at the Krylov step where its error estimate reaches the
tolerance; ``lineax.GMRES`` checks only at the end of each restart cycle, so every solve costs
at least ``restart`` + 1 products, however few it needs (cloud-tomo's adjoint at 1e-4: a
handful, against 41 with ``restart=40``).

:class:`CheckedSolver` wraps the linear solver of these tangent and adjoint solves and says
when one did not converge: it raises at run time (``throw=True``) or warns with an
:class:`AdjointWarning` (``throw=False``); it never passes an unconverged gradient silently.
Inside ``forward_mode()`` (a fit's Jacobian) a tangent solve reports by its value instead, NaN
where it did not converge, which the fit turns into a result code, and inside
:func:`solves_by_value` (the density fit's value and gradient) the adjoint solve does: those
programs then carry no host callback, which XLA's persistent cache would not store.
"""

from __future__ import annotations

import contextlib
import contextvars
import warnings
from collections.abc import Callable

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import lineax as lx
import numpy as np

from ..._errors import AdjointWarning
from ._krylov import block_gmres, gmres
from ._march import in_forward_mode

_BY_VALUE = contextvars.ContextVar("difffog_solves_by_value", default=False)


@contextlib.contextmanager
def solves_by_value():
    """Within this context (as within ``forward_mode()``), the implicit function's tangent and
    adjoint solves that are traced report one that did not converge by its value, NaN,
    instead of a check at run time: no
    host callback enters the program, so XLA's persistent cache keeps it (the density fit's
    value and gradient, which otherwise compiled again in every new process).  The caller
    checks the result for NaN.  The adjoint solve then goes through
    ``jax.lax.custom_linear_solve`` with the solver's own transposed solve (lineax's transpose
    rule checks every adjoint solve with a callback, whatever ``throw`` says), which is told
    the operator is symmetric so that JAX does not transpose the sweeps itself: first
    derivatives only (a second derivative through it would be wrong).  Like
    :func:`difffog.forward.sweep._march.forward_mode`, decided when the program is traced."""
    token = _BY_VALUE.set(True)
    try:
        yield
    finally:
        _BY_VALUE.reset(token)


def _by_value(sol, ok):
    """``sol`` where ``ok``, NaN elsewhere (a solve that did not converge, by its value)."""
    return jax.tree.map(lambda a: jnp.where(ok, a, jnp.nan), sol)


def _solve_by_value(operator, vector, linear_solver, options):
    """(∂G/∂x)⁻¹·vector by ``linear_solver``'s own solve (its ``CheckedSolver`` check left
    out), NaN where it did not converge, transposed (reverse mode) by the solver's transposed
    solve: see :func:`solves_by_value`."""
    inner = linear_solver.inner if isinstance(linear_solver, CheckedSolver) else linear_solver
    state = inner.init(operator, options)

    def by_value(out):
        sol, result, _ = out
        return _by_value(sol, result == lx.RESULTS.successful)

    def solve(_, b):
        return by_value(inner.compute(state, b, options))

    def transpose_solve(_, b):
        state_t, options_t = inner.transpose(state, options)
        return by_value(inner.compute(state_t, b, options_t))

    return jax.lax.custom_linear_solve(operator.mv, vector, solve, transpose_solve,
                                       symmetric=True)


def _solve_forward(operator, vector, linear_solver, options):
    """(∂G/∂x)⁻¹·vector in forward mode (a fit's Jacobian), NaN where it did not converge,
    with no host callback (see :func:`solves_by_value`).  Vmapped over right-hand sides (the
    Jacobian's columns, ``jax.vmap`` over the unknowns) with the operator itself not batched,
    a :class:`KrylovSolver` with ``block=True`` solves them together by block GMRES
    (``KrylovSolver.compute_block``) instead of one GMRES each in lockstep
    (``jax.custom_batching.custom_vmap``).  Not transposable: forward mode only."""
    inner = linear_solver.inner if isinstance(linear_solver, CheckedSolver) else linear_solver
    dyn, static = eqx.partition((operator, options.get("preconditioner")), eqx.is_array)
    y0 = options.get("y0")

    def opts_of(pre, y0):
        return {**({} if pre is None else {"preconditioner": pre}),
                **({} if y0 is None else {"y0": y0})}

    def one(dyn, b, y0):
        op, pre = eqx.combine(dyn, static)
        opts = opts_of(pre, y0)
        sol, result, _ = inner.compute(inner.init(op, opts), b, opts)
        return _by_value(sol, result == lx.RESULTS.successful)

    if not (isinstance(inner, KrylovSolver) and inner.block):
        return one(dyn, vector, y0)
    solve = jax.custom_batching.custom_vmap(one)

    @solve.def_vmap
    def _rule(axis_size, in_batched, dyn, b, y0):
        dyn_b, b_b, y0_b = in_batched
        axes = jax.tree.map(lambda t: 0 if t else None, in_batched)
        if any(jax.tree.leaves(dyn_b)):  # the operator itself is batched: a solve each
            out = jax.vmap(one, in_axes=tuple(axes))(dyn, b, y0)
            return out, jax.tree.map(lambda _: True, out)

        def batched(tree, flags):
            return jax.tree.map(lambda a, f: a if f else jnp.broadcast_to(a, (axis_size,)
                                                                           + a.shape),
                                tree, flags)

        op, pre = eqx.combine(dyn, static)
        opts = opts_of(pre, None if y0 is None else batched(y0, y0_b))
        out, ok = inner.compute_block(inner.init(op, opts), batched(b, b_b), opts)
        out = jax.vmap(_by_value)(out, ok)
        return out, jax.tree.map(lambda _: True, out)

    return solve(dyn, vector, y0)


def fixed_point(solve: Callable, rewrite: Callable, inputs, linear_solver: lx.AbstractLinearSolver,
                precondition: Callable | None = None, linear: Callable | None = None,
                transposed: Callable | None = None, guess=None):
    """``solve(inputs) -> (root, aux)``, differentiated implicitly through ``rewrite``.

    solve: inputs → (root, aux); root is the fixed point, aux anything (no gradient flows
        through it).  Must not close over JAX arrays (pass them in ``inputs``).
    rewrite: (root, inputs) → G(root, inputs), zero at the fixed point, with the root's
        structure.
    inputs: a pytree; its floating-point arrays get tangents.
    linear_solver: solves the tangent system (and its transpose, for reverse mode).
    precondition: inputs → a :class:`Preconditioner` for ∂G/∂x (or None): handed to the
        tangent solve as lineax's ``options["preconditioner"]``, and its transpose to the
        adjoint solve.  Must not close over JAX arrays either.
    linear: (v, inputs) → ∂G/∂x·v computed directly (or None), for a ``rewrite`` affine in
        the root: G(v) − G(0).  The tangent solve (forward mode) then applies it as it is,
        matrix-free, instead of linearising ``rewrite`` once and keeping every residual of that
        linearisation for the whole solve (the sweep's: ~1 KB per lattice node and direction);
        the adjoint solve (reverse mode) linearises it to transpose, unless ``transposed`` is
        given.  A module-level function (it is a static field).
    transposed: (v, inputs) → (∂G/∂x)ᵀ·v computed directly (or None), with ``linear``: the
        adjoint solve (reverse mode) then applies it, matrix-free, instead of transposing
        ``linear``'s linearisation.  A module-level function.
    guess: None, or a pytree with the root's structure whose *tangent* is where the tangent
        solve starts: a guess of the root's tangent (e.g. the one at a nearby point, where a
        fit's last step was).  Its value is not used, and the answer is the same to the
        linear solver's tolerance.  Forward mode only: a start that moves with the tangent
        makes the tangent solve affine in it, which reverse mode cannot transpose, so give it
        a zero (stopped) tangent there.
    """
    root, aux = _fixed_point(solve, rewrite, inputs, guess, linear_solver, precondition,
                             linear, transposed)
    return root, jax.tree.map(jax.lax.stop_gradient, aux)


class Preconditioner(eqx.Module):
    """An approximate inverse P ≈ (∂G/∂x)⁻¹ on the root's pytree, for the tangent and adjoint
    solves: ``apply(tree)`` is P·tree, ``transpose()`` the preconditioner Pᵀ of the transposed
    system (the adjoint's).  P need not be exactly linear (flexible GMRES, ``_krylov.py``)."""

    def apply(self, tree):
        raise NotImplementedError

    def transpose(self) -> "Preconditioner":
        raise NotImplementedError


@eqx.filter_custom_jvp
def _fixed_point(solve, rewrite, inputs, guess, linear_solver, precondition, linear, transposed):
    del rewrite, guess, linear_solver, precondition, linear, transposed
    return jax.tree.map(jnp.asarray, solve(inputs))


def _for_operator(root, args):
    rewrite, inputs = args
    return rewrite(root, inputs)


@_fixed_point.def_jvp
def _fixed_point_jvp(primals, tangents):
    solve, rewrite, inputs, _, linear_solver, precondition, linear, transposed = primals
    _, _, t_inputs, t_guess, _, _, _, _ = tangents
    root, aux = fixed_point(solve, rewrite, inputs, linear_solver, precondition, linear,
                            transposed)
    # inputs without a tangent (integer masks, static geometry) are held fixed
    no_tangent = jax.tree.map(lambda t: t is None, t_inputs, is_leaf=lambda t: t is None)
    fixed, moving = eqx.partition(inputs, no_tangent, is_leaf=lambda t: t is None)

    def g_of_inputs(m):
        return rewrite(root, eqx.combine(m, fixed))

    _, g_dot = jax.jvp(g_of_inputs, (moving,), (t_inputs,))
    operator = lx.JacobianLinearOperator(_for_operator, root, (rewrite, inputs))
    if linear is not None:
        operator = AffineJacobian(linear, inputs, operator, transposed)
    pre = None if precondition is None else precondition(inputs)
    options = {} if pre is None else {"preconditioner": pre}
    start = _start(t_guess, root)
    if start is not None:  # the solve is for −(the root's tangent)
        options["y0"] = start
    if in_forward_mode() and not _BY_VALUE.get():
        # a fit's Jacobian: by value as below, and its columns' solves (vmapped over the
        # unknowns) as one block solve
        x_dot = _solve_forward(operator, g_dot, linear_solver, options)
    elif _BY_VALUE.get():
        # a fit's Jacobian (forward mode) and the density fit's gradient: a solve that did not
        # converge gives NaN (their callers turn that into a result code or ``adjoint_failed``)
        # instead of a check at run time, whose host callback would keep XLA's persistent cache
        # from storing the program (the README example's fit step compiled again in every new
        # process: 12.8 s of its 46.5 s there, stop 62)
        x_dot = _solve_by_value(operator, g_dot, linear_solver, options)
    else:
        x_dot = lx.linear_solve(operator, g_dot, linear_solver, options=options).value
    t_root = jax.tree.map(jnp.negative, x_dot)
    t_aux = jax.tree.map(_zero_tangent, aux)
    return (root, aux), (t_root, t_aux)


class AffineJacobian(lx.AbstractLinearOperator):
    """∂G/∂x of a G affine in x, applied matrix-free: ``mv(v) = linear(v, inputs)``, which
    stores nothing between products (``lx.linearise`` of the ``JacobianLinearOperator`` keeps
    the residuals of one linearised G for as long as the solve runs).  ``transpose()``: with
    ``transposed``, the operator that applies it (matrix-free too); without, that Jacobian
    operator linearised and transposed."""

    linear: Callable = eqx.field(static=True)
    inputs: object
    jacobian: lx.JacobianLinearOperator
    transposed: Callable | None = eqx.field(static=True, default=None)

    def mv(self, vector):
        return self.linear(vector, self.inputs)

    def as_matrix(self):
        return self.jacobian.as_matrix()

    def transpose(self):
        if self.transposed is not None:
            return AffineJacobianT(self)
        return lx.linearise(self.jacobian).transpose()

    def in_structure(self):
        return self.jacobian.in_structure()

    def out_structure(self):
        return self.jacobian.out_structure()


class AffineJacobianT(lx.AbstractLinearOperator):
    """(∂G/∂x)ᵀ of an :class:`AffineJacobian` with a ``transposed`` product: ``mv(v) =
    transposed(v, inputs)`` (the sweep's: hand-written transposed face sweeps,
    ``_solver._rewrite_linear_transposed``), nothing kept between products."""

    of: AffineJacobian

    def mv(self, vector):
        return self.of.transposed(vector, self.of.inputs)

    def as_matrix(self):
        return self.of.as_matrix().T

    def transpose(self):
        return self.of

    def in_structure(self):
        return self.of.out_structure()

    def out_structure(self):
        return self.of.in_structure()


for _cls in (AffineJacobian, AffineJacobianT):
    lx.linearise.register(_cls)(lambda operator: operator)  # already a matrix-free product
    lx.conj.register(_cls)(lambda operator: operator)  # real

lx.materialise.register(AffineJacobian)(lambda operator: lx.materialise(operator.jacobian))
lx.materialise.register(AffineJacobianT)(
    lambda operator: lx.materialise(operator.of.jacobian).transpose())

# what lineax asks of an operator's structure (and its diagonals): that of the Jacobian
# (the diagonals and these properties are those of its transpose too)
for _query in (lx.is_symmetric, lx.is_diagonal, lx.is_tridiagonal, lx.has_unit_diagonal,
               lx.is_positive_semidefinite, lx.is_negative_semidefinite, lx.diagonal):
    _query.register(AffineJacobian)(lambda operator, _q=_query: _q(operator.jacobian))
    _query.register(AffineJacobianT)(lambda operator, _q=_query: _q(operator.of.jacobian))
for _query, _flip in ((lx.is_lower_triangular, lx.is_upper_triangular),
                      (lx.is_upper_triangular, lx.is_lower_triangular)):
    _query.register(AffineJacobian)(lambda operator, _q=_query: _q(operator.jacobian))
    _query.register(AffineJacobianT)(lambda operator, _f=_flip: _f(operator.of.jacobian))
lx.tridiagonal.register(AffineJacobian)(lambda operator: lx.tridiagonal(operator.jacobian))
lx.tridiagonal.register(AffineJacobianT)(
    lambda operator: (lambda d, lo, up: (d, up, lo))(*lx.tridiagonal(operator.of.jacobian)))


def _start(t_guess, root):
    """The tangent solve's start, −``t_guess`` in the root's dtypes, or None where the guess
    has no tangent (None, or a symbolic zero in any leaf)."""
    if t_guess is None:
        return None
    leaves = jax.tree.leaves(t_guess, is_leaf=lambda t: t is None)
    if any(t is None for t in leaves):
        return None
    return jax.tree.map(lambda t, r: -jnp.asarray(t, r.dtype), t_guess, root)


def _zero_tangent(x):
    """A zero tangent for ``x``: float0 for integer and boolean arrays, as JAX requires."""
    if jnp.issubdtype(x.dtype, jnp.inexact):
        return jnp.zeros_like(x)
    return np.zeros(x.shape, jax.dtypes.float0)


def _warn(bad, steps):
    if bool(bad):
        warnings.warn(AdjointWarning(
            f"a tangent/adjoint light solve (the derivative of the light field) did not "
            f"converge in {int(steps)} steps: the gradient is inaccurate; raise the solver's "
            f"max_iterations or adjoint_rtol, or check that the forward solve converged"),
            stacklevel=2)


class KrylovSolver(lx.AbstractLinearSolver):
    """A lineax solver for a square operator A by ``_krylov.gmres`` (restarted GMRES with a
    stopping test after every product).

    rtol: stop when the estimated relative error of the solution is below it.
    restart: Krylov steps per cycle (memory: restart + 1 vectors).
    max_matvecs: the products allowed; a solve that has not reached ``rtol`` by then returns
        ``RESULTS.max_steps_reached`` (and a non-finite one too).
    native: its Gram–Schmidt by the native CPU kernel where that serves (``_krylov.gmres``);
        False for a device mesh's sharded state.

    A :class:`Preconditioner` in the solve's options (``options["preconditioner"]``) makes it
    flexible GMRES with that right preconditioner; the transposed solve gets its transpose.
    ``options["y0"]`` (the solution's structure): where the iteration starts (else zero);
    the transposed solve starts from zero.
    """

    rtol: float = eqx.field(static=True)
    restart: int = eqx.field(static=True, default=40)
    max_matvecs: int = eqx.field(static=True, default=400)
    native: bool = eqx.field(static=True, default=True)
    block: bool = eqx.field(static=True, default=True)

    def init(self, operator, options):
        pre = options.get("preconditioner")
        if pre is not None and not isinstance(pre, Preconditioner):
            raise ValueError("KrylovSolver's preconditioner must be a Preconditioner")
        if not eqx.tree_equal(operator.in_structure(), operator.out_structure()):
            raise ValueError("KrylovSolver needs a square operator")
        return lx.linearise(operator)

    def compute(self, state, vector, options):
        operator = state
        b, unravel = jax.flatten_util.ravel_pytree(vector)
        pre = options.get("preconditioner")

        def apply_k(u, with_sources):  # K = I − A, so that (I − K)x = Ax = b
            au, _ = jax.flatten_util.ravel_pytree(operator.mv(unravel(u)))
            return u - au + jnp.where(with_sources, b, jnp.zeros_like(b))

        def precondition(u):
            return jax.flatten_util.ravel_pytree(pre.apply(unravel(u)))[0]

        y0 = options.get("y0")
        x0 = None if y0 is None else jax.flatten_util.ravel_pytree(y0)[0].astype(b.dtype)
        x, _, k, err = gmres(apply_k, b.shape, b.dtype, restart=self.restart,
                             max_matvecs=self.max_matvecs, tol=self.rtol,
                             precondition=None if pre is None else precondition, x0=x0,
                             native=self.native)
        ok = (err <= self.rtol) & jnp.all(jnp.isfinite(x))
        result = lx.RESULTS.where(ok, lx.RESULTS.successful, lx.RESULTS.max_steps_reached)
        return unravel(x), result, {"num_steps": k}

    def compute_block(self, state, vectors, options):
        """p solves with one operator at once by block GMRES (``_krylov.block_gmres``):
        ``vectors`` and ``options["y0"]`` (if any) carry a leading axis of p right-hand sides
        and starts.  Returns (solutions with that axis, converged (p,) bool): a column
        converged where its error estimate reached ``rtol`` and it is finite."""
        operator = state
        first = jax.tree.map(lambda a: a[0], vectors)
        unravel = jax.flatten_util.ravel_pytree(first)[1]

        def flat(tree):
            return jax.vmap(lambda t: jax.flatten_util.ravel_pytree(t)[0])(tree)

        B = flat(vectors)
        pre = options.get("preconditioner")

        def apply_a(U):
            return flat(jax.vmap(lambda u: operator.mv(unravel(u)))(U))

        def precondition(U):
            return flat(jax.vmap(lambda u: pre.apply(unravel(u)))(U))

        y0 = options.get("y0")
        X0 = None if y0 is None else flat(y0).astype(B.dtype)
        p = B.shape[0]
        # the basis as large as one single solve's (restart + 1 vectors), not p of them:
        # ⌈restart/p⌉ block steps a cycle, at least 8
        X, _, err = block_gmres(apply_a, B, restart=max(-(-self.restart // p), 8),
                                max_matvecs=self.max_matvecs * p, tol=self.rtol,
                                precondition=None if pre is None else precondition, X0=X0,
                                native=self.native)
        ok = (err <= self.rtol) & jnp.all(jnp.isfinite(X), axis=1)
        return jax.vmap(unravel)(X), ok

    def transpose(self, state, options):
        pre = options.get("preconditioner")
        return state.transpose(), ({} if pre is None else {"preconditioner": pre.transpose()})

    def conj(self, state, options):
        if options.get("preconditioner") is not None:
            raise NotImplementedError("KrylovSolver: a preconditioned complex solve")
        return lx.conj(state), {}

    def assume_full_rank(self):
        return True


class CheckedSolver(lx.AbstractLinearSolver):
    """A lineax solver that checks its inner solver's result code on every solve.

    inner: the solver doing the work (GMRES on the sweep's operator).
    throw: True → an unconverged solve raises at run time (``eqx.error_if``); False → it
        warns (:class:`difffog.AdjointWarning`) and returns the inner solver's best effort
        with non-finite entries zeroed.
    """

    inner: lx.AbstractLinearSolver
    throw: bool = eqx.field(static=True, default=True)

    def init(self, operator, options):
        return self.inner.init(operator, options)

    def compute(self, state, vector, options):
        sol, result, stats = self.inner.compute(state, vector, options)
        bad = result != lx.RESULTS.successful
        steps = stats.get("num_steps", jnp.asarray(-1))
        if self.throw:
            sol = eqx.error_if(sol, bad, "difffog: a tangent/adjoint light solve (the "
                               "derivative of the light field) did not converge; raise the "
                               "solver's max_iterations or adjoint_rtol, or check that the "
                               "forward solve converged (SweepSolver(throw=False) warns "
                               "instead)")
        else:
            jax.debug.callback(_warn, bad, steps)
            sol = jax.tree.map(lambda a: jnp.where(jnp.isfinite(a), a, 0.0), sol)
        # reported as successful either way: the check above has raised or warned already
        return sol, lx.RESULTS.successful, stats

    def transpose(self, state, options):
        return self.inner.transpose(state, options)

    def conj(self, state, options):
        return self.inner.conj(state, options)

    def assume_full_rank(self):
        return self.inner.assume_full_rank()
