"""``difffog bench``: the speed–accuracy study (``difffog.study``) from the command line."""

from __future__ import annotations

import sys
from pathlib import Path

from ..forward._registry import SOLVERS


def add_parser(sub) -> None:
    p = sub.add_parser("bench", help="the speed-accuracy study: both solvers over their knobs "
                                      "against the Monte Carlo references; CSV + Pareto plot")
    p.add_argument("--scenes", nargs="+", default=["fog-balls", "ring-box", "translucent-cube",
                                                   "cloud-plane"],
                   help="scenes with reference images (default: the four benchmark scenes)")
    p.add_argument("--solvers", nargs="+", default=list(SOLVERS), choices=list(SOLVERS))
    p.add_argument("--references", default=None, metavar="DIR",
                   help="reference images (<scene>/<camera>.npy, convergence.csv); default: "
                        "the Mitsuba 3 references shipped with difffog")
    p.add_argument("--quick", action="store_true",
                   help="one small setting per solver (a smoke test)")
    p.add_argument("--out", default="bench", help="output folder (default: bench)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress or summary")
    p.set_defaults(func=run)


def run(args) -> int:
    from .._output import check_out_dir
    from .._progress import NoProgress, TqdmProgress
    from ..study._bench import run_bench

    out = check_out_dir(args.out)
    progress = TqdmProgress("bench") if sys.stderr.isatty() and not args.quiet else NoProgress()
    res = run_bench(scenes=args.scenes, solvers=args.solvers, out=out,
                    references=Path(args.references) if args.references else None,
                    quick=args.quick, progress=progress)
    if not args.quiet:
        print(res.summary_path.read_text())
        print(f"{res.csv_path}, {res.plot_path}: {len(res.rows)} rows")
    return 0
