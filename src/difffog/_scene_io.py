"""Read scene files (schema v1), validate them, and apply ``--set PATH=VALUE`` overrides.

Public functions: :func:`load_scene`, :func:`apply_overrides`, :func:`builtin_scenes`,
:func:`scalar_paths`.  Every problem with the input raises one :class:`SceneError` whose message
names the file, the table and field (``[[shape]] #2 'ball-high'.radius``), the bad value and the
fix; errors of tomllib, NumPy and trimesh are wrapped, never passed on.

Choices where SCHEMA.md leaves room (beyond it, the loader accepts more, never less):

* Defaults: ``boundary = "open"``; ``fog.absorption = 0``, ``fog.phase = "isotropic"``;
  ``sun.azimuth_deg = 0``, ``sun.angular_radius_deg = 0`` (point sun); shape ``albedo = 0.5``,
  ``emission = 0``; torus ``axis = [0, 0, 1]``; open-box ``open = []``; mesh ``scale = 1``,
  ``translate = [0, 0, 0]``; camera ``up = [0, 0, 1]``.  Unnamed shapes are called
  ``<kind>-<n>`` and unnamed cameras ``camera-<n>``, n counting tables from 1 as messages do.
* ``phase = "henyey-greenstein"`` requires ``g`` in (-1, 1); a non-zero ``g`` with an isotropic
  phase is an error (it would be silently ignored).
* A torus needs ``0 < minor_radius < major_radius``: a horn or spindle torus has no hole and its
  surface intersects itself, which surface-based renderers (the references) get wrong.  The
  axis is stored normalised.
* An open-box needs ``0 < thickness < (smallest side) / 2`` and at least one closed face.
* A quad must be convex, planar within 1e-3 of its size, with non-zero area, its corners in
  order around it.
* A mesh must be *closed*: a mesh that trimesh reports as not watertight is rejected with the
  number of boundary edges (edges with one face) and non-manifold edges (more than two faces),
  since the solver needs an inside; a thin surface is a ``quad``.  A closed mesh with
  inconsistent or inward winding is repaired (``trimesh.repair.fix_normals``).  The shared
  meshes (airplane.obj, ring.obj) are watertight as they are.  Scale is about the origin, then
  translate; ``scale`` must be > 0.
* The density grid may be any float dtype (stored as float32), must be 3-D, finite, >= 0.
* Shapes may stick out of the domain but not lie entirely outside it; the same for fog.region.
* Scenes need a ``[domain]``; lights, fog, shapes and cameras are all optional.

Overrides change one scalar (number, string or boolean) each; the valid paths of a scene are
:func:`scalar_paths`.  Setting a field of an absent table creates it from these defaults:
``[fog]`` scattering 0, absorption 0, isotropic; ``[sun]`` irradiance 0, zenith 0, azimuth 0;
``[sky]`` radiance 0.  Setting ``fog.g`` switches the phase to Henyey-Greenstein; setting
``fog.phase = "isotropic"`` resets ``g`` to 0.  Setting a mesh's ``scale`` re-transforms its
vertices.  The result is re-validated as a file is.
"""

from __future__ import annotations

import dataclasses
import difflib
import io
import math
import os
import re
import tomllib
import warnings
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from ._errors import SceneError
from ._scene import (FACES, Box, Camera, Domain, Fog, Mesh, OpenBox, Quad, Scene, Sky, Sphere,
                     Sun, Torus)

__all__ = ["load_scene", "apply_overrides", "builtin_scenes", "scalar_paths"]

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
        return SceneError(f"{self.origin}: {head} {problem}")


# --------------------------------------------------------------------------- value converters
# Each takes (value, at, field) and returns the Python value or raises SceneError.


