"""The parser and the entry point.  Errors a user can fix print one line (``difffog: error:
…``) and exit with status 2; a light solve or fit that did not converge exits with status 1;
nothing is left half-written (outputs go through ``difffog._output.atomic_folder``)."""

from __future__ import annotations

import argparse
import gc
import os
import sys
import warnings

from .._errors import (AdjointWarning, DeviceWarning, DifffogError, MemoryWarning,
                       ResourceError, ThickStepWarning, ThinLayerWarning)
from ..fit._misfit import MisfitWarning
from ..fit._result import IdentifiabilityWarning
from ..forward._registry import LEVELS, SOLVERS, preset, solver_entry

DEFAULT_SCENE = "fog-balls"


def add_scene_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", nargs="?", default=DEFAULT_SCENE,
                   help=f"a scene file (.toml) or a built-in scene name (default: {DEFAULT_SCENE})")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="PATH=VALUE",
                   help="override a scalar of the scene, e.g. fog.scattering=2.5 (repeatable)")
    p.add_argument("--accuracy", choices=LEVELS, default="default",
                   help="preset of the solver's settings (resolution, directions, tolerance, "
                        "sheets) from the measured speed-accuracy study (default: default); the "
                        "options below override single settings")
    p.add_argument("--resolution", "-N", type=int, default=None,
                   help="lattice nodes along the longest domain axis (default: from --accuracy, "
                        f"{preset('sweep')['resolution']} at default)")
    p.add_argument("--directions", "-M", type=int, default=None,
                   help="sweep: direction half-width M, (2M+1)^2 directions per cube face "
                        f"(default: from --accuracy, {preset('sweep')['M']} at default)")
    p.add_argument("--phase-order", type=int, default=None, metavar="L",
                   help="sweep: order of a Henyey-Greenstein fog's phase in the light solve "
                        "((L+1)^2 angular moments per node, delta-M; 0: delta-isotropic; default: "
                        "0 for an isotropic fog, 3 otherwise)")
    p.add_argument("--scheme", choices=("auto", "step", "linear", "substep"), default=None,
                   help="sweep: the transport scheme along lattice rays: step (a constant "
                        "source per node), linear (the source linear along each segment: the "
                        "right diffusion limit where a lattice step is optically thick), "
                        "substep (each segment crossed plane by plane through the nearest "
                        "nodes: clouds' edges and thick fog at a coarse lattice; slower) or auto "
                        "(default: linear where one lattice step is thicker than a mean free "
                        "path; a density fit's default is substep; see docs/validation.md)")
    p.add_argument("--first-collision", choices=("beam", "deposit"), default=None,
                   help="sweep: what the fog's first collision scatters: beam (default: the "
                        "uncollided sun and sky at each node) or deposit (what the beams lose, "
                        "box-filtered as the lattice's steps are: conserves energy where a step "
                        "is optically thick; see docs/validation.md)")
    p.add_argument("--once-M", dest="once_M", type=int, default=None, metavar="K",
                   help="sweep: carry the sun's once-scattered light on the finer direction "
                        "set of half-width K (a Henyey-Greenstein fog under a sun: its forward "
                        "lobe, which M = 3 samples coarsely; one more sub-stepped sweep per "
                        "solve; default: off; see docs/validation.md)")


def positive_int(name: str, value: int | None) -> int | None:
    if value is not None and value < 1:
        raise DifffogError(f"{name} must be a positive integer, got {value}")
    return value


