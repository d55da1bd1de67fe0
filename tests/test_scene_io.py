"""Scene files: loading the shared scenes, overrides, and a corpus of bad files."""

import math
from pathlib import Path

import numpy as np
import pytest

from difffog._errors import SceneError
from difffog._scene_io import apply_overrides, builtin_scenes, load_scene, scalar_paths

HERE = Path(__file__).parent
BAD = HERE / "bad_scenes"
SHARED = Path(__file__).parents[1].parent / "shared" / "scenes"

# name -> (shapes, cameras)
SHARED_COUNTS = {
    "cloud-plane": (2, 2),
    "fog-balls": (4, 2),
    "furnace": (1, 1),
    "ring-box": (2, 2),
    "slab": (0, 1),
    "translucent-cube": (2, 2),
}


def _shared_files():
    if not SHARED.is_dir():
        return [pytest.param(None, marks=pytest.mark.skip(reason=f"{SHARED} is absent"))]
    return sorted(SHARED.glob("*.toml"))


def test_builtin_names():
    names = builtin_scenes()
    assert set(SHARED_COUNTS) <= set(names) and names == sorted(names)


@pytest.mark.parametrize("name", sorted(SHARED_COUNTS))
def test_builtin_scenes_load(name):
    s = load_scene(name)
    assert s.title == name
    assert (len(s.shapes), len(s.cameras)) == SHARED_COUNTS[name]
    assert s.source is not None and s.source.name == f"{name}.toml"


@pytest.mark.parametrize("path", _shared_files(), ids=lambda p: getattr(p, "stem", "absent"))
def test_shared_scene_files_load(path):
    s = load_scene(path)
    assert (len(s.shapes), len(s.cameras)) == SHARED_COUNTS[path.stem]
    shipped = load_scene(path.stem)  # the copy in the package says the same
    assert s.replace(source=None) == shipped.replace(source=None)
    for a, b in zip(s.shapes, shipped.shapes):
        if a.kind == "mesh":
            np.testing.assert_array_equal(a.vertices, b.vertices)


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
