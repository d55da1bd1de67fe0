"""One validation path for scenes, whether read from a file or built in Python.

Every scene object (:class:`Domain`, :class:`Fog`, a shape, a :class:`Camera`,
:class:`Scene`) converts and checks its own fields when it is constructed (``__post_init__``
calls :func:`check`), and the file loader (``_toml.py``) builds the same objects.  A message
names where the value sits — the file, table and field (``scene.toml: [[shape]] #2
'ball-high'.radius = -1.0 must be > 0``) when loading, the constructor
(``difffog.Sphere('ball'): radius = -1.0 ...``) in Python — then the bad value and the fix.
The loader says where it is with :func:`located`.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import difflib
import io
import math
import re
import warnings
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from .._errors import SceneError
from ._description import (FACES, Box, Camera, Domain, Fog, Mesh, OpenBox, Quad, Scene, Sky,
                           Sphere, Sun, Torus)

_PHASES = ("isotropic", "henyey-greenstein")
_BOUNDARIES = ("open", "periodic-xy")
_NAME_RE = re.compile(r"[^\s.=\[\]'\"]+")
_REQ = object()  # marks a required field in a spec
_UNSET = object()

# --------------------------------------------------------------------------- messages


def _fmt(v: Any) -> str:
    """A value as it would be written in TOML."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace('"', '\\"') + '"'
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if v != v else ("inf" if v > 0 else "-inf"))
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_fmt(x)}" for k, x in v.items()) + "}"
    if isinstance(v, np.ndarray):
        return _fmt(v.tolist())
    return str(v)


def _a(word: str) -> str:
    return ("an " if word[0] in "aeiou" else "a ") + word


def _type_name(v: Any) -> str:
    if isinstance(v, bool):
        return "a boolean"
    if isinstance(v, (int, float)):
        return "a number"
    if isinstance(v, str):
        return "a string"
    if isinstance(v, list):
        return "a list"
    if isinstance(v, dict):
        return "a table"
    return f"a {type(v).__name__}"


def _suggest(word: str, options: Iterable[str], quote: str = "'") -> str:
    close = difflib.get_close_matches(word, list(options), n=1, cutoff=0.6)
    return f" Did you mean {quote}{close[0]}{quote}?" if close else ""


@dataclasses.dataclass(frozen=True)
class _At:
    """Where a value sits: the file (or scene and overrides) and the table."""

    origin: str
    table: str

    def __call__(self, field: str | None, value: Any, problem: str) -> SceneError:
        head = ".".join(x for x in (self.table, field) if x)
        if value is not _UNSET:
            head += f" = {_fmt(value)}"
        return SceneError(f"{self.origin}: {head} {problem}" if head
                          else f"{self.origin}: {problem}")


# --------------------------------------------------------------------------- value converters
# Each takes (value, at, field) and returns the Python value or raises SceneError.


def _seq(v):
    """A list from a TOML list, a tuple or a NumPy array (Python-built scenes)."""
    if isinstance(v, (tuple, np.ndarray)):
        return list(np.asarray(v).tolist()) if isinstance(v, np.ndarray) else list(v)
    return v


#: the largest magnitude a scene number may have: difffog computes in float32 (largest 3.4e38),
#: and products of two scene numbers (σ_t × a length, an irradiance × an area) must stay finite
MAX_MAGNITUDE = 1e15
_TOO_BIG = (f"is beyond ±{MAX_MAGNITUDE:g}: difffog computes in float32 (up to 3.4e38), where "
            "such a number overflows once combined with others (σ_t × length, irradiance × "
            "area); rescale the units")


def _is_number(x) -> bool:
    return not isinstance(x, (bool, np.bool_)) and isinstance(x, (int, float, np.integer,
                                                                     np.floating))


def _number(v, at: _At, f: str) -> float:
    if not _is_number(v):
        raise at(f, v, f"must be a number, not {_type_name(v)} (write numbers without quotes, "
                       "e.g. 1.0)")
    try:
        x = float(v)
    except OverflowError:
        x = math.inf
    if not math.isfinite(x):
        raise at(f, v, "must be a finite number")
    if abs(x) > MAX_MAGNITUDE:
        raise at(f, v, _TOO_BIG)
    return x


def _string(v, at: _At, f: str) -> str:
    if not isinstance(v, str):
        raise at(f, v, f"must be a string, not {_type_name(v)}; write it in quotes, "
                       f'e.g. {f} = "..."')
    return v


