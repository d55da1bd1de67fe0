"""An unknown whose best value is its bound: a fog that does not absorb (γ = 0), a scene with
no fog.

The unknowns of a fit live in log coordinates (v = lower + exp(u)), so a bound is never
reached: the optimum at γ = 0 lies at u → −∞, which Levenberg–Marquardt approaches a step at a
time (fog-balls' γ from images of γ = 0: 0.12 → 0.0002 in 50 steps, the fit "not converged"
after max_steps, exit status 1).  ``fit`` then holds such an unknown at its bound and fits the
others again from where they were (``fit``'s ``_refit_at_bound``); this module states what the
images say of the held one: its estimate is the bound, and its standard error is that of the
joint linear model at the bound (the refit's Jacobian and the held unknown's column, from the
first fit's last step in physical units: ∂r/∂v = (∂r/∂u)/(v − lower)), so that the images
allow it up to lower + 1.645 σ at 95%, one-sided; the other unknowns' standard errors are that
model's too (they correlate with the held one, which may lie above its bound).  With ``model_error="refine"`` the finer
model's images at the estimate move it by the joint Gauss–Newton step, its "lattice" part.
"""

from __future__ import annotations

import math

import numpy as np

#: one-sided 95% quantile of a normal variable
Z95 = 1.6449


def held_columns(first, held: list[str]) -> np.ndarray:
    """The held unknowns' Jacobian columns (physical units) at the first fit's last step."""
    lin = first._linear
    st, u, J = lin["setup"], lin["u"], lin["J"]
    cols = []
    for path in held:
        k = [c.path for c in st.coords].index(path)
        c = st.coords[k]
        cols.append(J[:, k] / c.dv_du(float(u[k])))
    return np.stack(cols, axis=1)


def with_held(res, first, held: list[str], bounds: dict[str, float]):
    """``res`` (the refit without the ``held`` unknowns, at their ``bounds``) with them back:
    estimate the bound, standard error from the joint linear model, a lattice part from the
    finer model's change where the refit has one, and the one-sided 95% limit in
    ``res.at_bound``."""
    lin = res._linear
    st, J2, r = lin["setup"], lin["J"], lin["residual"]
    sqrt_w = np.asarray(st.data[1], np.float64)
    Jh = held_columns(first, held)
    J = np.concatenate([J2, Jh], axis=1)
    mask = sqrt_w > 0
    dof = max(int(np.sum(mask)) - J.shape[1], 1)
    s2 = float(np.sum(r[mask] ** 2)) / dof
    cov = s2 * np.linalg.pinv(J[mask].T @ J[mask])
    n2 = J2.shape[1]
    change = getattr(res, "_fine_change", None)
    shift = (-np.linalg.lstsq(J[mask], change[mask], rcond=None)[0][n2:]
             if change is not None else None)
    paths = list(first.paths)
    # the joint model's correlation (a correlation is the same in any monotone coordinates)
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        joint = cov / np.outer(sd, sd)
    at = {p: i for i, p in enumerate(list(res.paths) + list(held))}
    idx = [at[p] for p in paths]
    corr = joint[np.ix_(idx, idx)]
    np.fill_diagonal(corr, 1.0)
    # the others' standard errors: the joint model's (the held unknown may lie above its bound,
    # and they are correlated with it), not the refit's, which hold it fixed
    u = lin["u"]
    for i, c in enumerate(st.coords):
        joint_se = math.sqrt(max(float(cov[i, i]), 0.0)) * abs(c.dv_du(float(u[i])))
        if joint_se > res.stderr[c.path]:
            res.stderr[c.path] = joint_se
            res.uncertainty[c.path] = math.hypot(joint_se, res.model_error.get(c.path, 0.0))
    res.at_bound = {}
    for k, p in enumerate(held):
        se = math.sqrt(max(float(cov[n2 + k, n2 + k]), 0.0))
        res.estimates[p] = bounds[p]
        res.stderr[p] = se
        if res.fitted:
            res.fitted[p] = bounds[p]
        if shift is not None:  # the finer model's pull on it, as the refit's lattice part
            lat = abs(float(shift[k]))
            res.model_error_parts[p] = {"lattice": lat}
            res.model_error[p] = lat
        elif res.model_error:  # the refit's model error is unknown: so is this one's
            res.model_error[p] = math.nan
        total = math.hypot(se, res.model_error.get(p, 0.0))
        res.uncertainty[p] = total
        res.at_bound[p] = {"bound": bounds[p],
                           "upper_95": bounds[p] + Z95 * (total if math.isfinite(total) else se)}
    res.initial = dict(first.initial)  # (the refit started where the first fit stopped)
    order = {p: i for i, p in enumerate(paths)}
    res.paths = paths
    for d in (res.estimates, res.stderr, res.uncertainty, res.model_error,
              res.model_error_parts, res.fitted):
        items = sorted(d.items(), key=lambda kv: order.get(kv[0], len(order)))
        d.clear()
        d.update(items)
    res.correlation = corr
    said = "; ".join(f"{p} < {v['upper_95']:.3g} (95%, one-sided)"
                     for p, v in res.at_bound.items())
    note = (f"{', '.join(held)} ran to {'its bound' if len(held) == 1 else 'their bounds'} "
            f"({', '.join(f'{bounds[p]:g}' for p in held)}): the images need none of "
            f"{'it' if len(held) == 1 else 'them'}. Held there and the other unknowns fit "
            f"again: {said}")
    res.message = note if not res.message else f"{note}; {res.message}"
    res.history = list(first.history) + [
        {**h, "values": {**h["values"], **{p: bounds[p] for p in held}}, "held_at_bound": held}
        for h in res.history]
    res.iterations += first.iterations
    res.time_s += first.time_s
    return res