def model_settings(args, solver: str, *, accuracy: str | None) -> dict:
    """The forward model's settings from the command line: the preset of ``accuracy`` (None:
    none) overridden by the flags that were given, each checked against what the solver
    takes (a flag for another solver is a one-line error naming the flag)."""
    flags = {"resolution": ("--resolution", getattr(args, "resolution", None)),
             "M": ("--directions", getattr(args, "directions", None)),
             "sheets": ("--sheets", getattr(args, "sheets", None)),
             "method": ("--method", getattr(args, "method", None)),
             "tol": ("--tol", getattr(args, "tol", None)),
             "max_iterations": ("--max-iterations", getattr(args, "max_iterations", None)),
             "supersample": ("--supersample", getattr(args, "supersample", None)),
             "devices": ("--devices", getattr(args, "devices", None)),
             "phase_order": ("--phase-order", getattr(args, "phase_order", None)),
             "scheme": ("--scheme", getattr(args, "scheme", None)),
             "first_collision": ("--first-collision", getattr(args, "first_collision", None)),
             "once_M": ("--once-M", positive_int("--once-M", getattr(args, "once_M", None)))}
    if getattr(args, "iterations", None) is not None:
        flags["max_iterations"] = ("--iterations", args.iterations)
        flags["tol"] = ("--iterations", 0.0)  # exactly K iterations
    takes = solver_entry(solver).settings
    out = {} if accuracy is None else preset(solver, accuracy)
    for key, (flag, value) in flags.items():
        if value is None:
            continue
        if key not in takes:
            raise DifffogError(f"{flag} does not apply to --solver {solver}; its settings "
                               f"are {', '.join(takes)}")
        out[key] = value
    return out


def build_parser() -> argparse.ArgumentParser:
    from . import _bench, _fit, _info, _render

    parser = argparse.ArgumentParser(
        prog="difffog",
        description="Differentiable fog rendering and inverse fog estimation.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in (_info, _render, _fit, _bench):
        mod.add_parser(sub)
    return parser


def solver_help() -> str:
    return "; ".join(f"{n}: {e.summary}" for n, e in SOLVERS.items())


def _host_devices(n: int) -> None:
    """Ask XLA for n host (CPU) devices if JAX has not started yet and nobody chose a count;
    on a GPU machine the flag only concerns the host platform, so it is harmless."""
    try:  # XLA reads the flag when the first backend starts, not at ``import jax``
        from jax._src import xla_bridge

        started = xla_bridge.backends_are_initialized()
    except (ImportError, AttributeError):
        started = "jax" in sys.modules
    if n > 1 and not started:
        flags = os.environ.get("XLA_FLAGS", "")
        if "xla_force_host_platform_device_count" not in flags:
            os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={n}".strip()


def main(argv=None) -> int:
    if argv is None:  # run as the program (not called from Python with its own arguments)
        # the ~170,000 objects the imports made (JAX, SciPy, difffog) live as long as the
        # process: out of the collector's way, each full collection while JAX traces and
        # lowers the programs scans only what came after (a cached render: 0.15-0.2 s less)
        gc.freeze()
    parser = build_parser()
    args = parser.parse_args(argv)
    _host_devices(getattr(args, "devices", None) or 1)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    # difffog's own warnings (thick steps, unconverged adjoints, identifiability, a shape
    # thinner than a voxel: whatever its code warns) as one line each, like its errors, rather
    # than Python's file:line and source line
    shown = warnings.showwarning
    said = (ThickStepWarning, ThinLayerWarning, AdjointWarning, IdentifiabilityWarning,
            MemoryWarning, DeviceWarning, MisfitWarning)
    package = os.path.dirname(os.path.dirname(os.path.abspath(__file__))) + os.sep

    def one_line(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, said) or (
                os.path.abspath(str(filename)).startswith(package)):
            print(f"difffog: warning: {message}", file=sys.stderr)
        else:
            shown(message, category, filename, lineno, file, line)

    try:
        with warnings.catch_warnings():
            warnings.showwarning = one_line
            for category in said:
                warnings.simplefilter("always", category)  # said, never raised
            return args.func(args)
    except ResourceError as e:  # a valid request this machine cannot hold: like a failed solve
        print(f"difffog: error: {e}", file=sys.stderr)
        return 1
    except DifffogError as e:
        print(f"difffog: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("difffog: interrupted", file=sys.stderr)
        return 130


def peak_memory_mb() -> float:
    """This process's peak resident memory (MiB): VmHWM on Linux (the high-water mark of this
    program's own address space; ``ru_maxrss`` also keeps that of the process it was started
    from, e.g. a 1.3 GB pytest counted into a 0.7 GB render), else ``ru_maxrss``."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
