"""Errors and warnings a user can act on: each message names the input, the bad value and the
fix."""


class DifffogError(Exception):
    """Base class of every error difffog raises on purpose; the CLI prints it without a traceback."""


class SceneError(DifffogError, ValueError):
    """A scene file, a built-in scene name, a scene object or a ``--set`` override is invalid."""


class SolverError(DifffogError, RuntimeError):
    """A light solve cannot produce a meaningful answer (no steady state, not converged)."""


class AdjointWarning(UserWarning):
    """A tangent or adjoint light solve (a derivative of the light field) did not converge:
    the gradient is inaccurate."""


class ThickStepWarning(UserWarning):
    """One lattice step of the light solve spans more than a mean free path: the light's
    distribution inside the fog (and what a camera sees of thick fog) is coarse, and where
    such a node is sunlit at the fog's face the solve gains light (up to ~20% at two mean free
    paths per node; docs/validation.md).  The message names the step depth and the resolution
    that brings it to 1."""


class ThinLayerWarning(UserWarning):
    """The fog is a thin layer across a periodic domain: the lattice's horizontal directions
    never leave it, so its multiply scattered light is overestimated (images of a haze layer
    of optical depth 0.1: +10% at M = 2, +6% at M = 3, +3% at M = 5).  The message names the
    layer's optical depth and the M that lowers the error."""


class DeviceWarning(UserWarning):
    """A device layout that runs slower than the default here: on a CPU, several host devices
    (``devices=N``, ``--devices N``) run XLA's sweep loop instead of the native kernel, which
    already uses every core on one device."""


class ResourceError(DifffogError, MemoryError):
    """A run would not fit in the memory available: refused before allocating, with the
    estimate, what is available and the setting to lower (``difffog.estimate``)."""


class MemoryWarning(UserWarning):
    """A run's estimated peak memory is above half of what is available."""