def _vector(n: int, what: str) -> Callable:
    def conv(v, at: _At, f: str) -> tuple[float, ...]:
        v = _seq(v)
        if not isinstance(v, list) or len(v) != n or not all(_is_number(x) for x in v):
            got = f"{len(v)} items" if isinstance(v, list) else _type_name(v)
            raise at(f, v, f"must be a list of {n} numbers {what}, got {got}")
        out = tuple(float(x) for x in v)
        if not all(math.isfinite(x) for x in out):
            raise at(f, v, "must contain finite numbers only")
        if any(abs(x) > MAX_MAGNITUDE for x in out):
            raise at(f, v, _TOO_BIG)
        return out

    return conv


_vec3 = _vector(3, "[x, y, z]")
_vec2 = _vector(2, "[width, height]")


def _resolution(v, at: _At, f: str) -> tuple[int, int]:
    v = _seq(v)
    if not isinstance(v, list) or len(v) != 2 or any(
        isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, np.integer)) for x in v
    ):
        raise at(f, v, "must be two whole numbers [width, height] of pixels, e.g. [160, 120]")
    return (int(v[0]), int(v[1]))


def _faces(v, at: _At, f: str) -> tuple[str, ...]:
    v = _seq(v)
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
        raise at(f, v, f"must be a list of face names among {_fmt(list(FACES))}")
    return tuple(v)


def _corners(v, at: _At, f: str):
    v = _seq(v)
    if not isinstance(v, list) or len(v) != 4:
        got = f"{len(v)} points" if isinstance(v, list) else _type_name(v)
        raise at(f, v, f"must be 4 points [[x, y, z], ...] counter-clockwise seen from the lit "
                       f"side, got {got}")
    return tuple(_vec3(c, at, f"{f}[{i}]") for i, c in enumerate(v))


def _region(v, at: _At, f: str):
    if isinstance(v, (tuple, list)) and len(v) == 2:  # (min, max) as the dataclass holds it
        v = {"min": v[0], "max": v[1]}
    if not isinstance(v, dict):
        raise at(f, v, "must be a table, e.g. region = { min = [0, 0, 0], max = [1, 1, 1] }")
    sub = _At(at.origin, f"{at.table}.{f}")
    kw = _read_fields(v, {"min": (_vec3, _REQ), "max": (_vec3, _REQ)}, sub, "region")
    return (kw["min"], kw["max"])


_SCALAR_CONVERTERS = (_number, _string)

# --------------------------------------------------------------------------- specs
# field -> (converter, default); the field names are those of the dataclasses in _scene.py,
# except fog.density (-> density_path + the loaded grid).

_TABLES: dict[str, dict[str, tuple]] = {
    "domain": {"min": (_vec3, _REQ), "max": (_vec3, _REQ), "boundary": (_string, "open")},
    "fog": {
        "scattering": (_number, _REQ),
        "absorption": (_number, 0.0),
        "phase": (_string, "isotropic"),
        "g": (_number, None),
        "density": (_string, None),
        "region": (_region, None),
    },
    "sun": {
        "irradiance": (_number, _REQ),
        "zenith_deg": (_number, _REQ),
        "azimuth_deg": (_number, 0.0),
        "angular_radius_deg": (_number, 0.0),
    },
    "sky": {"radiance": (_number, _REQ)},
}
# what an override of an absent table starts from
_CREATED = {
    "fog": lambda: Fog(scattering=0.0, absorption=0.0),
    "sun": lambda: Sun(irradiance=0.0, zenith_deg=0.0, azimuth_deg=0.0),
    "sky": lambda: Sky(radiance=0.0),
}

_SHAPE_COMMON = {
    "name": (_string, None),
    "kind": (_string, _REQ),
    "albedo": (_number, 0.5),
    "emission": (_number, 0.0),
}
_SHAPES: dict[str, tuple[type, dict[str, tuple]]] = {
    "open-box": (OpenBox, {"min": (_vec3, _REQ), "max": (_vec3, _REQ),
                           "thickness": (_number, _REQ), "open": (_faces, ())}),
    "sphere": (Sphere, {"center": (_vec3, _REQ), "radius": (_number, _REQ)}),
    "torus": (Torus, {"center": (_vec3, _REQ), "major_radius": (_number, _REQ),
                      "minor_radius": (_number, _REQ), "axis": (_vec3, (0.0, 0.0, 1.0))}),
    "box": (Box, {"min": (_vec3, _REQ), "max": (_vec3, _REQ)}),
    "quad": (Quad, {"corners": (_corners, _REQ)}),
    "mesh": (Mesh, {"path": (_string, _REQ), "scale": (_number, 1.0),
                    "translate": (_vec3, (0.0, 0.0, 0.0))}),
}

