"""The scene description (schema v1, ``data/scenes/SCHEMA.md``): what a scene file says, as
frozen dataclasses of Python floats, tuples and NumPy arrays, buildable in Python:

    scene = difffog.Scene(
        title="ball in fog",
        domain=difffog.Domain(min=(0, 0, 0), max=(1, 1, 1)),
        fog=difffog.Fog(scattering=2.0, absorption=0.1),
        sun=difffog.Sun(irradiance=2.0, zenith_deg=30.0),
        shapes=[difffog.Sphere("ball", center=(0.5, 0.5, 0.4), radius=0.2, albedo=0.6)],
        cameras=[difffog.Camera("top", "orthographic", position=(0.5, 0.5, 1.5),
                                look_at=(0.5, 0.5, 0), up=(0, 1, 0), resolution=(64, 64),
                                extent=(1, 1))])

Constructing any of them converts and validates its fields (``_checks.py``), with the same
one-line messages as the file loader.  Nothing here is traced by JAX; the lattice and the
parameter pytree (``_params.py``) are built from them.  Lengths are in scene units,
coefficients per scene unit, angles in degrees, radiance and irradiance in the same
(arbitrary, e.g. SI) units as the images.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Union


import numpy as np

Vec3 = tuple[float, float, float]

FACES = ("+x", "-x", "+y", "-y", "+z", "-z")


@dataclass(frozen=True)
class Domain:
    """The box the lattice covers: ``min``, ``max`` (x, y, z); ``boundary`` "open" (light
    leaving is lost) or "periodic-xy" (wraps laterally)."""

    min: Vec3
    max: Vec3
    boundary: Literal["open", "periodic-xy"] = "open"

    def __post_init__(self):
        from ._checks import check

        check(self)

    @property
    def size(self) -> Vec3:
        return tuple(b - a for a, b in zip(self.min, self.max))  # type: ignore[return-value]


@dataclass(frozen=True)
class Fog:
    """The participating medium.

    scattering, absorption: ζ and γ per unit length (multiplied by ``density``).
    phase: "isotropic" or "henyey-greenstein" (then ``g`` in (-1, 1), > 0 forward).
    density: a cell-centred (nx, ny, nz) multiplier grid over the domain (None: 1), or
        ``density_path``, an .npz file with an array ``density``.
    region: ((x, y, z), (x, y, z)): the fog fills only this box (None: the domain).
    """

    scattering: float  # ζ, per unit length
    absorption: float = 0.0  # γ, per unit length
    phase: Literal["isotropic", "henyey-greenstein"] = "isotropic"
    g: float | None = None
    density_path: str | None = None
    # cell-centred multiplier grid over the domain, indexed [ix, iy, iz]; None = 1 everywhere
    density: np.ndarray | None = field(default=None, compare=False, repr=False)
    region: tuple[Vec3, Vec3] | None = None  # (min, max); None = whole domain

    def __post_init__(self):
        from ._checks import check

        check(self)

    @property
    def extinction(self) -> float:
        return self.scattering + self.absorption

    @property
    def single_scattering_albedo(self) -> float:
        e = self.extinction
        return self.scattering / e if e > 0 else 0.0


def sun_vector(zenith_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit vector towards a sun at these angles (from +z; from +x towards +y)."""
    t, p = math.radians(zenith_deg), math.radians(azimuth_deg)
    return np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])


@dataclass(frozen=True)
class Sun:
    """A directional light: ``irradiance`` on a plane perpendicular to the beam, the direction
    towards it by ``zenith_deg`` (from +z) and ``azimuth_deg`` (from +x towards +y), and its
    ``angular_radius_deg`` (0: a point sun, hard shadows)."""

    irradiance: float  # on a plane perpendicular to the beam
    zenith_deg: float
    azimuth_deg: float = 0.0
    angular_radius_deg: float = 0.0  # 0 = a point sun (hard shadows)

    def __post_init__(self):
        from ._checks import check

        check(self)

    @property
    def direction(self) -> np.ndarray:
        """Unit vector pointing *towards* the sun."""
        return sun_vector(self.zenith_deg, self.azimuth_deg)


@dataclass(frozen=True)
class Sky:
    """A uniform sky: ``radiance`` over the upper hemisphere, zero below the horizon."""

    radiance: float  # uniform over the upper hemisphere, zero below the horizon

    def __post_init__(self):
        from ._checks import check

        check(self)


@dataclass(frozen=True)
class _ShapeBase:
    """What every shape has: a ``name`` (unique; "" → ``<kind>-<n>`` in its scene), a
    Lambertian ``albedo`` in [0, 1] and an ``emission`` (emitted radiance)."""

    name: str = ""
    albedo: float = 0.5
    emission: float = 0.0

    def __post_init__(self):
        from ._checks import check

        check(self)


@dataclass(frozen=True)
class Sphere(_ShapeBase):
    center: Vec3 = (0.0, 0.0, 0.0)
    radius: float = 1.0
    kind: str = "sphere"


@dataclass(frozen=True)
class Torus(_ShapeBase):
    center: Vec3 = (0.0, 0.0, 0.0)
    major_radius: float = 1.0
    minor_radius: float = 0.25
    axis: Vec3 = (0.0, 0.0, 1.0)
    kind: str = "torus"