def _number(v, at: _At, f: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise at(f, v, f"must be a number, not {_type_name(v)} (write numbers without quotes, "
                       "e.g. 1.0)")
    try:
        x = float(v)
    except OverflowError:
        x = math.inf
    if not math.isfinite(x):
        raise at(f, v, "must be a finite number")
    return x


def _string(v, at: _At, f: str) -> str:
    if not isinstance(v, str):
        raise at(f, v, f"must be a string, not {_type_name(v)}; write it in quotes, "
                       f'e.g. {f} = "..."')
    return v


def _vector(n: int, what: str) -> Callable:
    def conv(v, at: _At, f: str) -> tuple[float, ...]:
        if not isinstance(v, list) or len(v) != n or any(
            isinstance(x, bool) or not isinstance(x, (int, float)) for x in v
        ):
            got = f"{len(v)} items" if isinstance(v, list) else _type_name(v)
            raise at(f, v, f"must be a list of {n} numbers {what}, got {got}")
        out = tuple(float(x) for x in v)
        if not all(math.isfinite(x) for x in out):
            raise at(f, v, "must contain finite numbers only")
        return out

    return conv


_vec3 = _vector(3, "[x, y, z]")
_vec2 = _vector(2, "[width, height]")


def _resolution(v, at: _At, f: str) -> tuple[int, int]:
    if not isinstance(v, list) or len(v) != 2 or any(
        isinstance(x, bool) or not isinstance(x, int) for x in v
    ):
        raise at(f, v, "must be two whole numbers [width, height] of pixels, e.g. [160, 120]")
    return (int(v[0]), int(v[1]))


def _faces(v, at: _At, f: str) -> tuple[str, ...]:
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
        raise at(f, v, f"must be a list of face names among {_fmt(list(FACES))}")
    return tuple(v)


def _corners(v, at: _At, f: str):
    if not isinstance(v, list) or len(v) != 4:
        got = f"{len(v)} points" if isinstance(v, list) else _type_name(v)
        raise at(f, v, f"must be 4 points [[x, y, z], ...] counter-clockwise seen from the lit "
                       f"side, got {got}")
    return tuple(_vec3(c, at, f"{f}[{i}]") for i, c in enumerate(v))


def _region(v, at: _At, f: str):
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


def _spec(table: str, kind: str | None = None) -> dict[str, tuple]:
    if table == "shape":
        return {**_SHAPE_COMMON, **_SHAPES[kind][1]}
    if table == "camera":
        return {**_CAMERA_COMMON, **_CAMERAS[kind]}
    return _TABLES[table]


def _scalar_fields(spec: dict[str, tuple], numeric: bool = False) -> list[str]:
    ok = (_number,) if numeric else _SCALAR_CONVERTERS
    return [k for k, (conv, _) in spec.items() if conv in ok and k not in _FIXED]


def scalar_paths(scene: Scene, numeric: bool = False) -> list[str]:
    """Every dotted path that ``--set`` (and a fit) may change in this scene.

    ``numeric=True`` keeps the numbers only (drops ``domain.boundary`` and ``fog.phase``).
    Paths of absent tables (``fog.*``, ``sun.*``, ``sky.*``) are included: setting one
    creates the table (see the module docstring).
    """
    out = []
    for t in ("domain", "fog", "sun", "sky"):
        out += [f"{t}.{k}" for k in _scalar_fields(_TABLES[t], numeric)]
    for s in scene.shapes:
        out += [f"shape.{s.name}.{k}" for k in _scalar_fields(_spec("shape", s.kind), numeric)]
    for c in scene.cameras:
        out += [f"camera.{c.name}.{k}" for k in _scalar_fields(_spec("camera", c.kind), numeric)]
    return out


# --------------------------------------------------------------------------- reading tables


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


def _shape_label(i: int, name: str | None) -> str:
    return f"[[shape]] #{i}" + (f" '{name}'" if name else "")


def _camera_label(i: int, name: str | None) -> str:
    return f"[[camera]] #{i}" + (f" '{name}'" if name else "")


def _kind_of(raw: dict, known: Iterable[str], at: _At, what: str) -> str:
    if "kind" not in raw:
        raise at(None, _UNSET, f"is missing the required key 'kind'; add kind = \"...\", one of "
                               f"{', '.join(known)}")
    kind = _string(raw["kind"], at, "kind")
    if kind not in known:
        raise at("kind", kind, f"is not a known {what} kind.{_suggest(kind, known, chr(34))} "
                               f"Known kinds: {', '.join(known)}.")
    return kind


def _build(raw: dict, origin: str, base, source: Path | None, stem: str) -> Scene:
    top = _At(origin, "")
    for k in raw:
        if k not in _TOP_KEYS:
            hint = _suggest(k, _TOP_KEYS)
            raise SceneError(f"{origin}: unknown table or key '{k}' at the top level.{hint} "
                             "Schema v1 has: title, [domain], [fog], [sun], [sky], [[shape]], "
                             "[[camera]].")
    title = _string(raw["title"], top, "title") if "title" in raw else stem

    tables: dict[str, dict | None] = {}
    for t in ("domain", "fog", "sun", "sky"):
        v = raw.get(t)
        if v is not None and not isinstance(v, dict):
            raise SceneError(f"{origin}: '{t}' must be a single table [{t}], not {_type_name(v)}; "
                             f"write it as [{t}] followed by its keys")
        at = _At(origin, f"[{t}]")
        tables[t] = None if v is None else _read_fields(v, _TABLES[t], at, f"[{t}]")
    if tables["domain"] is None:
        raise SceneError(f"{origin}: the [domain] table is missing; add [domain] with "
                         "min = [x, y, z], max = [x, y, z] (the box the lattice covers)")
    domain = Domain(**tables["domain"])

    fog = None
    if (f := tables["fog"]) is not None:
        at = _At(origin, "[fog]")
        g = f.pop("g")
        if f["phase"] == "henyey-greenstein" and g is None:
            raise at(None, _UNSET, "has phase = \"henyey-greenstein\" but no g; add g = ... in "
                                   "(-1, 1) (0 is isotropic, > 0 forward scattering)")
        if f["phase"] == "isotropic" and g not in (None, 0.0):
            raise at("g", g, 'has no effect with phase = "isotropic"; set phase = '
                             '"henyey-greenstein" or remove g')
        rel = f.pop("density")
        grid = None if rel is None else _load_density(base, rel, at)
        fog = Fog(**f, g=g or 0.0, density_path=rel, density=grid)
    sun = Sun(**tables["sun"]) if tables["sun"] is not None else None
    sky = Sky(**tables["sky"]) if tables["sky"] is not None else None

    shapes = []
    for i, s in enumerate(_array_of_tables(raw, "shape", origin), start=1):
        name = s.get("name") if isinstance(s.get("name"), str) else None
        at = _At(origin, _shape_label(i, name))
        kind = _kind_of(s, _SHAPES, at, "shape")
        others = {k: f"'{k}' belongs to {_a(kk)} shape, not {_a(kind)}."
                  for kk, (_, sp) in _SHAPES.items() for k in sp if kk != kind}
        kw = _read_fields(s, _spec("shape", kind), at, f"{_a(kind)} shape", others)
        kw["name"] = kw["name"] if kw["name"] is not None else f"{kind}-{i}"
        del kw["kind"]
        if kind == "torus" and (n := float(np.linalg.norm(kw["axis"]))) > 0:
            kw["axis"] = tuple(x / n for x in kw["axis"])  # a zero axis is reported by _validate
        if kind == "mesh":
            v, fc = _load_mesh(base, kw["path"], at)
            kw["vertices"] = v * kw["scale"] + np.asarray(kw["translate"])
            kw["faces"] = fc
        shapes.append(_SHAPES[kind][0](**kw))

    cameras = []
    for i, c in enumerate(_array_of_tables(raw, "camera", origin), start=1):
        name = c.get("name") if isinstance(c.get("name"), str) else None
        at = _At(origin, _camera_label(i, name))
        kind = _kind_of(c, _CAMERAS, at, "camera")
        others = {
            "fov_deg": "'fov_deg' is for perspective cameras; an orthographic camera takes "
                       "extent = [width, height] instead (or set kind = \"perspective\").",
            "extent": "'extent' is for orthographic cameras; a perspective camera takes fov_deg "
                      "instead (or set kind = \"orthographic\").",
        }
        kw = _read_fields(c, _spec("camera", kind), at, f"{_a(kind)} camera", others)
        kw["name"] = kw["name"] if kw["name"] is not None else f"camera-{i}"
        cameras.append(Camera(**kw))

    scene = Scene(title=title, domain=domain, fog=fog, sun=sun, sky=sky, shapes=tuple(shapes),
                  cameras=tuple(cameras), source=source)
    _validate(scene, origin)
    return scene


def _array_of_tables(raw: dict, key: str, origin: str) -> list[dict]:
    v = raw.get(key, [])
    if not isinstance(v, list) or not all(isinstance(x, dict) for x in v):
        raise SceneError(f"{origin}: '{key}' must be an array of tables, each one written as "
                         f"[[{key}]] followed by its keys (not [{key}] or {key} = ...)")
    return v


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
    if not m.is_watertight:
        from trimesh.grouping import group_rows

        edges = m.edges_sorted
        boundary = len(group_rows(edges, require_count=1))
        _, counts = np.unique(edges, axis=0, return_counts=True)
        nonmanifold = int((counts > 2).sum())
        raise at("path", rel, f"is not watertight: {boundary} boundary edges (used by one face) "
                              f"and {nonmanifold} non-manifold edges (used by more than two). A "
                              "mesh must be a closed surface around a solid; close its holes (e.g. "
                              "trimesh.repair.fill_holes) or describe a thin surface with quads")
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
    if v not in options:
        raise at(f, v, f"is not a known {what}.{_suggest(v, options, chr(34))} "
                       f"Use one of: {', '.join(_fmt(o) for o in options)}.")


def _check_name(name: str, at: _At, what: str) -> None:
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


def _validate(scene: Scene, origin: str) -> None:
    """Checks shared by files and overrides (types were checked when values were read)."""
    d = scene.domain
    at = _At(origin, "[domain]")
    _check_choice(d.boundary, _BOUNDARIES, at, "boundary", "boundary")
    _check_min_max(d.min, d.max, at, "the domain")
    dlo, dhi = np.asarray(d.min), np.asarray(d.max)

    if (f := scene.fog) is not None:
        at = _At(origin, "[fog]")
        _check_range(f.scattering, at, "scattering", 0, why="it is a coefficient per unit length")
        _check_range(f.absorption, at, "absorption", 0, why="it is a coefficient per unit length")
        _check_choice(f.phase, _PHASES, at, "phase", "phase function")
        if f.phase == "henyey-greenstein":
            _check_range(f.g, at, "g", -1, 1, True, True,
                         "0 is isotropic, > 0 forward, < 0 backward scattering")
        if f.region is not None:
            rat = _At(origin, "[fog].region")
            _check_min_max(f.region[0], f.region[1], rat, "the fog region")
            if np.any(np.asarray(f.region[0]) > dhi) or np.any(np.asarray(f.region[1]) < dlo):
                raise rat("min", f.region[0], f"and max = {_fmt(f.region[1])} lie entirely outside "
                                              f"the domain {_fmt(d.min)}..{_fmt(d.max)}; move the "
                                              "region into the domain")
    if (s := scene.sun) is not None:
        at = _At(origin, "[sun]")
        _check_range(s.irradiance, at, "irradiance", 0)
        _check_range(s.zenith_deg, at, "zenith_deg", 0, 180,
                     why="it is the angle in degrees between +z and the direction towards the sun")
        _check_range(s.angular_radius_deg, at, "angular_radius_deg", 0, 90, hi_open=True,
                     why="0 is a point sun; the real sun's is about 0.27")
    if scene.sky is not None:
        _check_range(scene.sky.radiance, _At(origin, "[sky]"), "radiance", 0)

    seen: dict[str, int] = {}
    for i, sh in enumerate(scene.shapes, start=1):
        at = _At(origin, _shape_label(i, sh.name))
        _check_name(sh.name, at, "shape")
        if sh.name in seen:
            raise at("name", sh.name, f"is already used by [[shape]] #{seen[sh.name]}; give each "
                                      "shape a unique name (unnamed shapes are called "
                                      "<kind>-<number>)")
        seen[sh.name] = i
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
            if np.linalg.norm(sh.axis) == 0:
                raise at("axis", sh.axis, "has zero length; give the ring's axis, e.g. [0, 0, 1]")
        elif isinstance(sh, (Box, OpenBox)):
            _check_min_max(sh.min, sh.max, at, f"a {sh.kind}")
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
        lo, hi = _bounds(sh)
        if np.any(lo > dhi) or np.any(hi < dlo):
            raise at(None, _UNSET, f"lies entirely outside the domain {_fmt(d.min)}.."
                                   f"{_fmt(d.max)} (its bounds are {_fmt(lo.round(6))}.."
                                   f"{_fmt(hi.round(6))}); move it into the domain or enlarge "
                                   "[domain]")

    seen = {}
    for i, c in enumerate(scene.cameras, start=1):
        at = _At(origin, _camera_label(i, c.name))
        _check_name(c.name, at, "camera")
        if c.name in seen:
            raise at("name", c.name, f"is already used by [[camera]] #{seen[c.name]}; give each "
                                     "camera a unique name")
        seen[c.name] = i
        _check_camera(c, at)


# --------------------------------------------------------------------------- entry points


def _scene_dir():
    return resources.files("difffog").joinpath("scenes")


def builtin_scenes() -> list[str]:
    """Names of the scenes shipped with difffog (usable wherever a scene file is)."""
    return sorted(p.name[:-5] for p in _scene_dir().iterdir() if p.name.endswith(".toml"))


def load_scene(source: str | os.PathLike, overrides: Iterable[str] = ()) -> Scene:
    """Read a scene file or a built-in scene by name, validate it, then apply ``overrides``."""
    p = Path(source)
    if p.is_file():
        origin, base, where, stem = str(source), p.absolute().parent, p.absolute(), p.stem
        try:
            data = p.read_bytes()
        except OSError as e:
            raise SceneError(f"{origin}: cannot read the scene file ({e.strerror or e}); check "
                             "its permissions") from None
    elif p.is_dir():
        raise SceneError(f"{source}: is a folder, not a scene file; give a .toml file or a "
                         f"built-in scene name ({', '.join(builtin_scenes())})")
    elif str(source) in builtin_scenes():
        t = _scene_dir().joinpath(f"{source}.toml")
        data, base, stem = t.read_bytes(), _scene_dir(), str(source)
        where = Path(str(t)) if isinstance(t, Path) else None
        origin = str(t) if isinstance(t, Path) else f"built-in scene '{source}'"
    else:
        names = builtin_scenes()
        hint = _suggest(str(source), names) or _suggest(p.stem, names)
        raise SceneError(f"{source}: no such scene file, and no built-in scene of that name.{hint} "
                         f"Built-in scenes: {', '.join(names)}.")
    try:
        raw = tomllib.loads(data.decode("utf-8"))
    except UnicodeDecodeError as e:
        raise SceneError(f"{origin}: is not UTF-8 text (bad byte at offset {e.start}); save the "
                         "scene file as UTF-8 TOML") from None
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"{origin}: is not valid TOML: {e}; fix the syntax there") from None
    scene = _build(raw, origin, base, where, stem)
    overrides = [overrides] if isinstance(overrides, str) else list(overrides)
    return _apply(scene, overrides, origin) if overrides else scene