_CAMERA_COMMON = {
    "name": (_string, None),
    "kind": (_string, _REQ),
    "position": (_vec3, _REQ),
    "look_at": (_vec3, _REQ),
    "up": (_vec3, (0.0, 0.0, 1.0)),
    "resolution": (_resolution, _REQ),
}
_CAMERAS = {
    "perspective": {"fov_deg": (_number, _REQ)},
    "orthographic": {"extent": (_vec2, _REQ)},
}

_TOP_KEYS = ("title", "domain", "fog", "sun", "sky", "shape", "camera")
# fields a --set may not change (identity, files)
_FIXED = ("name", "kind", "path", "density")



def _read_fields(raw: dict, spec: dict[str, tuple], at: _At, what: str,
                 elsewhere: dict[str, str] | None = None) -> dict[str, Any]:
    """Check keys (unknown, missing) and convert every value of one table."""
    for k in raw:
        if k not in spec:
            hint = (elsewhere or {}).get(k) or _suggest(k, spec).strip()
            raise at(None, _UNSET, f"has an unknown key '{k}'. {hint + ' ' if hint else ''}"
                                   f"The keys of {what} are: {', '.join(spec)}.")
    out = {}
    for k, (conv, default) in spec.items():
        if k in raw:
            out[k] = conv(raw[k], at, k)
        elif default is _REQ:
            raise at(None, _UNSET, f"is missing the required key '{k}'; add {k} = ... "
                                   f"(the keys of {what} are: {', '.join(spec)})")
        else:
            out[k] = default
    return out



# --------------------------------------------------------------------------- files


def _rel_file(base, rel: str, at: _At, field: str, what: str):
    """The file ``rel`` next to the scene file (a Path or an importlib Traversable)."""
    if base is None:
        raise at(field, rel, "cannot be found: the scene has no file to take relative paths from")
    p = Path(rel)
    target = p if p.is_absolute() else base.joinpath(rel)
    try:
        ok = target.is_file()
    except OSError:
        ok = False
    if not ok:
        raise at(field, rel, f"names no readable file (looked for {target}); put the {what} "
                             "there or fix the path, which is relative to the scene file")
    return target


def _load_density(base, rel: str, at: _At) -> np.ndarray:
    target = _rel_file(base, rel, at, "density", "density grid")
    fix = "save it with numpy.savez(path, density=grid) (float32 grid indexed [ix, iy, iz])"
    try:
        data = target.read_bytes()
    except OSError as e:
        raise at("density", rel, f"cannot be read ({e.strerror or e})") from None
    if data.startswith(b"\x93NUMPY"):
        raise at("density", rel, f"is a single .npy array, not an .npz archive; {fix}")
    if not data.startswith(b"PK"):
        raise at("density", rel, f"is not an .npz archive (not a zip file); {fix}")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            if "density" not in z.files:
                raise at("density", rel, f"holds no array 'density' (it has: "
                                         f"{', '.join(z.files) or 'nothing'}); {fix}")
            a = z["density"]
    except SceneError:
        raise
    except Exception as e:  # noqa: BLE001 - anything NumPy or zipfile says about a bad file
        raise at("density", rel, f"could not be read as an .npz archive ({type(e).__name__}: "
                                 f"{e}); {fix}") from None
    return check_grid(a, at, rel)


def check_grid(a, at: _At, shown) -> np.ndarray:
    """A density grid checked and converted to float32: 3-D, floats, finite, >= 0.  ``shown``
    is what the message calls it (the file's path, or the array)."""
    fix = "save it with numpy.savez(path, density=grid) (float32 grid indexed [ix, iy, iz])"
    rel = shown
    a = np.asarray(a)
    if a.ndim != 3 or min(a.shape) < 1:
        raise at("density", rel, f"grid has shape {a.shape}; it must be a non-empty 3-D array "
                                 f"indexed [ix, iy, iz]; {fix}")
    if not np.issubdtype(a.dtype, np.floating):
        raise at("density", rel, f"grid has dtype {a.dtype}; it must hold floats (float32); "
                                 f"convert it with grid.astype(numpy.float32)")
    with np.errstate(over="ignore"):
        a = a.astype(np.float32)
    bad = ~np.isfinite(a)
    if bad.any():
        i = tuple(int(x) for x in np.argwhere(bad)[0])
        raise at("density", rel, f"grid has {int(bad.sum())} NaN or Inf values (or values too "
                                 f"large for float32), the first at index {list(i)}; replace them "
                                 "with finite values >= 0")
    if (a < 0).any():
        i = tuple(int(x) for x in np.argwhere(a < 0)[0])
        raise at("density", rel, f"grid has {int((a < 0).sum())} negative values (minimum "
                                 f"{float(a.min()):.6g} at index {list(i)}); a density multiplier "
                                 "must be >= 0")
    return a


