import os
import tempfile

import jax
import pytest

import notebook_runs
from difffog import enable_compilation_cache
from difffog._cache import release_if_crowded
from helpers import MODELS, XLA_OPT_FLAG, build_fit_model, build_model


#: the marker expression of the default suite (pyproject.toml's addopts)
DEFAULT_MARKS = "not slow and not bench"


def _xla_optimization(config) -> None:
    """The default suite compiles XLA's own code at LLVM's -O0; ``-m slow`` / ``-m bench`` and
    ``DIFFFOG_TEST_XLA_OPT=default`` keep XLA's default (-O3, what users run).

    The default suite is bound by XLA's compiles (user time ~1,200 s on 2 cores against ~650 s
    of wall time, most of it compiling small programs), and -O0 compiles them in about half the
    time (a fit's Jacobian program of the tests' 10-node model 5.6 s instead of 9.9 s): on a
    clean clone the suite took 8:04 (user 868 s) instead of 10:41 (user 1167 s) 40 minutes
    before, on this 2-core CPU, though warm renders run 2-2.5x slower at -O0 (the camera march
    is XLA's code), which the tests' small lattices barely feel.  The native C++ kernels are
    built with -O3 either way.  The values are the same to float32 rounding (three scenes'
    images and gradients at both levels: at most 6e-6 apart), and ``test_camera.py::
    test_the_suites_xla_level_...`` holds the rounding-sensitive camera march at both levels to
    1e-12 on every run, so that a fault only -O3's code shows (the march's FMA rounding, stop
    41) still fails the suite.  ``DIFFFOG_TEST_XLA_OPT=N`` asks for level N whatever the
    markers."""
    opt = os.environ.get("DIFFFOG_TEST_XLA_OPT")
    if opt is None:
        opt = "0" if (config.getoption("markexpr", "") or "").strip() == DEFAULT_MARKS else ""
    if opt in ("", "default"):
        return
    if opt not in ("0", "1", "2", "3"):
        raise pytest.UsageError(f"DIFFFOG_TEST_XLA_OPT={opt!r}: use 0-3 (LLVM's level for XLA's "
                                "code) or 'default' (XLA's own, -O3)")
    flags = os.environ.get("XLA_FLAGS", "")
    if XLA_OPT_FLAG not in flags:  # a level set by hand stays
        os.environ["XLA_FLAGS"] = f"{flags} {XLA_OPT_FLAG}={opt}".strip()


def pytest_configure(config):
    _xla_optimization(config)
    # Tests build many small models whose compiled programs are identical (the same scene at
    # the same size in several modules, or in both pytest-xdist workers): a persistent
    # compilation cache shared by this session's processes turns every repeat compile into a
    # cache hit.  A fresh folder per session (the first process makes it; xdist workers
    # inherit it through the environment), so runs stay independent.
    # The command line (in-process and in subprocesses) uses the same folder.
    cache = os.environ.get("DIFFFOG_TEST_XLA_CACHE")
    if not cache:
        cache = tempfile.mkdtemp(prefix="difffog-test-xla-")
        os.environ["DIFFFOG_TEST_XLA_CACHE"] = cache
    os.environ["DIFFFOG_CACHE_DIR"] = cache
    # pytest-xdist's workers share the cores: the native kernels' threads take fixed shares
    # of a sweep (so that its sums are the same to the bit), and with two workers of two
    # threads each on two cores a thread whose core was taken held up its call (the suite
    # 8.5 → 12.6 minutes); each worker's kernels get its share of the cores instead
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1)
    if workers > 1 and "DIFFFOG_THREADS" not in os.environ:
        try:
            cores = len(os.sched_getaffinity(0))
        except AttributeError:
            cores = os.cpu_count() or 1
        os.environ["DIFFFOG_THREADS"] = str(max(1, cores // workers))
    enable_compilation_cache(cache)


# The test files that take longest, longest first (junit times of the default suite at -O0,
# stop 83: test_fit 170 s, test_native 118, test_extremes 98, test_sweep 94, test_tomography 72,
# test_batch 64, then 30-50 s each; the notebooks' small runs are in test_notebooks' first
# test).  pytest-xdist hands each worker a whole file at a time in collection order (addopts:
# --dist loadfile --no-loadscope-reorder); with the long files first the short ones fill the
# gaps at the end, where alphabetical order, or xdist's own by-test-count order, left one
# worker running a long file alone for minutes (test_native.py, unlisted, ran last at stop 83).
LONGEST_FIRST = ["test_fit.py", "test_native.py", "test_extremes.py", "test_sweep.py",
                 "test_tomography.py", "test_batch.py", "test_anisotropic.py", "test_camera.py",
                 "test_notebooks.py", "test_thick.py", "test_splat.py", "test_interface.py",
                 "test_pallas.py", "test_cli.py", "test_substep.py", "test_slab_cameras.py",
                 "test_linear_scheme.py", "test_sun_unknown.py"]


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable within a file


def pytest_collection_finish(session):
    # the notebooks' small-size runs start now, in the background (notebook_runs.py), to use
    # the core the other tests leave idle — unless the suite runs on several pytest-xdist
    # workers (its default, pyproject.toml), which use both cores already: then the worker
    # that gets test_notebooks.py runs them when it gets there (notebook_runs.results)
    # (a kernel whose pytest dies exits too: ipykernel polls its parent)
    names = notebook_runs.small_run_names(session.items)
    worker = hasattr(session.config, "workerinput")
    if names and not session.config.option.collectonly and not worker:
        notebook_runs.start(names)


@pytest.fixture(autouse=True)
def _release_compiled_programs():
    """After a test, drop JAX's compiled programs when they hold more than half the memory
    mappings a process may have.  Each XLA CPU executable maps its own code and data (~1,100
    mappings for a small render), and a worker that compiles most of the suite passed Linux's
    default limit (65,530) near its end: LLVM then failed to map memory for the next program
    and the worker died of a segmentation fault inside XLA's compiler (stop 47, on a clean
    clone; once in stop 45). Programs compiled again later load from the session's persistent
    cache.  (The library does the same above 60% when it builds a model, with a warning:
    ``difffog._cache.release_if_crowded``; half keeps the suite clear of that warning.)"""
    yield
    release_if_crowded(0.5, warn=False)


@pytest.fixture
def x64():
    """Run a test in float64 (and restore the previous setting afterwards)."""
    old = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", old)


_MODELS: dict = {}


@pytest.fixture(params=list(MODELS))
def model(request):
    """Each small forward model of ``helpers.MODELS`` (float32), built once per session and
    shared by every test module that asks for it (their compiled code is shared too)."""
    if request.param not in _MODELS:
        _MODELS[request.param] = build_model(request.param)
    return _MODELS[request.param]


@pytest.fixture(scope="session")
def sweep_model():
    """The small sweep model of ``helpers.MODELS`` (shared)."""
    if "sweep" not in _MODELS:
        _MODELS["sweep"] = build_model("sweep")
    return _MODELS["sweep"]


@pytest.fixture(params=list(MODELS))
def fit_model(request):
    """Each solver's fog-balls model as a fit builds it (``helpers.build_fit_model``), shared
    by every fit test of the session so that the fit's compiled step is shared."""
    key = ("fit", request.param)
    if key not in _MODELS:
        _MODELS[key] = build_fit_model(request.param)
    return _MODELS[key]


@pytest.fixture
def sweep_fit_model():
    """The sweep's fit model of ``fit_model`` (shared)."""
    if ("fit", "sweep") not in _MODELS:
        _MODELS[("fit", "sweep")] = build_fit_model("sweep")
    return _MODELS[("fit", "sweep")]
