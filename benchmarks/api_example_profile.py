"""Where the README API example's fit spends its time: the Levenberg–Marquardt steps, the final
statistics pass and each render of the refine correction and its checks, warm (the same fit
again in one process) and on its first call.

The fit is the README's (fog-balls, the Mitsuba 3 images, N = 28, both views at 1/4,
``model_error="refine"``); each phase is timed around difffog's own functions (wrapped here,
nothing in difffog changes).  The report starts with the machine and its copy bandwidth.

    PYTHONPATH=src python benchmarks/api_example_profile.py   # results/api_example_profile.md
"""

from __future__ import annotations

import argparse
import time

import _common as C


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=2, help="warm fits after the first")
    ap.add_argument("--out", default=str(C.RESULTS / "api_example_profile.md"))
    a = ap.parse_args(argv)
    info = C.machine()
    import difffog as df
    from difffog.fit import _driver as D
    from difffog.study.references import reference

    log = []

    def timed(label, fn):
        def wrapper(*args, **kw):
            t = time.perf_counter()
            out = fn(*args, **kw)
            log.append((label(args, kw), time.perf_counter() - t))
            return out
        return wrapper

    D._finer_images = timed(lambda a_, k: f"render N = {a_[1].resolution}", D._finer_images)
    D.make_model = timed(lambda a_, k: f"build model N = {k.get('resolution')}", D.make_model)
    D._fit_level = timed(lambda a_, k: "fit (LM steps + statistics)", D._fit_level)
    scene = df.load_scene("fog-balls")
    targets = {cam: reference("fog-balls", cam)[0] for cam in ("top", "oblique")}
    start = {"fog.scattering": 1.0, "fog.absorption": 0.8, "shape.walls.albedo": 0.5}
    kw = dict(resolution=28, downsample=4, model_error="refine", progress=False)
    lines = ["# Where the API example's fit spends its time", "",
             "`PYTHONPATH=src python benchmarks/api_example_profile.py` (see its docstring)", "",
             *C.machine_lines(info), ""]
    for run in ["first call"] + ["warm"] * a.repeat:
        log.clear()
        steps = []
        t = time.perf_counter()
        r = df.fit(scene, targets, start, callback=lambda e: steps.append(e["time_s"]), **kw)
        total = time.perf_counter() - t
        gaps = [round(b - a_, 1) for a_, b in zip([0.0] + steps, steps)]
        lines += [f"**{run}**: {total:.1f} s; {r.iterations} LM steps of {gaps} s; "
                  f"{r.ladder[1]['steps']} renders of the correction's model", "",
                  "| phase | s |", "|---|---:|"]
        lines += [f"| {what} | {s:.2f} |" for what, s in log] + [""]
        print("\n".join(lines[-len(log) - 5:]), flush=True)
    C.write_text(a.out, lines)


if __name__ == "__main__":
    main()