def apply_overrides(scene: Scene, overrides: Iterable[str]) -> Scene:
    """A copy of ``scene`` with ``"PATH=VALUE"`` items applied (paths: :func:`scalar_paths`)."""
    overrides = [overrides] if isinstance(overrides, str) else list(overrides)
    origin = str(scene.source) if scene.source else f"scene '{scene.title}'"
    return _apply(scene, overrides, origin) if overrides else scene


def _parse_value(text: str) -> Any:
    """A TOML scalar; text that is not TOML (e.g. periodic-xy) is taken as a bare string."""
    if "\n" in text:
        return text
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def _unknown_path(scene: Scene, path: str, origin: str, valid: list[str]) -> SceneError:
    parts = path.split(".")
    hint, typo = "", True
    if len(parts) == 2 and parts[0] in _TABLES and parts[1] in _TABLES[parts[0]]:
        hint, typo = (f" '{parts[1]}' of [{parts[0]}] cannot be set: --set changes numbers, "
                      "strings and booleans only, and not file paths; edit the scene file."), False
    elif len(parts) == 3 and parts[0] in ("shape", "camera"):
        items = scene.shapes if parts[0] == "shape" else scene.cameras
        match = [x for x in items if x.name == parts[1]]
        if not match:
            names = [x.name for x in items]
            hint = (f" This scene has no {parts[0]} '{parts[1]}'" + (f"; its {parts[0]}s are: "
                    f"{', '.join(names)}." if names else "."))
        elif parts[2] in _spec(parts[0], match[0].kind):
            typo = False
            hint = (f" '{parts[2]}' of {parts[0]} '{parts[1]}' cannot be set: --set changes "
                    "numbers, strings and booleans only, and not name, kind or file paths.")
        else:
            hint = (f" {parts[0].capitalize()} '{parts[1]}' is of kind {match[0].kind}; it has "
                    f"no '{parts[2]}'.")
    close = difflib.get_close_matches(path, valid, n=1, cutoff=0.6) if typo else []
    hint += f" Did you mean '{close[0]}'?" if close else ""
    return SceneError(f"{origin}: --set {path}: no such setting.{hint} "
                      f"Valid paths: {', '.join(valid)}.")


