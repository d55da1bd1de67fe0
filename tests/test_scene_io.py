"""Scenes: loading the built-in scenes (copies of the shared benchmark scenes, compared with
them by benchmarks/check_shared_scenes.py), overrides, a corpus of bad files, and scenes built in
Python (``difffog.Scene`` and friends), which validate as files do."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

import difffog as df
from difffog import SceneError, apply_overrides, builtin_scenes, load_scene, scalar_paths

HERE = Path(__file__).parent
BAD = HERE / "bad_scenes"

# name -> (shapes, cameras)
SHARED_COUNTS = {
    "cloud-plane": (2, 2),
    "fog-balls": (4, 2),
    "furnace": (1, 1),
    "ring-box": (2, 2),
    "slab": (0, 1),
    "translucent-cube": (2, 2),
}


def test_builtin_names():
    names = builtin_scenes()
    assert set(SHARED_COUNTS) <= set(names) and names == sorted(names)


@pytest.mark.parametrize("name", sorted(SHARED_COUNTS))
def test_builtin_scenes_load(name):
    s = load_scene(name)
    assert s.title == name
    assert (len(s.shapes), len(s.cameras)) == SHARED_COUNTS[name]
    assert s.source is not None and s.source.name == f"{name}.toml"


def test_fog_balls_values():
    s = load_scene("fog-balls")
    assert s.fog.scattering == 2.0 and s.fog.absorption == 0.5 and s.fog.phase == "isotropic"
    assert s.domain.boundary == "open"
    assert [x.name for x in s.shapes] == ["walls", "ball-high", "ball-mid", "ball-low"]
    walls = s.shape("walls")
    assert walls.kind == "open-box" and walls.open == ("+z",) and walls.thickness == 0.05
    assert s.shape("ball-high").center == (0.32, 0.55, 0.72)
    # zenith 20, azimuth 200: towards the sun
    t, p = math.radians(20), math.radians(200)
    want = [math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)]
    np.testing.assert_allclose(s.sun.direction, want, atol=1e-12)
    assert s.sun.direction[0] < 0 and s.sun.direction[1] < 0  # the third quadrant
    np.testing.assert_allclose(s.sun.direction, [-0.32139, -0.11698, 0.93969], atol=1e-5)
    top, obl = s.camera("top"), s.camera("oblique")
    assert top.kind == "orthographic" and top.extent == (1.0, 1.0) and top.resolution == (128, 128)
    assert obl.kind == "perspective" and obl.fov_deg == 45.0 and (obl.width, obl.height) == (160, 120)


def test_cloud_plane_density_and_mesh():
    s = load_scene("cloud-plane")
    f = s.fog
    assert f.phase == "henyey-greenstein" and f.g == 0.85 and f.density_path == "data/cloud64.npz"
    assert f.density.dtype == np.float32 and f.density.shape == (64, 64, 64)
    assert 0.0 <= f.density.min() and f.density.max() <= 1.0
    plane = s.shape("airplane")
    assert plane.vertices.dtype == np.float64 and plane.vertices.shape[1] == 3
    assert plane.faces.shape[1] == 3 and np.issubdtype(plane.faces.dtype, np.integer)
    # raw bounds [-0.155, -0.17, -0.025]..[0.155, 0.17, 0.065], translated by [0.45, 0.5, 0.8]
    np.testing.assert_allclose(plane.vertices.min(0), [0.295, 0.33, 0.775], atol=1e-7)
    np.testing.assert_allclose(plane.vertices.max(0), [0.605, 0.67, 0.865], atol=1e-7)
    assert s.shape("ground").kind == "quad"
    np.testing.assert_allclose(s.shape("ground").normal, [0, 0, 1])


def test_ring_box_and_translucent_cube():
    s = load_scene("ring-box")
    ring = s.shape("ring")
    assert ring.major_radius == 0.26 and ring.minor_radius == 0.07
    assert abs(np.linalg.norm(ring.axis) - 1) < 1e-12  # stored normalised
    np.testing.assert_allclose(ring.axis, np.array([0, -0.5, 0.866]) / np.linalg.norm([0, -0.5, 0.866]))
    assert s.fog is None and s.sky.radiance == 1.0 and s.sun.azimuth_deg == 180.0
    t = load_scene("translucent-cube")
    assert t.fog.region == ((0.2, 0.2, 0.1), (0.8, 0.8, 0.7))
    v = t.shape("ring").vertices
    np.testing.assert_allclose((v.min(0) + v.max(0)) / 2, [0.5, 0.5, 0.4], atol=1e-6)
    slab = load_scene("slab")
    assert slab.domain.boundary == "periodic-xy" and slab.shapes == ()
    furnace = load_scene("furnace")
    assert furnace.shape("walls").emission == 1.0 and furnace.shape("walls").open == ()


def test_defaults_and_auto_names(tmp_path):
    p = tmp_path / "mini.toml"
    p.write_text(
        "[domain]\nmin = [0, 0, 0]\nmax = [1, 1, 1]\n"
        "[fog]\nscattering = 1\n"
        "[sun]\nirradiance = 2\nzenith_deg = 0\n"
        '[[shape]]\nkind = "box"\nmin = [0.1, 0.1, 0.1]\nmax = [0.2, 0.2, 0.2]\n'
        '[[shape]]\nkind = "sphere"\ncenter = [0.5, 0.5, 0.5]\nradius = 0.1\n'
        '[[camera]]\nkind = "perspective"\nposition = [0.5, -1, 0.5]\nlook_at = [0.5, 0.5, 0.5]\n'
        "fov_deg = 40\nresolution = [8, 6]\n"
    )
    s = load_scene(p)
    assert s.title == "mini" and s.domain.boundary == "open"
    assert s.fog.absorption == 0.0 and s.fog.phase == "isotropic" and s.fog.density is None
    assert s.sun.azimuth_deg == 0.0 and s.sun.angular_radius_deg == 0.0 and s.sky is None
    assert [x.name for x in s.shapes] == ["box-1", "sphere-2"]
    assert s.shapes[0].albedo == 0.5 and s.shapes[0].emission == 0.0
    assert s.cameras[0].name == "camera-1" and s.cameras[0].up == (0.0, 0.0, 1.0)
    assert isinstance(s.domain.min[0], float) and isinstance(s.cameras[0].resolution[0], int)


def test_inward_mesh_is_repaired(tmp_path):
    # a closed tetrahedron wound inwards: loaded, and turned outwards
    (tmp_path / "t.obj").write_text(
        "v 0 0 0\nv 0.2 0 0\nv 0 0.2 0\nv 0 0 0.2\nf 1 2 3\nf 1 4 2\nf 1 3 4\nf 2 4 3\n"
    )
    (tmp_path / "s.toml").write_text(
        '[domain]\nmin = [0, 0, 0]\nmax = [1, 1, 1]\n[[shape]]\nkind = "mesh"\npath = "t.obj"\n'
        "scale = 2\ntranslate = [0.1, 0.1, 0.1]\n"
    )
    m = load_scene(tmp_path / "s.toml").shapes[0]
    v, f = m.vertices, m.faces
    vol = np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6
    assert vol == pytest.approx(0.4**3 / 6)
    np.testing.assert_allclose(v.min(0), [0.1, 0.1, 0.1])


def test_unknown_builtin_suggests():
    with pytest.raises(SceneError, match="Did you mean 'fog-balls'"):
        load_scene("fog-ball")
    with pytest.raises(SceneError, match="no such scene file"):
        load_scene(HERE / "no-such-scene.toml")


# --------------------------------------------------------------------------- overrides


def test_overrides_change_values():
    s = load_scene("fog-balls")
    o = apply_overrides(
        s,
        ["fog.scattering=2.5", "fog.absorption = 0", "shape.ball-high.albedo=0.3",
         "shape.ball-high.radius=0.2", "camera.oblique.fov_deg=40", "sun.zenith_deg=30",
         "sun.irradiance=1e1", "sky.radiance=0.25", "domain.boundary=periodic-xy"],
    )
    assert o.fog.scattering == 2.5 and o.fog.absorption == 0.0 and isinstance(o.fog.absorption, float)
    assert o.shape("ball-high").albedo == 0.3 and o.shape("ball-high").radius == 0.2
    assert o.shape("ball-mid").albedo == 0.8
    assert o.camera("oblique").fov_deg == 40.0
    assert o.sun.zenith_deg == 30.0 and o.sun.irradiance == 10.0 and o.sky.radiance == 0.25
    assert o.domain.boundary == "periodic-xy"
    assert s.fog.scattering == 2.0  # the original is untouched
    assert load_scene("fog-balls", ["fog.scattering=2.5"]).fog.scattering == 2.5
    assert apply_overrides(s, []) is s


def test_overrides_create_absent_tables():
    ring = apply_overrides(load_scene("ring-box"), ["fog.scattering=1.5"])
    assert (ring.fog.scattering, ring.fog.absorption, ring.fog.phase) == (1.5, 0.0, "isotropic")
    f = apply_overrides(load_scene("furnace"), ["sun.irradiance=2", "sky.radiance=0.5"])
    assert (f.sun.irradiance, f.sun.zenith_deg, f.sun.azimuth_deg) == (2.0, 0.0, 0.0)
    assert f.sky.radiance == 0.5
    g = apply_overrides(load_scene("slab"), ['fog.g=0.5'])
    assert g.fog.phase == "henyey-greenstein" and g.fog.g == 0.5 and g.anisotropic
    iso = apply_overrides(load_scene("cloud-plane"), ['fog.phase="isotropic"'])
    assert iso.fog.phase == "isotropic" and iso.fog.g == 0.0


def test_override_mesh_scale_moves_vertices():
    s = load_scene("cloud-plane")
    o = apply_overrides(s, ["shape.airplane.scale=0.5"])
    t = np.array([0.45, 0.5, 0.8])
    np.testing.assert_allclose(o.shape("airplane").vertices - t, (s.shape("airplane").vertices - t) / 2)


def test_scalar_paths():
    s = load_scene("fog-balls")
    paths = scalar_paths(s)
    for p in ["fog.scattering", "fog.absorption", "fog.g", "sun.zenith_deg", "sun.irradiance",
              "sky.radiance", "domain.boundary", "shape.ball-high.albedo",
              "shape.ball-high.radius", "shape.walls.thickness", "camera.oblique.fov_deg"]:
        assert p in paths
    assert "camera.top.fov_deg" not in paths  # an orthographic camera
    assert len(paths) == len(set(paths))
    numeric = scalar_paths(s, numeric=True)
    assert "fog.phase" not in numeric and "domain.boundary" not in numeric
    assert set(numeric) < set(paths)
    assert "shape.ring.minor_radius" in scalar_paths(load_scene("ring-box"))
    assert "shape.airplane.scale" in scalar_paths(load_scene("cloud-plane"))


@pytest.mark.parametrize(
    "scene, item, expect",
    [
        ("fog-balls", "fog.scattering=-1", ["--set fog.scattering=-1", "[fog].scattering = -1.0", ">= 0"]),
        ("fog-balls", "fog.scatering=1", ["fog.scatering", "Did you mean 'fog.scattering'"]),
        ("fog-balls", "shape.ball-hi.albedo=0.3", ["no shape 'ball-hi'", "ball-high"]),
        ("fog-balls", "camera.top.fov_deg=40", ["camera.top.fov_deg", "no 'fov_deg'", "camera.oblique.fov_deg"]),
        ("fog-balls", "shape.ball-high.center=0.2", ["'center'", "cannot be set"]),
        ("fog-balls", "fog.scattering=abc", ['scattering = "abc"', "must be a number"]),
        ("fog-balls", "fog.scattering=true", ["scattering = true", "must be a number"]),
        ("fog-balls", "fog.scattering=[1, 2]", ["scattering = [1, 2]", "must be a number"]),
        ("fog-balls", "fog.scattering=inf", ["scattering = inf", "finite"]),
        ("fog-balls", "fog.phase=2", ["phase = 2", "must be a string"]),
        ("fog-balls", "fog.scattering", ["'fog.scattering' is not PATH=VALUE"]),
        ("fog-balls", "shape.ball-high.albedo=1.5", ["'ball-high'.albedo = 1.5", "[0, 1]"]),
        ("fog-balls", "shape.ball-high.radius=-0.2", ["'ball-high'.radius = -0.2", "> 0"]),
        ("fog-balls", "shape.walls.thickness=0.6", ["'walls'.thickness = 0.6", "< 0.5"]),
        ("fog-balls", "domain.boundary=periodic", ['boundary = "periodic"', '"periodic-xy"']),
        ("fog-balls", "fog.g=1.0", ["[fog].g = 1.0", "(-1, 1)"]),
        ("fog-balls", "camera.oblique.fov_deg=180", ["'oblique'.fov_deg = 180.0", "(0, 180)"]),
        ("fog-balls", "sun.zenith_deg=-5", ["[sun].zenith_deg = -5.0", "[0, 180]"]),
        ("ring-box", "shape.ring.minor_radius=0.3", ["'ring'.minor_radius = 0.3", "major_radius"]),
        ("cloud-plane", "shape.airplane.scale=0", ["'airplane'.scale = 0.0", "> 0"]),
        ("furnace", "sky.radiance=-1", ["[sky].radiance = -1.0", ">= 0"]),
    ],
)
def test_bad_overrides(scene, item, expect):
    with pytest.raises(SceneError) as e:
        apply_overrides(load_scene(scene), [item])
    msg = str(e.value)
    assert f"{scene}.toml" in msg
    for part in expect:
        assert part in msg, msg


def test_overrides_are_validated_together():
    # minor then major: only the final state must be valid
    s = apply_overrides(load_scene("ring-box"),
                        ["shape.ring.minor_radius=0.3", "shape.ring.major_radius=0.35"])
    assert (s.shape("ring").minor_radius, s.shape("ring").major_radius) == (0.3, 0.35)


# --------------------------------------------------------------------------- bad files
# file stem -> substrings its one message must contain (besides the file name)
BAD_FILES = {
    "toml-syntax": ["not valid TOML", "line 6"],
    "unknown-table": ["unknown table or key 'fogg'", "Did you mean 'fog'"],
    "unknown-fog-key": ["[fog] has an unknown key 'scatering'", "Did you mean 'scattering'"],
    "unknown-shape-key": ["'ball' has an unknown key 'radious'", "Did you mean 'radius'"],
    "key-of-other-kind": ["unknown key 'thickness'", "belongs to an open-box"],
    "missing-domain": ["[domain] table is missing"],
    "missing-domain-max": ["[domain] is missing the required key 'max'"],
    "missing-sphere-radius": ["[[shape]] #1 'ball' is missing the required key 'radius'"],
    "missing-shape-kind": ["'ball' is missing the required key 'kind'", "sphere"],
    "string-for-number": ['[fog].scattering = "2.0"', "must be a number"],
    "nan-coefficient": ["[fog].scattering = nan", "finite"],
    "vector-wrong-length": ["'ball'.center = [0.5, 0.5]", "3 numbers"],
    "negative-scattering": ["[fog].scattering = -1.0", ">= 0"],
    "negative-absorption": ["[fog].absorption = -0.5", ">= 0"],
    "albedo-above-one": ["'ball'.albedo = 1.2", "[0, 1]"],
    "negative-emission": ["'ball'.emission = -1.0", ">= 0"],
    "hg-g-out-of-range": ["[fog].g = 1.0", "(-1, 1)"],
    "hg-missing-g": ['phase = "henyey-greenstein" but no g'],
    "g-with-isotropic": ["[fog].g = 0.5", 'phase = "isotropic"'],
    "unknown-phase": ['[fog].phase = "rayleigh"', '"henyey-greenstein"'],
    "domain-min-ge-max": ["[domain].min = [0.0, 0.0, 1.0]", "z axis"],
    "unknown-boundary": ['[domain].boundary = "periodic"', 'Did you mean "periodic-xy"'],
    "negative-sky": ["[sky].radiance = -0.1", ">= 0"],
    "sun-zenith-out-of-range": ["[sun].zenith_deg = 200.0", "[0, 180]"],
    "negative-sun-irradiance": ["[sun].irradiance = -3.0", ">= 0"],
    "fog-as-array": ["'fog' must be a single table [fog]"],
    "camera-as-table": ["'camera' must be an array of tables", "[[camera]]"],
    "camera-look-at-position": ["'view'.look_at = [0.5, -0.5, 1.0]", "is the camera's position"],
    "camera-up-parallel": ["'view'.up = [0.0, 0.0, 1.0]", "parallel to the view direction"],
    "camera-fov-180": ["'view'.fov_deg = 180.0", "(0, 180)"],
    "camera-fov-negative": ["'view'.fov_deg = -10.0", "(0, 180)"],
    "camera-missing-fov": ["'view' is missing the required key 'fov_deg'"],
    "camera-fov-on-ortho": ["unknown key 'fov_deg'", "extent"],
    "camera-extent-zero": ["'top'.extent = [1.0, 0.0]", "positive"],
    "camera-resolution-zero": ["'top'.resolution = [16, 0]", "positive"],
    "camera-resolution-float": ["'top'.resolution = [16.5, 16]", "whole numbers"],
    "camera-unknown-kind": ["'fish'.kind = \"fisheye\"", "perspective, orthographic"],
    "duplicate-camera-names": ["[[camera]] #2 'top'.name = \"top\"", "already used by [[camera]] #1"],
    "unknown-shape-kind": ["'can'.kind = \"cylinder\"", "open-box, sphere, torus, box, quad, mesh"],
    "openbox-bad-face": ["'walls'.open = [\"top\"]", '"+z"'],
    "openbox-thickness-zero": ["'walls'.thickness = 0.0", "> 0"],
    "openbox-too-thick": ["'walls'.thickness = 0.6", "< 0.5"],
    "openbox-all-open": ["'walls'.open = [", "no walls"],
    "sphere-negative-radius": ["'ball'.radius = -0.2", "> 0"],
    "torus-minor-ge-major": ["'ring'.minor_radius = 0.15", "< major_radius = 0.1"],
    "torus-zero-axis": ["'ring'.axis = [0.0, 0.0, 0.0]", "zero length"],
    "box-min-ge-max": ["'block'.min = [0.2, 0.6, 0.2]", "y axis"],
    "quad-three-corners": ["'ground'.corners = [[", "4 points", "got 3"],
    "quad-zero-area": ["'ground'.corners = [[", "zero area"],
    "quad-non-planar": ["'ground'.corners = [[", "not planar"],
    "quad-bowtie": ["'ground'.corners = [[0.0, 0.0, 0.1], [1.0, 1.0, 0.1]", "convex"],
    "mesh-missing-file": ["'plane'.path = \"meshes/no-such.obj\"", "no readable file"],
    "mesh-open": ["'lid'.path = \"open-tetra.obj\"", "not watertight", "3 boundary edges"],
    "mesh-garbage": ["'junk'.path = \"garbage.obj\"", "no triangles"],
    "mesh-unknown-format": ["'junk'.path = \"mesh.foo\"", "could not be read as a mesh"],
    "mesh-negative-scale": ["'tet'.scale = -1.0", "> 0"],
    "mesh-outside-domain": ["'tet' lies entirely outside the domain"],
    "density-missing-file": ['[fog].density = "no-such.npz"', "no readable file"],
    "density-wrong-key": ['[fog].density = "density-wrong-key.npz"', "no array 'density'", "cloud"],
    "density-2d": ['[fog].density = "density-2d.npz"', "shape (4, 4)", "3-D"],
    "density-int": ['[fog].density = "density-int.npz"', "dtype int32"],
    "density-nan": ['[fog].density = "density-nan.npz"', "NaN", "[1, 2, 3]"],
    "density-negative": ['[fog].density = "density-negative.npz"', "negative", "-0.5"],
    "density-not-npz": ['[fog].density = "not-an-archive.npz"', "not an .npz archive"],
    "density-npy": ['[fog].density = "density.npy"', ".npy array"],
    "region-min-ge-max": ["[fog].region.min = [0.2, 0.2, 0.8]", "z axis"],
    "region-outside-domain": ["[fog].region.min = [2.0, 2.0, 2.0]", "outside the domain"],
    "region-unknown-key": ["[fog].region has an unknown key 'maxi'", "Did you mean 'max'"],
    "shape-outside-domain": ["'far' lies entirely outside the domain", "[4.8, 4.8, 4.8]"],
    "duplicate-shape-names": ["[[shape]] #2 'ball'.name = \"ball\"", "already used by [[shape]] #1"],
    "auto-name-clash": ["[[shape]] #2 'sphere-2'.name", "already used by [[shape]] #1"],
    "shape-name-with-dot": ["'ball.high'.name = \"ball.high\"", "no dots"],
    "title-not-string": ["title = 3", "must be a string"],
}


def test_bad_corpus_is_complete():
    assert sorted(p.stem for p in BAD.glob("*.toml")) == sorted(BAD_FILES)
    assert len(BAD_FILES) >= 30


@pytest.mark.parametrize("stem", sorted(BAD_FILES))
def test_bad_file(stem):
    path = BAD / f"{stem}.toml"
    with pytest.raises(SceneError) as e:
        load_scene(path)
    err, msg = e.value, str(e.value)
    assert msg.startswith(f"{path}: "), msg  # names the file
    for part in BAD_FILES[stem]:
        assert part in msg, msg
    assert "\n" not in msg
    # no library traceback chained to it
    assert err.__cause__ is None and (err.__context__ is None or err.__suppress_context__)


# --------------------------------------------------------------------------- scenes in Python

UNIT = df.Domain(min=(0.0, 0.0, 0.0), max=(1.0, 1.0, 1.0))
# a closed tetrahedron wound inwards (as tests/bad_scenes/closed-tetra.obj is a closed one)
TET_V = np.array([[0, 0, 0], [0.2, 0, 0], [0, 0.2, 0], [0, 0, 0.2]]) + 0.3
TET_F = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])


def _tet_volume(v, f):
    return np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6


def _cam(name="view", kind="perspective", **kw):
    base = dict(position=(0.5, -0.5, 1.0), look_at=(0.5, 0.5, 0.3), up=(0.0, 0.0, 1.0),
                resolution=(16, 12))
    base.update(kw)
    if kind == "perspective" and "fov_deg" not in kw:
        base["fov_deg"] = 45.0
    if kind == "orthographic" and "extent" not in kw:
        base["extent"] = (1.0, 1.0)
    return df.Camera(name, kind, **base)


def _scene(*shapes, cameras=(), fog=None, **kw):
    return df.Scene(title="t", domain=UNIT, fog=fog, shapes=shapes, cameras=cameras, **kw)


# bad file stem -> (the same mistake in Python, where the file's and Python's message start to
# agree).  The message names the constructor instead of the file and table, then says the same.
PARITY = {
    "sphere-negative-radius": (lambda: df.Sphere("ball", center=(0.5, 0.5, 0.5), radius=-0.2),
                               "radius = -0.2"),
    "albedo-above-one": (lambda: df.Sphere("ball", center=[0.5, 0.5, 0.5], radius=0.2,
                                           albedo=1.2), "albedo = 1.2"),
    "negative-emission": (lambda: df.Sphere("ball", center=(0.5, 0.5, 0.5), radius=0.2,
                                            emission=-1), "emission = -1.0"),
    "domain-min-ge-max": (lambda: df.Domain(min=[0, 0, 1], max=np.ones(3)),
                          "min = [0.0, 0.0, 1.0]"),
    "unknown-boundary": (lambda: df.Domain((0, 0, 0), (1, 1, 1), "periodic"), "boundary ="),
    "box-min-ge-max": (lambda: df.Box("block", min=(0.2, 0.6, 0.2), max=(0.8, 0.4, 0.8)),
                       "min = [0.2, 0.6, 0.2]"),
    "string-for-number": (lambda: df.Fog(scattering="2.0"), 'scattering = "2.0"'),
    "negative-scattering": (lambda: df.Fog(scattering=-1), "scattering = -1.0"),
    "hg-g-out-of-range": (lambda: df.Fog(scattering=1.0, phase="henyey-greenstein", g=1.0),
                          "g = 1.0"),
    "g-with-isotropic": (lambda: df.Fog(scattering=1.0, g=0.5), "g = 0.5"),
    "unknown-phase": (lambda: df.Fog(scattering=1.0, phase="rayleigh"), "phase ="),
    "region-min-ge-max": (lambda: df.Fog(scattering=1.0, region=((0.2, 0.2, 0.8),
                                                                  (0.8, 0.8, 0.2))),
                          "region.min ="),
    "density-negative": (lambda: df.Fog(scattering=1.0, density_path="density-negative.npz",
                                        density=np.load(BAD / "density-negative.npz")["density"]),
                         "density ="),
    "negative-sky": (lambda: df.Sky(radiance=-0.1), "radiance = -0.1"),
    "sun-zenith-out-of-range": (lambda: df.Sun(irradiance=1.0, zenith_deg=200),
                                "zenith_deg = 200.0"),
    "negative-sun-irradiance": (lambda: df.Sun(irradiance=-3, zenith_deg=0),
                                "irradiance = -3.0"),
    "vector-wrong-length": (lambda: df.Sphere("ball", center=np.array([0.5, 0.5]), radius=0.2),
                            "center = [0.5, 0.5]"),
    "torus-minor-ge-major": (lambda: df.Torus("ring", center=(0.5, 0.5, 0.5), major_radius=0.1,
                                              minor_radius=0.15), "minor_radius = 0.15"),
    "torus-zero-axis": (lambda: df.Torus("ring", center=(0.5, 0.5, 0.5), major_radius=0.2,
                                         minor_radius=0.05, axis=np.zeros(3)), "axis ="),
    "openbox-bad-face": (lambda: df.OpenBox("walls", thickness=0.05, open=["top"]), "open ="),
    "openbox-too-thick": (lambda: df.OpenBox("walls", thickness=0.6, open=("+z",)),
                          "thickness = 0.6"),
    "quad-bowtie": (lambda: df.Quad("ground", corners=np.array(
        [[0.0, 0.0, 0.1], [1.0, 1.0, 0.1], [1.0, 0.0, 0.1], [0.0, 1.0, 0.1]])), "corners ="),
    "shape-name-with-dot": (lambda: df.Sphere("ball.high", center=(0.5, 0.5, 0.5), radius=0.2),
                            "name ="),
    "mesh-negative-scale": (lambda: df.Mesh("tet", vertices=TET_V, faces=TET_F, scale=-1.0),
                            "scale = -1.0"),
    "camera-up-parallel": (lambda: df.Camera("view", "perspective", position=[0.5, 0.5, 1.5],
                                             look_at=(0.5, 0.5, 0), up=np.array([0, 0, 1]),
                                             resolution=(16, 12), fov_deg=45), "up ="),
    "camera-look-at-position": (lambda: _cam(look_at=(0.5, -0.5, 1.0)), "look_at ="),
    "camera-fov-180": (lambda: _cam(fov_deg=180), "fov_deg = 180.0"),
    "camera-fov-negative": (lambda: _cam(fov_deg=-10), "fov_deg = -10.0"),
    "camera-extent-zero": (lambda: _cam("top", "orthographic", extent=(1, 0)), "extent ="),
    "camera-resolution-zero": (lambda: _cam("top", "orthographic", resolution=(16, 0)),
                               "resolution ="),
    "camera-resolution-float": (lambda: _cam("top", "orthographic", resolution=(16.5, 16)),
                                "resolution = [16.5, 16]"),
    # what involves several objects is checked by the Scene
    "shape-outside-domain": (lambda: _scene(df.Sphere("far", center=(5, 5, 5), radius=0.2)),
                             "[[shape]] #1 'far'"),
    "duplicate-shape-names": (lambda: _scene(df.Sphere("ball", center=(0.5, 0.5, 0.5), radius=0.2),
                                             df.Sphere("ball", center=(0.3, 0.3, 0.3), radius=0.2)),
                              "[[shape]] #2"),
    "auto-name-clash": (lambda: _scene(df.Sphere("sphere-2", center=(0.5, 0.5, 0.5), radius=0.1),
                                       df.Sphere(center=(0.2, 0.2, 0.2), radius=0.1)),
                        "[[shape]] #2"),
    "region-outside-domain": (lambda: _scene(fog=df.Fog(scattering=1.0, region=((2, 2, 2),
                                                                              (3, 3, 3)))),
                              "[fog].region.min ="),
    "duplicate-camera-names": (lambda: _scene(cameras=[_cam("top", "orthographic"),
                                                       _cam("top", "orthographic")]),
                               "[[camera]] #2"),
}


def test_parity_cases_are_bad_files():
    assert set(PARITY) <= set(BAD_FILES) and len(PARITY) >= 30


@pytest.mark.parametrize("stem", sorted(PARITY))
def test_python_scene_says_what_the_file_says(stem):
    build, anchor = PARITY[stem]
    with pytest.raises(SceneError) as file_err:
        load_scene(BAD / f"{stem}.toml")
    with pytest.raises(SceneError) as py_err:
        build()
    f, p = str(file_err.value), str(py_err.value)
    assert anchor in f and anchor in p, (f, p)
    assert p[p.index(anchor):] == f[f.index(anchor):]  # the same words from the field on
    assert p.startswith("difffog.") and "\n" not in p  # names the constructor, one line
    for part in BAD_FILES[stem]:  # what the file's message must say, Python's says too
        if not part.startswith(("[", "'")):
            assert part in p, (part, p)
    err = py_err.value
    assert err.__cause__ is None and (err.__context__ is None or err.__suppress_context__)


@pytest.mark.parametrize(
    "build, match",
    [
        (lambda: df.Sphere("ball", center=(0.5, 0.5, 0.5), radius=-1),
         r"^difffog\.Sphere\('ball'\): radius = -1\.0 must be > 0$"),
        (lambda: df.Sphere(center=(0.5, 0.5, 0.5), radius=0.1, albedo=2),
         r"^difffog\.Sphere: albedo = 2\.0 must be in \[0, 1\]; it is the Lambertian reflectance$"),
        (lambda: df.Domain(min=(0, 0, 0), max=(1, 0, 1)),
         r"^difffog\.Domain: min = \[0\.0, 0\.0, 0\.0\] is not below max = \[1\.0, 0\.0, 1\.0\] "
         r"on the y axis"),
        (lambda: df.Box("b", min=(0.5, 0.5, 0.5), max=(0.5, 0.6, 0.7)),
         r"^difffog\.Box\('b'\): min = .* on the x axis \(0\.5 >= 0\.5\).* for a box$"),
        (lambda: _scene(df.Box("b", min=(2, 2, 2), max=(3, 3, 3))),
         r"^difffog\.Scene\('t'\): \[\[shape\]\] #1 'b' lies entirely outside the domain"),
        (lambda: _scene(df.Sphere("a", center=(0.5, 0.5, 0.5), radius=0.1),
                        df.Torus("a", center=(0.5, 0.5, 0.5), major_radius=0.2,
                                 minor_radius=0.05)),
         r"^difffog\.Scene\('t'\): \[\[shape\]\] #2 'a'\.name = \"a\" is already used by "
         r"\[\[shape\]\] #1"),
        (lambda: _cam(position=(0.5, 0.5, 2.0), look_at=(0.5, 0.5, 0.0), up=[0, 0, -3]),
         r"^difffog\.Camera\('view'\): up = \[0\.0, 0\.0, -3\.0\] is parallel to the view "
         r"direction"),
        (lambda: df.Fog(scattering="1.5"),
         r"^difffog\.Fog: scattering = \"1\.5\" must be a number, not a string"),
        (lambda: df.Sphere("b", center=(0.5, 0.5, 0.5), radius=True),
         r"radius = true must be a number, not a boolean"),
        (lambda: df.Sun(irradiance=[1.0], zenith_deg=0),
         r"^difffog\.Sun: irradiance = \[1\.0\] must be a number, not a list"),
        (lambda: df.Sky(radiance=float("nan")), r"^difffog\.Sky: radiance = nan must be a finite"),
        (lambda: df.Sphere("b", center=(0.5, "x", 0.5), radius=0.1),
         r"center = \[0\.5, \"x\", 0\.5\] must be a list of 3 numbers"),
        (lambda: df.Sphere("b", center=(0.5, 0.5, np.inf), radius=0.1), r"finite numbers only"),
        # None where a value is needed, and wrong types, are one-line SceneErrors too
        (lambda: df.Sphere("b", center=None, radius=0.1),
         r"^difffog\.Sphere\('b'\): center is None, but it needs a value; pass center=\.\.\.$"),
        (lambda: df.Fog(scattering=1.0, absorption=None), r"absorption is None"),
        (lambda: _cam(fov_deg=None), r"^difffog\.Camera\('view'\): fov_deg is None"),
        (lambda: _cam("top", "orthographic", extent=None), r"extent is None"),
        (lambda: _cam("top", "orthographic", fov_deg=40),
         r"fov_deg = 40 is for perspective cameras; an orthographic camera takes extent"),
        (lambda: _cam(extent=(1, 1)),
         r"extent = \[1, 1\] is for orthographic cameras; a perspective camera takes fov_deg"),
        (lambda: _cam(kind=3), r"kind = 3 must be a string"),
        (lambda: _cam(kind="perspectiv"), r'kind = "perspectiv" is not a known camera kind\. '
                                          r'Did you mean "perspective"\?'),
        (lambda: _cam(resolution=np.array([16.0, 12.0])), r"must be two whole numbers"),
        (lambda: df.Sphere(3, center=(0.5, 0.5, 0.5), radius=0.1),
         r"^difffog\.Sphere\(3\): name = 3 must be a string"),
        (lambda: df.Scene(title=3, domain=UNIT), r"^difffog\.Scene\(3\): title = 3 must be a "
                                                 r"string"),
        (lambda: df.Scene(title="t", domain=((0, 0, 0), (1, 1, 1))),
         r"^difffog\.Scene\('t'\): domain must be a difffog\.Domain, got tuple$"),
        (lambda: df.Scene(title="t", domain=UNIT, fog={"scattering": 1.0}),
         r"fog must be a difffog\.Fog or None, got dict"),
        (lambda: _scene("ball"), r"shapes\[0\] is a str, not a shape"),
        (lambda: _scene(cameras=[UNIT]), r"cameras\[0\] is a Domain, not a difffog\.Camera"),
        (lambda: df.Fog(scattering=1.0, density=np.ones((4, 4))),
         r"density = \"the density array\" grid has shape \(4, 4\)"),
        (lambda: df.Fog(scattering=1.0, density=np.ones((2, 2, 2), np.int32)), r"dtype int32"),
        (lambda: df.Mesh("m"), r"^difffog\.Mesh\('m'\): path = \"\" is empty"),
        (lambda: df.Mesh("m", path="no-such.obj"),
         r"path = \"no-such.obj\" names no readable file"),
        (lambda: df.Sphere("b", center=(0.5, 0.5, 0.5), radius=0.1, kind="box"),
         r"^difffog\.Sphere\('b'\): kind = \"box\" is not the kind of a difffog\.Sphere, which "
         r"is \"sphere\""),
    ],
)
def test_python_scene_objects_validate(build, match):
    with pytest.raises(SceneError, match=match) as e:
        build()
    assert "\n" not in str(e.value)


def test_python_objects_convert_vectors_and_numbers():
    arr = np.array([0.25, 0.5, 0.75], np.float32)
    for center in ([0.25, 0.5, 0.75], (0.25, 0.5, 0.75), arr, np.array([0.25, 0.5, 0.75])):
        s = df.Sphere("b", center=center, radius=np.float32(0.125), albedo=np.int64(1))
        assert s.center == (0.25, 0.5, 0.75) and type(s.center) is tuple
        assert all(type(x) is float for x in s.center)
        assert s.radius == 0.125 and type(s.radius) is float and s.albedo == 1.0
    c = df.Camera("c", "orthographic", position=np.array([0.5, 0.5, 2]), look_at=[0.5, 0.5, 0],
                  up=(0, 1, 0), resolution=np.array([8, 6]), extent=np.array([1.0, 0.75]))
    assert c.resolution == (8, 6) and all(type(x) is int for x in c.resolution)
    assert c.extent == (1.0, 0.75) and c.position == (0.5, 0.5, 2.0) and c.up == (0.0, 1.0, 0.0)
    q = df.Quad("q", corners=np.array([[0, 0, 0.5], [1, 0, 0.5], [1, 1, 0.5], [0, 1, 0.5]]))
    assert q.corners[2] == (1.0, 1.0, 0.5) and type(q.corners) is tuple
    np.testing.assert_allclose(q.normal, [0, 0, 1])
    w = df.OpenBox("w", thickness=0.1, open=["+z", "-y"])
    assert w.open == ("+z", "-y")
    t = df.Torus("r", center=(0.5, 0.5, 0.5), major_radius=0.2, minor_radius=0.05,
                 axis=np.array([0, 0, 2.0]))
    assert t.axis == (0.0, 0.0, 1.0)  # stored normalised, as a file's
    f = df.Fog(scattering=1, absorption=np.float64(0.5), region=[[0, 0, 0], np.ones(3)])
    assert f.region == ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)) and f.extinction == 1.5
    g = df.Fog(scattering=1, density=np.ones((2, 3, 4), np.float64))
    assert g.density.dtype == np.float32 and g.density.shape == (2, 3, 4)
    d = df.Domain(min=np.zeros(3), max=[2, 1, 1], boundary="periodic-xy")
    assert d.min == (0.0, 0.0, 0.0) and d.size == (2.0, 1.0, 1.0)
    # frozen, and a replaced object is validated again
    with pytest.raises(dataclasses.FrozenInstanceError):
        t.radius = 0.3
    with pytest.raises(SceneError, match=r"^difffog\.Torus\('r'\): minor_radius = 0\.3"):
        dataclasses.replace(t, minor_radius=0.3)


def test_python_unnamed_shapes_and_cameras_are_numbered():
    s = df.Scene(
        title="named",
        domain=UNIT,
        shapes=[df.Sphere(center=(0.5, 0.5, 0.5), radius=0.1),
                df.Box("block", min=(0.1, 0.1, 0.1), max=(0.2, 0.2, 0.2)),
                df.Torus(center=(0.5, 0.5, 0.5), major_radius=0.3, minor_radius=0.05),
                df.OpenBox(thickness=0.02),
                df.Quad(corners=((0, 0, 0.1), (1, 0, 0.1), (1, 1, 0.1), (0, 1, 0.1))),
                df.Mesh(vertices=TET_V, faces=TET_F)],
        cameras=(_cam(""), _cam("side"), _cam("")),
    )
    assert [x.name for x in s.shapes] == ["sphere-1", "block", "torus-3", "open-box-4", "quad-5",
                                          "mesh-6"]
    assert [c.name for c in s.cameras] == ["camera-1", "side", "camera-3"]
    assert s.shape("torus-3").kind == "torus" and s.camera("camera-3").fov_deg == 45.0
    assert isinstance(s.shapes, tuple) and isinstance(s.cameras, tuple)
    with pytest.raises(SceneError, match="has no shape 'sphere-2'; its shapes are: sphere-1, "
                                         "block, torus-3"):
        s.shape("sphere-2")
    # a scene built in Python has the paths a file's has, and takes overrides
    assert "shape.torus-3.minor_radius" in scalar_paths(s)
    o = apply_overrides(s, ["shape.sphere-1.radius=0.2", "fog.scattering=1"])
    assert o.shape("sphere-1").radius == 0.2 and o.fog.scattering == 1.0 and s.fog is None
    with pytest.raises(SceneError, match=r"^scene 'named' with --set shape\.sphere-1\.radius=-1: "
                                         r"\[\[shape\]\] #1 'sphere-1'\.radius = -1\.0 must be "
                                         r"> 0"):
        apply_overrides(s, ["shape.sphere-1.radius=-1"])
    # replacing the shapes checks the scene again
    with pytest.raises(SceneError, match="already used by"):
        s.replace(shapes=s.shapes + (df.Sphere("block", center=(0.5, 0.5, 0.5), radius=0.1),))


def _rebuild(obj):
    """The object built again from its constructor's fields, as a user would write it."""
    return type(obj)(**{f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)
                        if f.init and (f.name != "kind" or isinstance(obj, df.Camera))})