@dataclass(frozen=True)
class Box(_ShapeBase):
    min: Vec3 = (0.0, 0.0, 0.0)
    max: Vec3 = (1.0, 1.0, 1.0)
    kind: str = "box"


@dataclass(frozen=True)
class OpenBox(_ShapeBase):
    min: Vec3 = (0.0, 0.0, 0.0)
    max: Vec3 = (1.0, 1.0, 1.0)
    thickness: float = 0.05
    open: tuple[str, ...] = ()
    kind: str = "open-box"

    def walls(self) -> list[tuple[Vec3, Vec3]]:
        """The closed walls as solid boxes (min, max), lying inside [min, max]."""
        lo, hi, t = np.array(self.min), np.array(self.max), self.thickness
        out = []
        for face in FACES:
            if face in self.open:
                continue
            axis = "xyz".index(face[1])
            a, b = lo.copy(), hi.copy()
            if face[0] == "+":
                a[axis] = hi[axis] - t
            else:
                b[axis] = lo[axis] + t
            out.append((tuple(a), tuple(b)))
        return out


@dataclass(frozen=True)
class Quad(_ShapeBase):
    corners: tuple[Vec3, Vec3, Vec3, Vec3] = ((0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0))
    kind: str = "quad"

    @property
    def normal(self) -> np.ndarray:
        """Unit normal of the lit side (corners counter-clockwise seen from it)."""
        c = np.asarray(self.corners, float)
        n = np.cross(c[2] - c[0], c[3] - c[1])
        return n / np.linalg.norm(n)


@dataclass(frozen=True)
class Mesh(_ShapeBase):
    path: str = ""
    scale: float = 1.0
    translate: Vec3 = (0.0, 0.0, 0.0)
    # world-space geometry after scale (about the origin) then translate
    vertices: np.ndarray | None = field(default=None, compare=False, repr=False)
    faces: np.ndarray | None = field(default=None, compare=False, repr=False)
    kind: str = "mesh"


Shape = Union[Sphere, Torus, Box, OpenBox, Quad, Mesh]


@dataclass(frozen=True)
class Camera:
    """A pinhole ("perspective", ``fov_deg`` the full horizontal field of view) or
    "orthographic" (``extent`` (width, height) of the view window) camera at ``position``
    looking at ``look_at``, ``up`` up in the image, ``resolution`` (width, height) pixels."""

    name: str
    kind: Literal["perspective", "orthographic"]
    position: Vec3
    look_at: Vec3
    up: Vec3 = (0.0, 0.0, 1.0)
    resolution: tuple[int, int] = (64, 64)  # (width, height)
    fov_deg: float | None = None  # perspective: full horizontal field of view
    extent: tuple[float, float] | None = None  # orthographic: (width, height) in scene units

    def __post_init__(self):
        from ._checks import check

        check(self)

    @property
    def width(self) -> int:
        return self.resolution[0]

    @property
    def height(self) -> int:
        return self.resolution[1]


@dataclass(frozen=True)
class Scene:
    """A validated scene: a title, the domain, optional fog, sun and sky, shapes and cameras
    (lists or tuples; unnamed ones are named ``<kind>-<n>`` / ``camera-<n>``)."""

    title: str
    domain: Domain
    fog: Fog | None = None
    sun: Sun | None = None
    sky: Sky | None = None
    shapes: tuple[Shape, ...] = ()
    cameras: tuple[Camera, ...] = ()
    source: Path | None = None  # the file it came from (for messages and relative paths)

    def __post_init__(self):
        from ._checks import check

        for name in ("shapes", "cameras"):
            v = getattr(self, name)
            if not isinstance(v, (list, tuple)):
                from .._errors import SceneError

                raise SceneError(f"difffog.Scene({self.title!r}): {name} must be a list of "
                                 f"{name}, got {type(v).__name__}; wrap a single one as [x]")
            object.__setattr__(self, name, tuple(v))
        check(self)

    def camera(self, name: str) -> Camera:
        for c in self.cameras:
            if c.name == name:
                return c
        known = ", ".join(c.name for c in self.cameras) or "(none)"
        from .._errors import SceneError

        raise SceneError(f"scene '{self.title}' has no camera '{name}'; its cameras are: {known}")

    def shape(self, name: str) -> Shape:
        for s in self.shapes:
            if s.name == name:
                return s
        known = ", ".join(s.name for s in self.shapes) or "(none)"
        from .._errors import SceneError

        raise SceneError(f"scene '{self.title}' has no shape '{name}'; its shapes are: {known}")

    def replace(self, **changes) -> "Scene":
        return dataclasses.replace(self, **changes)

    # --- what physics the scene needs (used by `difffog info` and the solver's plan) ---
    @property
    def has_fog(self) -> bool:
        return self.fog is not None and self.fog.extinction > 0

    @property
    def anisotropic(self) -> bool:
        return (
            self.fog is not None and self.fog.phase == "henyey-greenstein" and self.fog.g != 0.0
        )

    @property
    def has_meshes(self) -> bool:
        return any(s.kind in ("mesh", "quad") for s in self.shapes)
