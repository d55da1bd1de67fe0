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
import os
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from .._errors import SceneError
from ._checks import (_CAMERAS, _CREATED, _FIXED, _SCALAR_CONVERTERS, _SHAPES,
                      _TABLES, _TOP_KEYS, _UNSET, _At, _a, _camera_label, _load_density,
                      _load_mesh, _number, _read_fields, _shape_label, _string, _suggest,
                      _type_name, deferred, located, validate_scene, _CAMERA_COMMON,
                      _SHAPE_COMMON)
from ._description import Camera, Fog, Mesh, Scene, Sky, Sun, Domain

__all__ = ["load_scene", "apply_overrides", "builtin_scenes", "scalar_paths"]


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
    with located(_At(origin, "[domain]")):
        domain = Domain(**tables["domain"])

    fog = None
    if (f := tables["fog"]) is not None:
        at = _At(origin, "[fog]")
        g = f.pop("g")
        if f["phase"] == "henyey-greenstein" and g is None:
            raise at(None, _UNSET, "has phase = \"henyey-greenstein\" but no g; add g = ... in "
                                   "(-1, 1) (0 is isotropic, > 0 forward scattering)")
        rel = f.pop("density")
        grid = None if rel is None else _load_density(base, rel, at)
        with located(at):
            fog = Fog(**f, g=g, density_path=rel, density=grid)
    with located(_At(origin, "[sun]")):
        sun = Sun(**tables["sun"]) if tables["sun"] is not None else None
    with located(_At(origin, "[sky]")):
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
        if kind == "mesh":
            v, fc = _load_mesh(base, kw["path"], at)
            kw["vertices"] = v * kw["scale"] + np.asarray(kw["translate"])
            kw["faces"] = fc
        with located(at):
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
        with located(at):
            cameras.append(Camera(**kw))

    with located(_At(origin, "")):
        return Scene(title=title, domain=domain, fog=fog, sun=sun, sky=sky, shapes=shapes,
                     cameras=cameras, source=source)


def _array_of_tables(raw: dict, key: str, origin: str) -> list[dict]:
    v = raw.get(key, [])
    if not isinstance(v, list) or not all(isinstance(x, dict) for x in v):
        raise SceneError(f"{origin}: '{key}' must be an array of tables, each one written as "
                         f"[[{key}]] followed by its keys (not [{key}] or {key} = ...)")
    return v


# --------------------------------------------------------------------------- entry points


def _scene_dir():
    return resources.files("difffog").joinpath("data", "scenes")


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
    with deferred():
        scene = _apply_each(scene, overrides, origin)
    validate_scene(scene, f"{origin} with --set {', --set '.join(overrides)}")
    return scene


def _apply_each(scene: Scene, overrides: list[str], origin: str) -> Scene:
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
    return scene