@pytest.mark.parametrize("name", sorted(SHARED_COUNTS))
def test_python_rebuild_of_builtin_scene_is_equal(name):
    s = load_scene(name)
    py = df.Scene(
        title=s.title,
        domain=_rebuild(s.domain),
        fog=None if s.fog is None else _rebuild(s.fog),
        sun=None if s.sun is None else _rebuild(s.sun),
        sky=None if s.sky is None else _rebuild(s.sky),
        shapes=[_rebuild(x) for x in s.shapes],
        cameras=[_rebuild(c) for c in s.cameras],
    )
    assert py == s.replace(source=None)
    for a, b in zip(py.shapes, s.shapes):
        if a.kind == "mesh":  # arrays do not take part in ==
            np.testing.assert_array_equal(a.vertices, b.vertices)
            np.testing.assert_array_equal(a.faces, b.faces)
    if s.fog is not None and s.fog.density is not None:
        np.testing.assert_array_equal(py.fog.density, s.fog.density)


def test_fog_balls_written_in_python_equals_the_file():
    cams = [
        df.Camera("top", "orthographic", position=(0.5, 0.5, 1.5), look_at=(0.5, 0.5, 0.0),
                  up=(0, 1, 0), resolution=(128, 128), extent=(1, 1)),
        df.Camera("oblique", "perspective", position=[0.5, -0.35, 1.75],
                  look_at=np.array([0.5, 0.5, 0.35]), up=(0, 0, 1), resolution=[160, 120],
                  fov_deg=45),
    ]
    balls = [df.Sphere(n, center=c, radius=0.12, albedo=0.8)
             for n, c in (("ball-high", (0.32, 0.55, 0.72)), ("ball-mid", (0.62, 0.38, 0.50)),
                          ("ball-low", (0.45, 0.70, 0.28)))]
    py = df.Scene(
        title="fog-balls",
        domain=df.Domain(min=(0, 0, 0), max=(1, 1, 1)),
        fog=df.Fog(scattering=2, absorption=0.5),
        sun=df.Sun(irradiance=3, zenith_deg=20, azimuth_deg=200),
        sky=df.Sky(radiance=0.1),
        shapes=[df.OpenBox("walls", min=(0, 0, 0), max=(1, 1, 1), thickness=0.05, open=["+z"],
                           albedo=0.7), *balls],
        cameras=cams,
    )
    assert py == load_scene("fog-balls").replace(source=None)
    assert py.source is None and py.sun.direction == pytest.approx(load_scene("fog-balls")
                                                                   .sun.direction)