def _load_mesh(base, rel: str, at: _At) -> tuple[np.ndarray, np.ndarray]:
    import trimesh  # slow import; only scenes with meshes need it

    target = _rel_file(base, rel, at, "path", "mesh")
    ext = Path(rel).suffix.lower().lstrip(".")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if isinstance(target, Path):
                m = trimesh.load(str(target), force="mesh")
            else:
                m = trimesh.load(io.BytesIO(target.read_bytes()), file_type=ext, force="mesh")
    except Exception as e:  # noqa: BLE001 - trimesh raises many kinds
        raise at("path", rel, f"could not be read as a mesh ({type(e).__name__}: {e}); use a "
                              f"format trimesh loads: "
                              f"{', '.join(sorted(trimesh.available_formats()))}") from None
    if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
        raise at("path", rel, "contains no triangles (is it empty or not a mesh file?); export the "
                              "closed mesh again, e.g. as .obj, .stl or .ply")
    return _closed_mesh(m, at, "path", rel, "is")


def _closed_mesh(m, at: _At, field: str, value, verb: str) -> tuple[np.ndarray, np.ndarray]:
    """The vertices and faces of a trimesh mesh that must be closed (watertight), its normals
    turned outwards if they are not (a file's or a Python-built Mesh's arrays alike)."""
    import trimesh

    if not m.is_watertight:
        from trimesh.grouping import group_rows

        edges = m.edges_sorted
        boundary = len(group_rows(edges, require_count=1))
        _, counts = np.unique(edges, axis=0, return_counts=True)
        nonmanifold = int((counts > 2).sum())
        raise at(field, value, f"{verb} not watertight: {boundary} boundary edges (used by one "
                               f"face) and {nonmanifold} non-manifold edges (used by more than "
                               "two). A mesh must be a closed surface around a solid; close its "
                               "holes (e.g. trimesh.repair.fill_holes) or describe a thin surface "
                               "with quads")
    if not (m.is_winding_consistent and m.is_volume):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            trimesh.repair.fix_normals(m)
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


# --------------------------------------------------------------------------- validation


def _bounds(s) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(s, Sphere):
        c = np.asarray(s.center)
        return c - s.radius, c + s.radius
    if isinstance(s, Torus):
        a = np.asarray(s.axis) / np.linalg.norm(s.axis)
        h = s.major_radius * np.sqrt(np.clip(1 - a * a, 0, 1)) + s.minor_radius
        return np.asarray(s.center) - h, np.asarray(s.center) + h
    if isinstance(s, (Box, OpenBox)):
        return np.asarray(s.min), np.asarray(s.max)
    if isinstance(s, Quad):
        c = np.asarray(s.corners)
        return c.min(0), c.max(0)
    v = s.vertices
    return v.min(0), v.max(0)


def _check_min_max(lo, hi, at: _At, what: str) -> None:
    for ax in range(3):
        if not lo[ax] < hi[ax]:
            raise at("min", lo, f"is not below max = {_fmt(hi)} on the {'xyz'[ax]} axis "
                                f"({lo[ax]:g} >= {hi[ax]:g}); every component of min must be "
                                f"smaller than max for {what}")


def _check_range(v: float, at: _At, f: str, lo=None, hi=None, lo_open=False, hi_open=False,
                 why: str = "") -> None:
    ok = True
    if lo is not None:
        ok &= v > lo if lo_open else v >= lo
    if hi is not None:
        ok &= v < hi if hi_open else v <= hi
    if not ok:
        if hi is None:
            rng = f"> {lo:g}" if lo_open else f">= {lo:g}"
        else:
            rng = ("(" if lo_open else "[") + f"{lo:g}, {hi:g}" + (")" if hi_open else "]")
            rng = f"in {rng}"
        raise at(f, v, f"must be {rng}{'; ' + why if why else ''}")


