"""Runs the notebooks at the small size in the background while the rest of the suite runs.

Most of a notebook's run, like most of the suite's, is XLA compiling, which keeps about one of
CI's two cores busy: started when collection finishes (``conftest.py``), one kernel at a time
in a background thread, the notebooks use the core the other tests leave idle, and
``test_notebooks.py`` collects the results when it gets there (waiting if they are not done).
Each run is a fresh Jupyter kernel (nbclient) with ``DIFFFOG_NOTEBOOK_SIZE=small``, this
checkout's ``difffog`` on its path and the session's persistent compilation cache.
"""

import asyncio
import os
import threading
import time
from pathlib import Path

import jupytext
import nbformat
from nbclient import NotebookClient

import difffog

NB_DIR = Path(__file__).resolve().parents[1] / "notebooks"
SRC = str(Path(difffog.__file__).resolve().parents[1])  # the difffog under test
LANES = 1  # kernels at a time (the other core runs the other tests)
CELL_TIMEOUT_S = 600  # generous: a loaded 2-core machine compiles the solver in up to ~60 s
FIRST = "02-fitting"  # the longest: started first

_runs: dict = {}  # {frozenset of names: _Runs}


class _Runs:
    def __init__(self, names):
        self.results: dict = {}
        self.thread = threading.Thread(target=asyncio.run, args=(self._run_all(sorted(names)),),
                                       daemon=True, name="notebooks")
        self.thread.start()

    @staticmethod
    def _env():
        path_entries = [SRC] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep)
                                if p]
        env = dict(os.environ, DIFFFOG_NOTEBOOK_SIZE="small",
                   PYTHONPATH=os.pathsep.join(path_entries))
        cache = os.environ.get("DIFFFOG_TEST_XLA_CACHE")  # conftest.py's: this session's cache
        if cache:  # a program another kernel or an earlier test compiled is a cache hit
            env |= {"JAX_COMPILATION_CACHE_DIR": cache,
                    "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0.5",
                    "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": "0"}
        return env

    async def _run(self, name, lanes, env):
        nb = jupytext.read(NB_DIR / f"{name}.py")
        nb.cells.append(nbformat.v4.new_code_cell("import difffog; print(difffog.__file__)"))
        client = NotebookClient(nb, timeout=CELL_TIMEOUT_S, kernel_name="python3",
                                resources={"metadata": {"path": str(NB_DIR)}})
        async with lanes:
            t = time.perf_counter()
            try:
                await client.async_execute(env=env)
                error = None
            except Exception as e:  # CellExecutionError names the cell, with its traceback
                error = e
            self.results[name] = (nb, error, time.perf_counter() - t)

    async def _run_all(self, names):
        lanes = asyncio.Semaphore(LANES)
        env = self._env()
        order = sorted(names, key=lambda n: n != FIRST)
        await asyncio.gather(*(self._run(n, lanes, env) for n in order))


def start(names) -> None:
    """Start running ``names`` (once per set of names)."""
    key = frozenset(names)
    if key and key not in _runs:
        _runs[key] = _Runs(key)


def results(names) -> dict:
    """{name: (executed notebook, the exception it raised or None, seconds)}, waiting for the
    runs (started now if they were not)."""
    start(names)
    runs = _runs[frozenset(names)]
    runs.thread.join()
    return runs.results


def small_run_names(items) -> set:
    """The notebooks whose small-size run this session's ``items`` test."""
    return {item.callspec.params["name"] for item in items
            if getattr(item, "originalname", None) == "test_notebook_runs_at_the_small_size"}