def test_small_scene_in_toml_and_in_python_agree(tmp_path, monkeypatch):
    # the inward tetrahedron of test_inward_mesh_is_repaired, as a file and as arrays
    obj = "".join(f"v {x} {y} {z}\n" for x, y, z in TET_V - 0.3)
    obj += "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in TET_F)
    (tmp_path / "t.obj").write_text(obj)
    np.savez(tmp_path / "d.npz", density=np.linspace(0, 1, 24, dtype=np.float32).reshape(2, 3, 4))
    (tmp_path / "mini.toml").write_text(
        'title = "mini"\n'
        '[domain]\nmin = [0, 0, 0]\nmax = [1, 1, 1]\nboundary = "periodic-xy"\n'
        '[fog]\nscattering = 1.5\nphase = "henyey-greenstein"\ng = 0.3\ndensity = "d.npz"\n'
        "region = { min = [0, 0, 0], max = [1, 1, 0.5] }\n"
        "[sun]\nirradiance = 2\nzenith_deg = 30\nangular_radius_deg = 0.27\n"
        '[[shape]]\nkind = "box"\nmin = [0.1, 0.1, 0.1]\nmax = [0.2, 0.2, 0.2]\n'
        '[[shape]]\nname = "tet"\nkind = "mesh"\npath = "t.obj"\nscale = 2\n'
        "translate = [0.1, 0.1, 0.1]\nalbedo = 0.25\n"
        '[[shape]]\nkind = "quad"\ncorners = [[0, 0, 0.9], [1, 0, 0.9], [1, 1, 0.9], [0, 1, 0.9]]\n'
        "emission = 1\n"
        '[[camera]]\nkind = "perspective"\nposition = [0.5, -1, 0.5]\nlook_at = [0.5, 0.5, 0.5]\n'
        "fov_deg = 40\nresolution = [8, 6]\n"
    )
    f = load_scene(tmp_path / "mini.toml")
    monkeypatch.chdir(tmp_path)  # a Python Mesh's path and a Fog's density_path: from here
    py = df.Scene(
        title="mini",
        domain=df.Domain([0, 0, 0], [1, 1, 1], "periodic-xy"),
        fog=df.Fog(scattering=1.5, phase="henyey-greenstein", g=0.3, density_path="d.npz",
                   region=((0, 0, 0), (1, 1, 0.5))),
        sun=df.Sun(irradiance=2, zenith_deg=30, angular_radius_deg=0.27),
        shapes=(df.Box(min=(0.1, 0.1, 0.1), max=(0.2, 0.2, 0.2)),
                df.Mesh("tet", path="t.obj", scale=2, translate=(0.1, 0.1, 0.1), albedo=0.25),
                df.Quad(corners=[[0, 0, 0.9], [1, 0, 0.9], [1, 1, 0.9], [0, 1, 0.9]],
                        emission=1)),
        cameras=[df.Camera("", "perspective", position=(0.5, -1, 0.5), look_at=(0.5, 0.5, 0.5),
                           resolution=(8, 6), fov_deg=40)],
    )
    assert py == f.replace(source=None)
    assert [x.name for x in py.shapes] == ["box-1", "tet", "quad-3"]
    np.testing.assert_array_equal(py.fog.density, f.fog.density)
    np.testing.assert_array_equal(py.shape("tet").vertices, f.shape("tet").vertices)
    np.testing.assert_array_equal(py.shape("tet").faces, f.shape("tet").faces)
    v, fc = py.shape("tet").vertices, py.shape("tet").faces
    assert _tet_volume(v, fc) == pytest.approx(0.4**3 / 6)  # turned outwards, scaled
    np.testing.assert_allclose(v.min(0), [0.1, 0.1, 0.1])


