"""difffog: a differentiable JAX solver for inverse fog estimation.

Pipeline: ``load_scene`` (scene file → :class:`Scene`) → ``voxelize`` (→ :class:`Lattice`) →
a light solver (``SweepSolver``) → :class:`LightField` → cameras → images; :func:`render` runs
it all with one light solve for every camera, :class:`Renderer` keeps the host-side work for
repeated, differentiable renders.  :class:`SplatRenderer` is the fast, approximate alternative
(Zhang & Crawfis' sheet-based splatting) for forward-scattering clouds and polygon meshes.
"""

from ._batch import (
    map_batch as map_batch,
    render_batch as render_batch,
    stack_params as stack_params,
    unstack_params as unstack_params,
)
from ._directions import DirectionSet as DirectionSet, direction_set as direction_set
from ._errors import DifffogError as DifffogError, SceneError as SceneError, SolverError as SolverError
from ._fit import (
    FitResult as FitResult,
    IdentifiabilityWarning as IdentifiabilityWarning,
    Unknown as Unknown,
    fit as fit,
    fit_batch as fit_batch,
)
from ._lattice import Lattice as Lattice, voxelize as voxelize
from ._lightfield import LightField as LightField
from ._params import (
    Params as Params,
    get_param as get_param,
    param_paths as param_paths,
    set_param as set_param,
)
from ._plan import Plan as Plan, plan as plan
from ._render import Rendered as Rendered, Renderer as Renderer, render as render
from ._scene import Camera as Camera, Scene as Scene
from ._scene_io import (
    apply_overrides as apply_overrides,
    builtin_scenes as builtin_scenes,
    load_scene as load_scene,
    scalar_paths as scalar_paths,
)
from ._solver import AbstractLightSolver as AbstractLightSolver, SweepSolver as SweepSolver
from ._splat import SplatRenderer as SplatRenderer

__version__ = "0.1.0"


def __getattr__(name):
    # ``difffog.plot`` (matplotlib) loads on first use, so ``import difffog`` stays free of it
    if name == "plot":
        import importlib

        return importlib.import_module(".plot", __name__)
    raise AttributeError(f"module 'difffog' has no attribute {name!r}")
