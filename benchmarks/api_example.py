"""The README's API example, timed and checked: the estimates against the truth, the stated
uncertainties, and the fit's wall time in a new process and warm.

The first ```python block of README.md is run as it stands (it fits ζ, γ and the walls'
albedo of fog-balls to the Mitsuba 3 images shipped with difffog), in fresh processes:

* ``first``: a new process with an empty compilation cache (a folder of this run's own);
* ``new process``: a second new process on the cache the first one filled (what a user gets
  the second time they run the example, ``import difffog`` keeps XLA's programs on disk);
* ``warm``: the same fit once more inside that second process (what a notebook gets when a
  cell is run again); ``--warm K`` runs it K times and reports the median.

Each ``difffog.fit`` call is timed around the call (its wall time, the refined model error's
render included).  The truth is the scene file's own values (the references were rendered
from them).  The report starts with the machine and its copy bandwidth, measured in the same
run.

    PYTHONPATH=src python benchmarks/api_example.py            # writes results/api_example.md
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _common as C

ROOT = Path(__file__).resolve().parents[1]

# run inside a child process: the README's block with difffog.fit timed, then (``--warm``) the
# last fit again in the same process
CHILD = r"""
import json, sys, time
import difffog as df
calls = []
_fit = df.fit
def timed(*a, **k):
    t = time.perf_counter()
    r = _fit(*a, **k)
    calls.append((a, k, r, time.perf_counter() - t))
    return r
df.fit = timed
code = sys.stdin.read()
t0 = time.perf_counter()
exec(compile(code, "README.md", "exec"), {"__name__": "__main__"})
total = time.perf_counter() - t0
a, k, r, wall = calls[-1]
out = {"total_s": total, "fit_s": wall, "result": r.to_json()}
if "--warm" in sys.argv:
    out["warm_all_s"] = []
    for _ in range(int(sys.argv[sys.argv.index("--warm") + 1])):
        t = time.perf_counter()
        r2 = _fit(*a, **k)
        out["warm_all_s"].append(time.perf_counter() - t)
    out["warm_fit_s"] = sorted(out["warm_all_s"])[len(out["warm_all_s"]) // 2]
    out["warm_estimates"] = r2.estimates
print("@@" + json.dumps(out))
"""


def readme_block() -> str:
    text = (ROOT / "README.md").read_text()
    m = re.search(r"```python\n(.*?)```", text, re.S)
    if m is None:
        raise SystemExit("README.md has no ```python block")
    return m.group(1)


def run_child(code: str, cache: Path, warm: int) -> dict:
    env = dict(os.environ, DIFFFOG_CACHE_DIR=str(cache))
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", CHILD] + (["--warm", str(warm)] if warm else []),
                          input=code, capture_output=True, text=True, env=env, cwd=ROOT)
    wall = time.perf_counter() - t
    if proc.returncode:
        raise SystemExit(f"the README example failed:\n{proc.stderr[-3000:]}")
    sys.stdout.write(proc.stdout.split("@@")[0])
    line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("@@"))
    out = json.loads(line[2:])
    out["process_s"] = wall
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=C.RESULTS)
    ap.add_argument("--warm", type=int, default=1,
                    help="how many times the fit runs again warm (the median is reported)")
    args = ap.parse_args()
    import difffog as df

    info = C.machine()
    C.print_machine(info)
    scene = df.load_scene("fog-balls")
    code = readme_block()
    with tempfile.TemporaryDirectory() as cache:
        first = run_child(code, Path(cache), warm=0)
        second = run_child(code, Path(cache), warm=max(1, args.warm))
    res = second["result"]
    rows = []
    for p in res["paths"]:
        truth = float(df.get_param(df.Params.from_scene(scene), scene, p))
        est, unc = res["estimates"][p], res["uncertainty"].get(p) or res["stderr"][p]
        rows.append([p, f"{truth:g}", f"{res['fitted'][p]:.4g}", f"{est:.4g}",
                     f"{100 * (est / truth - 1):+.2f}", f"{100 * res['stderr'][p] / truth:.2f}",
                     f"{100 * unc / truth:.2f}", f"{abs(est - truth) / unc:.2f}"])
    lines = ["# The README's API example", "",
             "`PYTHONPATH=src python benchmarks/api_example.py`: the README's first Python "
             "block run as it stands, in new processes (see the script's docstring).", "",
             *C.machine_lines(info), "",
             *C.md_table(["unknown", "truth", "fit (its N)", "estimate", "error %",
                          "std err %", "total ± %", "|error| / total"], rows), "",
             f"- result `{res['result']}` after {res['iterations']} steps; estimates: the fit "
             f"at N = {res['ladder'][0]['resolution']} corrected to N = "
             f"{res['ladder'][1]['resolution']}"
             + (f", M = {res['ladder'][1]['M']}" if "M" in res["ladder"][1] else "")
             if res.get("ladder") else "",
             f"- `difffog.fit` wall time: first run (empty compilation cache) "
             f"{first['fit_s']:.1f} s, a new process on the filled cache "
             f"{second['fit_s']:.1f} s, warm (the same fit again in that process) "
             f"{second['warm_fit_s']:.1f} s"
             + (f" (median of {len(second['warm_all_s'])}: "
                f"{', '.join(f'{x:.1f}' for x in second['warm_all_s'])})"
                if len(second["warm_all_s"]) > 1 else ""),
             f"- the whole example (render, fit, printout): {first['total_s']:.1f} s first, "
             f"{second['total_s']:.1f} s in a new process; the process including Python and "
             f"JAX start-up {first['process_s']:.1f} / {second['process_s']:.1f} s"]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "api_example.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