def _check_choice(v: str, options: tuple, at: _At, f: str, what: str) -> None:
    _string(v, at, f)
    if v not in options:
        raise at(f, v, f"is not a known {what}.{_suggest(v, options, chr(34))} "
                       f"Use one of: {', '.join(_fmt(o) for o in options)}.")


def _check_name(name: str, at: _At, what: str) -> None:
    _string(name, at, "name")
    if not _NAME_RE.fullmatch(name):
        raise at("name", name, f"cannot name a {what}: --set and fits refer to it as "
                               f"{what}.<name>.<field>, so use letters, digits, '-' or '_' "
                               "(no dots, spaces, quotes, brackets or '=')")


def _check_quad(q: Quad, at: _At) -> None:
    c = np.asarray(q.corners, dtype=float)
    size = max(np.linalg.norm(c[i] - c[j]) for i in range(4) for j in range(i))
    fix = ("give 4 distinct corners of a flat convex quadrilateral, counter-clockwise seen from "
           "the lit side")
    if size == 0:
        raise at("corners", q.corners, f"all coincide (zero area); {fix}")
    centred = c - c.mean(0)
    _, sv, vt = np.linalg.svd(centred)
    if sv[1] <= 1e-9 * size:
        raise at("corners", q.corners, f"lie on one line (zero area); {fix}")
    n = vt[2]
    off = np.abs(centred @ n)
    if off.max() > 1e-3 * size:
        raise at("corners", q.corners, f"are not planar: they lie up to {off.max():.3g} off "
                                        f"their best-fit plane (tolerance {1e-3 * size:.3g}, "
                                        f"1e-3 of the quad's size); {fix}")
    for i in range(4):
        if np.linalg.norm(c[(i + 1) % 4] - c[i]) <= 1e-9 * size:
            raise at("corners", q.corners, f"has corners {i} and {(i + 1) % 4} at the same "
                                            f"point; {fix}")
    turns = [np.cross(c[(i + 1) % 4] - c[i], c[(i + 2) % 4] - c[(i + 1) % 4]) @ n for i in range(4)]
    if not (all(t > 1e-9 * size**2 for t in turns) or all(t < -1e-9 * size**2 for t in turns)):
        raise at("corners", q.corners, "do not go around a convex quadrilateral in this order (the "
                                        f"outline crosses itself or bends inwards); {fix}")


def _check_camera(c: Camera, at: _At) -> None:
    _check_choice(c.kind, tuple(_CAMERAS), at, "kind", "camera kind")
    # the other kind's field (in a file, the loader's "unknown key")
    other, own, kind = (("extent", "fov_deg", "orthographic") if c.kind == "perspective"
                        else ("fov_deg", "extent", "perspective"))
    if getattr(c, other) is not None:
        raise at(other, getattr(c, other), f"is for {kind} cameras; {_a(c.kind)} camera takes "
                                           f"{own} instead (remove {other} or set kind = "
                                           f"{_fmt(kind)})")
    w, h = c.resolution
    if w <= 0 or h <= 0:
        raise at("resolution", list(c.resolution), "must be positive whole numbers [width, height]")
    d = np.asarray(c.look_at) - np.asarray(c.position)
    if np.linalg.norm(d) <= 1e-12:
        raise at("look_at", c.look_at, "is the camera's position, so it has no view direction; "
                                       "move look_at to the point the camera should aim at")
    up = np.asarray(c.up)
    if np.linalg.norm(up) == 0:
        raise at("up", c.up, "has zero length; give the direction that is up in the image, "
                             "e.g. [0, 0, 1]")
    d = d / np.linalg.norm(d)
    if np.linalg.norm(np.cross(d, up / np.linalg.norm(up))) < 1e-6:
        raise at("up", c.up, f"is parallel to the view direction {_fmt(d.round(6))},"
                             " so the image has no defined orientation; pick an up vector across "
                             "the view, e.g. [0, 1, 0] for a camera looking straight down")
    if c.kind == "perspective":
        _check_range(c.fov_deg, at, "fov_deg", 0, 180, True, True,
                     "it is the full horizontal field of view in degrees")
    else:
        ex = c.extent
        if ex[0] <= 0 or ex[1] <= 0:
            raise at("extent", list(ex), "must be positive [width, height] of the view window in "
                                         "scene units")




# --------------------------------------------------------------------------- where a value sits

_WHERE: contextvars.ContextVar[_At | None] = contextvars.ContextVar("difffog_scene_where",
                                                                   default=None)