def _apply(scene: Scene, overrides: list[str], origin: str) -> Scene:
    for item in overrides:
        if not isinstance(item, str) or "=" not in item:
            raise SceneError(f"{origin}: --set {item!r} is not PATH=VALUE; write e.g. "
                             "--set fog.scattering=2.5")
        path, text = (x.strip() for x in item.split("=", 1))
        valid = scalar_paths(scene)
        if path not in valid:
            raise _unknown_path(scene, path, origin, valid)
        value = _parse_value(text)
        parts = path.split(".")
        field = parts[-1]
        if parts[0] in _TABLES:
            table = parts[0]
            at = _At(f"{origin}: --set {item}", f"[{table}]")
            v = _TABLES[table][field][0](value, at, field)
            changes = {field: v}
            if table == "fog" and field == "g":
                changes["phase"] = "henyey-greenstein"
            if table == "fog" and field == "phase" and v == "isotropic":
                changes["g"] = 0.0
            obj = getattr(scene, table) or _CREATED[table]()
            scene = scene.replace(**{table: dataclasses.replace(obj, **changes)})
        else:
            group = parts[0]
            items = list(scene.shapes if group == "shape" else scene.cameras)
            i = [x.name for x in items].index(parts[1])
            label = (_shape_label if group == "shape" else _camera_label)(i + 1, parts[1])
            at = _At(f"{origin}: --set {item}", label)
            v = _spec(group, items[i].kind)[field][0](value, at, field)
            old = items[i]
            new = dataclasses.replace(old, **{field: v})
            if isinstance(old, Mesh) and field == "scale":
                if not v > 0:
                    raise at("scale", v, "must be > 0 (a zero or negative scale collapses or turns "
                                         "the mesh inside out)")
                t = np.asarray(old.translate)
                new = dataclasses.replace(new, vertices=(old.vertices - t) / old.scale * v + t)
            items[i] = new
            scene = scene.replace(**{("shapes" if group == "shape" else "cameras"): tuple(items)})
    _validate(scene, f"{origin} with --set {', --set '.join(overrides)}")
    return scene
