"""difffog: a differentiable JAX solver for inverse fog estimation."""

from ._errors import DifffogError as DifffogError, SceneError as SceneError, SolverError as SolverError
from ._params import Params as Params, get_param as get_param, param_paths as param_paths, set_param as set_param
from ._scene import Scene as Scene

__version__ = "0.1.0"