@contextlib.contextmanager
def located(at: _At):
    """Objects constructed inside this block report problems at ``at`` (the loader's file and
    table) instead of as Python constructors."""
    token = _WHERE.set(at)
    try:
        yield
    finally:
        _WHERE.reset(token)


def _where(obj, default_table: str = "") -> _At:
    at = _WHERE.get()
    if at is not None:
        return at
    name = getattr(obj, "name", None) or getattr(obj, "title", None)
    return _At(f"difffog.{type(obj).__name__}({name!r})" if name
               else f"difffog.{type(obj).__name__}", default_table)


def _convert(obj, spec: dict[str, tuple], at: _At, skip=()) -> None:
    """Convert the fields of a frozen dataclass in place with the spec's converters (lists,
    tuples and arrays become tuples of floats, numbers floats), None left alone where the
    spec allows it (default None) and an error where the field needs a value."""
    for name, (conv, default) in spec.items():
        if name in skip or not hasattr(obj, name):
            continue
        v = getattr(obj, name)
        if v is None:
            if default is None:
                continue
            raise at(name, _UNSET, f"is None, but it needs a value; pass {name}=...")
        object.__setattr__(obj, name, conv(v, at, name))


_KIND_OF = {cls: kind for kind, (cls, _) in _SHAPES.items()}
_UNNAMED = "<unnamed>"


# --------------------------------------------------------------------------- per object


_DEFER: contextvars.ContextVar[bool] = contextvars.ContextVar("difffog_scene_defer",
                                                             default=False)


@contextlib.contextmanager
def deferred():
    """Objects constructed inside this block are not checked (``--set`` applies several
    changes, whose intermediate states need not be valid); call :func:`validate_scene` on the
    result."""
    token = _DEFER.set(True)
    try:
        yield
    finally:
        _DEFER.reset(token)


def validate_scene(scene: Scene, origin: str) -> None:
    """Check every object of ``scene`` again, reporting problems at ``origin`` and the
    object's table (what the loader and ``--set`` do for the finished scene)."""
    for table in ("domain", "fog", "sun", "sky"):
        obj = getattr(scene, table)
        if obj is not None:
            with located(_At(origin, f"[{table}]")):
                check(obj)
    for i, sh in enumerate(scene.shapes, start=1):
        with located(_At(origin, _shape_label(i, sh.name))):
            check(sh)
    for i, cam in enumerate(scene.cameras, start=1):
        with located(_At(origin, _camera_label(i, cam.name))):
            check(cam)
    with located(_At(origin, "")):
        check(scene)


def check(obj) -> None:
    """Convert and validate one scene object (called by its ``__post_init__``)."""
    if _DEFER.get():
        return
    at = _where(obj)
    if isinstance(obj, Domain):
        _convert(obj, _TABLES["domain"], at)
        _check_choice(obj.boundary, _BOUNDARIES, at, "boundary", "boundary")
        _check_min_max(obj.min, obj.max, at, "the domain")
    elif isinstance(obj, Fog):
        _convert(obj, _TABLES["fog"], at, skip=("density",))
        for f in ("scattering", "absorption"):
            _check_range(getattr(obj, f), at, f, 0, why="it is a coefficient per unit length")
        _check_choice(obj.phase, _PHASES, at, "phase", "phase function")
        if obj.phase == "henyey-greenstein":
            if obj.g is None:
                raise at(None, _UNSET, "has phase = \"henyey-greenstein\" but no g; add g = ... "
                                       "in (-1, 1) (0 is isotropic, > 0 forward scattering)")
            _check_range(obj.g, at, "g", -1, 1, True, True,
                         "0 is isotropic, > 0 forward, < 0 backward scattering")
        elif obj.g not in (None, 0.0):
            raise at("g", obj.g, 'has no effect with phase = "isotropic"; set phase = '
                                 '"henyey-greenstein" or remove g')
        if obj.g is None:
            object.__setattr__(obj, "g", 0.0)
        if obj.region is not None:
            _check_min_max(obj.region[0], obj.region[1], _At(at.origin, f"{at.table}.region"
                           if at.table else "region"), "the fog region")
        if obj.density is not None:
            shown = obj.density_path or "the density array"
            object.__setattr__(obj, "density", check_grid(obj.density, at, shown))
        elif obj.density_path is not None:
            object.__setattr__(obj, "density", _load_density(Path.cwd(), obj.density_path, at))
    elif isinstance(obj, Sun):
        _convert(obj, _TABLES["sun"], at)
        _check_range(obj.irradiance, at, "irradiance", 0)
        _check_range(obj.zenith_deg, at, "zenith_deg", 0, 180,
                     why="it is the angle in degrees between +z and the direction towards the sun")
        _check_range(obj.angular_radius_deg, at, "angular_radius_deg", 0, 90, hi_open=True,
                     why="0 is a point sun; the real sun's is about 0.27")
    elif isinstance(obj, Sky):
        _convert(obj, _TABLES["sky"], at)
        _check_range(obj.radiance, at, "radiance", 0)
    elif isinstance(obj, Camera):
        _convert(obj, {**_CAMERA_COMMON, **_CAMERAS.get(obj.kind, {})}, at, skip=("name",
                                                                                     "kind"))
        if obj.name:
            _check_name(obj.name, at, "camera")
        _check_camera(obj, at)
    elif type(obj) in _KIND_OF:
        _check_shape(obj, at)
    elif isinstance(obj, Scene):
        _check_scene(obj)
    else:  # pragma: no cover - every scene class is listed above
        raise TypeError(type(obj).__name__)


