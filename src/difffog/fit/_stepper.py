"""The optimizer, stepped from Python: jitted init/step/terminate of an optimistix solver on
the fit problem, so that every step can be checkpointed, reported and checked."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._errors import DifffogError
from ._residuals import FitProblem, residual, residual_and_jacobian

OPTIMIZERS = ("lm", "gauss-newton", "bfgs")


def make_optimizer(optimizer, rtol: float, atol: float):
    """An optimistix solver from a name ("lm", "gauss-newton", "bfgs") or as given."""
    if isinstance(optimizer, (optx.AbstractLeastSquaresSolver, optx.AbstractMinimiser)):
        return optimizer
    table = {
        "lm": lambda: optx.LevenbergMarquardt(rtol=rtol, atol=atol),
        "gauss-newton": lambda: optx.GaussNewton(rtol=rtol, atol=atol),
        "bfgs": lambda: optx.BFGS(rtol=rtol, atol=atol),
    }
    if optimizer not in table:
        raise DifffogError(f"optimizer {optimizer!r}: choose 'lm' (Levenberg–Marquardt, "
                           f"default), 'gauss-newton', 'bfgs' or an optimistix solver instance")
    return table[optimizer]()


class Stepper:
    """init / step / terminate of ``optimizer`` on ``problem``, each compiled once.

    The residual function returns aux = (loss, light result code, images, the light state's
    tangents, the light state) so that the driver sees, at every accepted point, whether the
    light solve behind it converged, and has the images there without another (separately
    compiled) light solve, and the light state where the model error's finer renders start;
    each step starts its tangent solves from the last accepted point's tangents (the guess
    slot of ``data``, :func:`residual`; zero at the first step).  ``args`` is (model, data):
    the forward model and the per-fit data.
    """

    def __init__(self, problem: FitProblem, optimizer):
        self.problem = problem
        self.optimizer = optimizer
        self.minimise = isinstance(optimizer, optx.AbstractMinimiser)
        self.options = {} if self.minimise else {"jac": "fwd"}

        def fn(u, args):
            r, code, y, tangents, state = residual(problem, u, args)
            loss = 0.5 * jnp.sum(r * r)
            aux = (loss, code, y, tangents, state)
            return (loss, aux) if self.minimise else (r, aux)

        self.fn = fn
        self._static = None
        self._init = eqx.filter_jit(self.init_impl)
        self._step = eqx.filter_jit(self.step_impl)
        self._term = eqx.filter_jit(self.term_impl)
        self._rj = eqx.filter_jit(lambda u, args: residual_and_jacobian(problem, u, args))
        self._from_state = eqx.filter_jit(lambda info: (info.residual, info.jac.as_matrix()))
        self._model = eqx.filter_jit(lambda u, args, init: problem.model(args[0], u,
                                                                         args[1][4], init))

    def init_impl(self, u0, args):
        f_struct, aux_struct = jax.eval_shape(self.fn, u0, args)
        return self.optimizer.init(self.fn, u0, args, self.options, f_struct, aux_struct,
                                   frozenset())

    def init(self, u0, args):
        # compiled, so that the optimizer's shapes (a trace of the linearised residual: ~2 s
        # of Python for the README example) are found once per stepper, not once per fit
        state = self._init(u0, args)
        # The state's static part holds a closure-converted jaxpr (the linearised residual)
        # that compares by identity: reuse the first fit's so that later fits with this
        # stepper hit the compilation cache instead of compiling the step again.
        dyn, static = eqx.partition(state, eqx.is_array)
        if self._static is None:
            self._static = static
        return eqx.combine(dyn, self._static)

    def step_impl(self, u, state, args):
        return self.optimizer.step(self.fn, u, _with_guess(args, state), self.options, state,
                                   frozenset())

    def term_impl(self, u, state, args):
        return self.optimizer.terminate(self.fn, u, args, self.options, state, frozenset())

    def step(self, u, state, args):
        return self._step(u, state, args)

    def terminate(self, u, state, args):
        return self._term(u, state, args)

    def images(self, u, args, init=None):
        """(the model's flattened images at u, light result code, light state): one light
        solve, compiled once per model; ``init``: a light state to start from (the state of
        an earlier call with this model, e.g. the previous render of the model error's
        iterated correction), else zero (passed as zeros, so that both are one program)."""
        if init is None:
            init = args[0].zero_light_state(args[1][0].dtype)
        return self._model(u, args, init)

    def final(self, u, state, args):
        """Residual, Jacobian, images, light result code and light state (None where not
        known) at the final u.  A least-squares solver's state holds the residual, the
        (linearised) Jacobian and (in its aux) the images, the result code and the light
        state at u already: reuse them, so nothing is solved or compiled again (BFGS:
        everything but the light state)."""
        info = getattr(state, "f_info", None)
        if isinstance(info, optx.FunctionInfo.ResidualJac):
            r, J = self._from_state(info)
            _, code, y, _, light = state.aux  # what self.fn returned at u
            return r, J, y, code, light
        return (*self._rj(u, args), None)


def _with_guess(args, state):
    """``args`` with the light state's tangents of the optimizer's last accepted point (its
    aux; zero before the first step) as where the next tangent solves start."""
    aux = getattr(state, "aux", None)
    if aux is None or aux[3] is None:
        return args
    model, data = args
    return model, data[:5] + (aux[3],)


# Compiled steppers of recent fits, so that fitting new targets (or from a new start) with
# the same forward model, unknowns and optimizer does not compile again.  Keyed on the model's
# structure (its static fields, which compare by value, and its arrays' shapes and dtypes),
# not its identity: a fit that builds its model anew (``fit(scene, ...)`` called twice in a
# notebook, a command line fit after a test's) steps with the program compiled for the first.
_STEPPERS: dict = {}


def _model_key(model):
    leaves, treedef = jax.tree_util.tree_flatten(model)
    shapes = tuple((np.shape(x), str(getattr(x, "dtype", type(x).__name__))) for x in leaves)
    return treedef, shapes


def stepper_for(model, coords, names, loss, optimizer) -> Stepper:
    key = (_model_key(model), tuple(coords), tuple(names), loss, repr(optimizer))
    hit = _STEPPERS.get(key)
    if hit is not None:
        return hit
    st = Stepper(FitProblem(model.scene, tuple(coords), tuple(names), loss), optimizer)
    _STEPPERS[key] = st
    while len(_STEPPERS) > 4:
        _STEPPERS.pop(next(iter(_STEPPERS)))
    return st