def test_python_mesh_from_arrays():
    m = df.Mesh("tet", vertices=TET_V.tolist(), faces=TET_F, albedo=0.3)
    assert m.vertices.dtype == np.float64 and m.faces.dtype == np.int64
    assert m.vertices.shape == (4, 3) and m.faces.shape == (4, 3)
    assert _tet_volume(TET_V, TET_F) < 0 < _tet_volume(m.vertices, m.faces)  # wound outwards
    assert m.path == "" and m.scale == 1.0  # arrays are world space as given
    np.testing.assert_allclose(np.sort(m.vertices, 0), np.sort(TET_V, 0))
    # a cube given as arrays voxelizes as the box of the same bounds
    cube_v = np.array([[x, y, z] for x in (0.3, 0.7) for y in (0.35, 0.6) for z in (0.2, 0.5)])
    cube_f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                       [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    cube = df.Mesh("cube", vertices=cube_v, faces=cube_f)
    box = df.Box("cube", min=(0.3, 0.35, 0.2), max=(0.7, 0.6, 0.5))
    lat = df.voxelize(df.Scene(title="m", domain=UNIT, shapes=[cube]), 16, 1)
    ref = df.voxelize(df.Scene(title="b", domain=UNIT, shapes=[box]), 16, 1)
    np.testing.assert_array_equal(lat.node_type, ref.node_type)
    assert lat.counts()["solid"] == 6 * 4 * 5
    # outside the domain, open, or malformed: one line each
    with pytest.raises(SceneError, match=r"\[\[shape\]\] #1 'far' lies entirely outside"):
        df.Scene(title="m", domain=UNIT, shapes=[df.Mesh("far", vertices=TET_V + 5,
                                                         faces=TET_F)])
    with pytest.raises(SceneError, match=r"^difffog\.Mesh\('lid'\): vertices and faces are not "
                                         r"watertight: 3 boundary edges"):
        df.Mesh("lid", vertices=TET_V, faces=TET_F[:3])
    for v, f in [(TET_V[:, :2], TET_F), (TET_V, TET_F + 1), (TET_V, TET_F.astype(float)),
                 (TET_V, np.zeros((0, 3), int)), (np.where(TET_V > 0.4, np.nan, TET_V), TET_F)]:
        with pytest.raises(SceneError, match=r"^difffog\.Mesh\('bad'\): vertices and faces must "
                                             r"be \(V, 3\) finite floats and \(F, 3\) vertex "
                                             r"indices"):
            df.Mesh("bad", vertices=v, faces=f)