def _check_shape(sh, at: _At) -> None:
    kind = _KIND_OF[type(sh)]
    if sh.kind != kind:
        raise at("kind", sh.kind, f"is not the kind of a difffog.{type(sh).__name__}, which is "
                                  f"{_fmt(kind)}; leave kind out")
    _convert(sh, {**_SHAPE_COMMON, **_SHAPES[kind][1]}, at, skip=("name", "kind", "path"))
    if sh.name:
        _check_name(sh.name, at, "shape")
    _check_range(sh.albedo, at, "albedo", 0, 1, why="it is the Lambertian reflectance")
    _check_range(sh.emission, at, "emission", 0, why="it is an emitted radiance")
    if isinstance(sh, Sphere):
        _check_range(sh.radius, at, "radius", 0, lo_open=True)
    elif isinstance(sh, Torus):
        _check_range(sh.major_radius, at, "major_radius", 0, lo_open=True)
        _check_range(sh.minor_radius, at, "minor_radius", 0, lo_open=True)
        if sh.minor_radius >= sh.major_radius:
            raise at("minor_radius", sh.minor_radius, f"must be < major_radius = "
                     f"{sh.major_radius:g}: a torus without a hole intersects itself; make it "
                     "thinner or use a sphere")
        n = float(np.linalg.norm(sh.axis))
        if n == 0:
            raise at("axis", sh.axis, "has zero length; give the ring's axis, e.g. [0, 0, 1]")
        object.__setattr__(sh, "axis", tuple(x / n for x in sh.axis))
    elif isinstance(sh, (Box, OpenBox)):
        _check_min_max(sh.min, sh.max, at, f"a {kind}")
        if isinstance(sh, OpenBox):
            for face in sh.open:
                if face not in FACES:
                    raise at("open", list(sh.open), f"names {_fmt(face)}, which is not a face."
                             f"{_suggest(face, FACES, chr(34))} Faces are "
                             f"{', '.join(_fmt(x) for x in FACES)}.")
            dup = sorted({x for x in sh.open if sh.open.count(x) > 1})
            if dup:
                raise at("open", list(sh.open), f"lists {_fmt(dup)} more than once; list each "
                                                "open face once")
            if len(set(sh.open)) == 6:
                raise at("open", list(sh.open), "opens all six faces, so the open-box has no "
                                                "walls; close a face or remove the shape")
            side = min(b - a for a, b in zip(sh.min, sh.max))
            _check_range(sh.thickness, at, "thickness", 0, lo_open=True,
                         why="the walls need a thickness")
            if 2 * sh.thickness >= side:
                raise at("thickness", sh.thickness, f"must be < {side / 2:g}, half the box's "
                         f"smallest side ({side:g}), or the walls leave no inside")
    elif isinstance(sh, Quad):
        _check_quad(sh, at)
    elif isinstance(sh, Mesh):
        _check_range(sh.scale, at, "scale", 0, lo_open=True,
                     why="a zero or negative scale collapses or turns the mesh inside out")
        if sh.vertices is None or sh.faces is None:
            if not sh.path:
                raise at("path", sh.path, "is empty: give a mesh file (path=...) or vertices "
                                          "and faces arrays")
            v, f = _load_mesh(Path.cwd(), sh.path, at)
            object.__setattr__(sh, "vertices", v * sh.scale + np.asarray(sh.translate))
            object.__setattr__(sh, "faces", f)
        else:
            v = np.asarray(sh.vertices, np.float64)
            f = np.asarray(sh.faces)
            if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 \
                    or not np.issubdtype(f.dtype, np.integer) or f.min() < 0 \
                    or f.max() >= len(v) or not np.all(np.isfinite(v)):
                raise at("vertices", _UNSET, "and faces must be (V, 3) finite floats and (F, 3) "
                                             "vertex indices; give a closed triangle mesh")
            import trimesh

            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                m = trimesh.Trimesh(v, f)  # merges duplicate vertices, as loading a file does
            v, f = _closed_mesh(m, at, "vertices and faces", _UNSET, "are")
            object.__setattr__(sh, "vertices", v)
            object.__setattr__(sh, "faces", f)


