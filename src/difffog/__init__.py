"""difffog: a differentiable JAX solver for inverse fog estimation.

The pipeline, one sub-package each: ``scene`` (the description: files, Python objects,
parameters) → ``geometry`` (lattice, directions, rays) → ``forward`` (the forward models:
``sweep`` and ``splat`` behind one interface, cameras) → ``fit`` (inverse estimation) →
``cli`` (the command line); ``study`` is the speed–accuracy study and the shipped references;
``plot`` draws.

    scene = difffog.load_scene("fog-balls")            # or difffog.Scene(...) in Python
    model = difffog.forward_model(scene, "sweep")        # or "splat"; accuracy="draft"|"high"
    images = model(model.params())                       # {camera: (H, W)}, jit/vmap/grad-able
    out = difffog.render(model)                          # timed, checked, with the light
    result = difffog.fit(scene, targets, ["fog.scattering"])
"""

from ._errors import (
    AdjointWarning as AdjointWarning,
    DeviceWarning as DeviceWarning,
    ThickStepWarning as ThickStepWarning,
    ThinLayerWarning as ThinLayerWarning,
    DifffogError as DifffogError,
    MemoryWarning as MemoryWarning,
    ResourceError as ResourceError,
    SceneError as SceneError,
    SolverError as SolverError,
)
from ._progress import (
    AbstractProgressMeter as AbstractProgressMeter,
    NoProgress as NoProgress,
    TextProgress as TextProgress,
    TqdmProgress as TqdmProgress,
)
from ._results import RESULTS as RESULTS
from .fit._density import DensityFit as DensityFit, fit_density as fit_density
from .fit._driver import fit as fit, fit_batch as fit_batch
from .fit._images import load_target as load_target
from .fit._misfit import MisfitWarning as MisfitWarning
from .fit._result import FitResult as FitResult, IdentifiabilityWarning as IdentifiabilityWarning
from .fit._unknowns import Unknown as Unknown
from .forward._model import (
    AbstractForwardModel as AbstractForwardModel,
    AbstractLight as AbstractLight,
    Rendered as Rendered,
    map_batch as map_batch,
    render as render,
    render_batch as render_batch,
    stack_params as stack_params,
    unstack_params as unstack_params,
)
from ._cost import CostEstimate as CostEstimate
from ._cache import (
    enable_compilation_cache as enable_compilation_cache,
    enable_default_cache as _enable_default_cache,
)
from .forward._registry import (
    SOLVERS as SOLVERS,
    forward_model as forward_model,
    model_estimate as estimate,  # noqa: F401 (difffog.estimate: the public name)
)
from .forward.splat._model import SheetLight as SheetLight, SplatModel as SplatModel
from .forward.sweep._lightfield import LightField as LightField
from .forward.sweep._model import SweepModel as SweepModel
from .forward.sweep._solver import SweepSolver as SweepSolver
from .geometry._directions import DirectionSet as DirectionSet, direction_set as direction_set
from .geometry._lattice import Lattice as Lattice, voxelize as voxelize
from .scene._description import (
    Box as Box,
    Camera as Camera,
    Domain as Domain,
    Fog as Fog,
    Mesh as Mesh,
    OpenBox as OpenBox,
    Quad as Quad,
    Scene as Scene,
    Sky as Sky,
    Sphere as Sphere,
    Sun as Sun,
    Torus as Torus,
)
from .scene._params import (
    Params as Params,
    get_param as get_param,
    param_paths as param_paths,
    set_param as set_param,
    with_density as with_density,
)
from .scene._toml import (
    apply_overrides as apply_overrides,
    builtin_scenes as builtin_scenes,
    load_scene as load_scene,
    scalar_paths as scalar_paths,
)

__version__ = "0.2.0"


def __getattr__(name):
    # ``difffog.plot`` (matplotlib) loads on first use, so ``import difffog`` stays free of it
    if name == "plot":
        import importlib

        return importlib.import_module(".plot", __name__)
    raise AttributeError(f"module 'difffog' has no attribute {name!r}")


# compiled programs kept between processes (docs: difffog._cache; DIFFFOG_CACHE_DIR=off)
_enable_default_cache()