def _shape_label(i: int, name: str | None) -> str:
    return f"[[shape]] #{i}" + (f" '{name}'" if name else "")


def _camera_label(i: int, name: str | None) -> str:
    return f"[[camera]] #{i}" + (f" '{name}'" if name else "")


def _check_scene(scene: Scene) -> None:
    """What involves several objects: names (unnamed shapes and cameras get ``<kind>-<n>`` /
    ``camera-<n>``), unique names, and shapes and the fog region inside the domain."""
    base = _WHERE.get()
    origin = base.origin if base is not None else (
        f"difffog.Scene({scene.title!r})" if scene.title else "difffog.Scene")
    _string(scene.title, _At(origin, ""), "title")
    for field, cls in (("domain", Domain), ("fog", Fog), ("sun", Sun), ("sky", Sky)):
        v = getattr(scene, field)
        if (v is None and field != "domain") or isinstance(v, cls):
            continue
        raise SceneError(f"{origin}: {field} must be a difffog.{cls.__name__}"
                         f"{'' if field == 'domain' else ' or None'}, got {type(v).__name__}")
    shapes = tuple(scene.shapes)
    for i, sh in enumerate(shapes, start=1):
        if type(sh) not in _KIND_OF:
            raise SceneError(f"{origin}: shapes[{i - 1}] is a {type(sh).__name__}, not a shape "
                             f"(difffog.{', difffog.'.join(c.__name__ for c in _KIND_OF)})")
    named = tuple(sh if sh.name else dataclasses.replace(sh, name=f"{_KIND_OF[type(sh)]}-{i}")
                  for i, sh in enumerate(shapes, start=1))
    for i, c in enumerate(scene.cameras, start=1):
        if not isinstance(c, Camera):
            raise SceneError(f"{origin}: cameras[{i - 1}] is a {type(c).__name__}, not a "
                             "difffog.Camera")
    cams = tuple(c if c.name else dataclasses.replace(c, name=f"camera-{i}")
                 for i, c in enumerate(scene.cameras, start=1))
    object.__setattr__(scene, "shapes", named)
    object.__setattr__(scene, "cameras", cams)
    d = scene.domain
    dlo, dhi = np.asarray(d.min), np.asarray(d.max)
    f = scene.fog
    if f is not None and f.region is not None:
        if np.any(np.asarray(f.region[0]) > dhi) or np.any(np.asarray(f.region[1]) < dlo):
            rat = _At(origin, "[fog].region")
            raise rat("min", f.region[0], f"and max = {_fmt(f.region[1])} lie entirely outside "
                                          f"the domain {_fmt(d.min)}..{_fmt(d.max)}; move the "
                                          "region into the domain")
    seen: dict[str, int] = {}
    for i, sh in enumerate(named, start=1):
        at = _At(origin, _shape_label(i, sh.name))
        if sh.name in seen:
            raise at("name", sh.name, f"is already used by [[shape]] #{seen[sh.name]}; give each "
                                      "shape a unique name (unnamed shapes are called "
                                      "<kind>-<number>)")
        seen[sh.name] = i
        lo, hi = _bounds(sh)
        if np.any(lo > dhi) or np.any(hi < dlo):
            raise at(None, _UNSET, f"lies entirely outside the domain {_fmt(d.min)}.."
                                   f"{_fmt(d.max)} (its bounds are {_fmt(lo.round(6))}.."
                                   f"{_fmt(hi.round(6))}); move it into the domain or enlarge "
                                   "[domain]")
    seen = {}
    for i, c in enumerate(cams, start=1):
        at = _At(origin, _camera_label(i, c.name))
        if c.name in seen:
            raise at("name", c.name, f"is already used by [[camera]] #{seen[c.name]}; give each "
                                     "camera a unique name")
        seen[c.name] = i
