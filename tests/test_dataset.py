"""Dataset folders and scene files (DESIGN §12).

Round trips are exact (angles included: the file holds the shortest degree value that reads
back to the same radians). Every kind of bad input is refused twice over: by the API, with an
InputError of one line naming the file, the field and the value; and by ``fsswarp check``,
with exit status 2, one line on stderr and nothing written.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import tomllib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import tifffile
import tomli_w
from hypothesis import given, settings
from hypothesis import strategies as st

from fsswarp.dataset import (BUILTIN_TARGETS, Dataset, Manifest, SurfaceEstimate, Target, Truth,
                             image_file, load_dataset, load_manifest, load_scene, manifest_to_toml,
                             parse_manifest, save_dataset, save_scene)
from fsswarp.errors import InputError
from fsswarp.rig import Rig, View
from fsswarp.sonar import SonarSpec
from fsswarp.surface import COMPONENTS

REPO = Path(__file__).resolve().parents[1]
BEAMS, BINS = 8, 16


# --- builders ----------------------------------------------------------------------------

def beam_angles_deg(beams: int = BEAMS) -> list[float]:
    """A lens-like (cubic) beam-angle table spanning about ±14.4°."""
    u = np.linspace(-1.0, 1.0, beams)
    return [float(a) for a in 14.4 * (0.8 * u + 0.2 * u**3)]


def make_manifest(*, table: bool = True, truth: bool = True, target: Target | None = None,
                  images: bool = True) -> Manifest:
    """Three views with nonzero offsets, a beam-angle table, the second view as reference."""
    rad = math.radians
    if table:
        deg = beam_angles_deg()
        sonar = SonarSpec(beams=BEAMS, bins=BINS, azimuth_fov=rad(deg[-1] - deg[0]), elevation_fov=rad(14.0),
                          range_min=0.8, range_max=3.2, beam_angles=np.array([rad(a) for a in deg]))
    else:
        sonar = SonarSpec(beams=BEAMS, bins=BINS, azimuth_fov=rad(28.8), elevation_fov=rad(14.0),
                          range_min=1.0, range_max=3.0)
    views = (
        View("a", position=(0.0, 0.0), heading=0.0, roll=rad(-45.0)),
        View("b", position=(0.5, -0.25), heading=rad(30.0), roll=rad(22.5), depth_offset=0.02,
             tilt_offset=rad(-1.5), optimize=False, image="frames/b-view.tif" if images else None),
        View("c", position=(1.0, 2.0), heading=rad(-90.0), roll=rad(67.5), depth_offset=-0.01,
             tilt_offset=rad(0.7)),
    )
    return Manifest(sonar=sonar, surface=SurfaceEstimate(depth=0.47, tilt=rad(11.1), depth_sigma=0.03,
                                                         tilt_sigma=rad(0.6)),
                    rig=Rig(views, reference=1),
                    truth=Truth(depth=0.43, tilt=rad(10.3)) if truth else None, target=target)


def make_images(manifest: Manifest, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    shape = (manifest.sonar.bins, manifest.sonar.beams)
    return {v.name: rng.random(shape, dtype=np.float32) * 10 for v in manifest.rig.views}


def listing(folder: Path) -> list[tuple[str, int, int]]:
    """Every file and folder under ``folder``: (relative path, size, mtime_ns)."""
    out = []
    for path in sorted(folder.rglob("*")):
        st_ = path.stat()
        out.append((str(path.relative_to(folder)), st_.st_size if path.is_file() else -1, st_.st_mtime_ns))
    return out


def same_manifest(a: Manifest, b: Manifest) -> bool:
    """Manifest equality (which includes the beam-angle table), checked field by field too."""
    angles_a, angles_b = a.sonar.beam_angles, b.sonar.beam_angles
    assert (angles_a is None) == (angles_b is None)
    if angles_a is not None:
        np.testing.assert_array_equal(angles_a, angles_b)
    assert (a.sonar, a.surface, a.rig, a.truth, a.target) == (b.sonar, b.surface, b.rig, b.truth, b.target)
    return a == b


# --- round trips -------------------------------------------------------------------------

def test_dataset_round_trip(tmp_path):
    import trimesh

    manifest = make_manifest()
    images = make_images(manifest)
    rng = np.random.default_rng(1)
    layers = {name: {c: rng.random((BINS, BEAMS), dtype=np.float32) for c in COMPONENTS} for name in ("a", "c")}
    mesh = trimesh.creation.box(extents=(0.2, 0.1, 0.05))
    folder = save_dataset(Dataset(manifest, images), tmp_path / "ds", truth_layers=layers, truth_mesh=mesh)

    loaded = load_dataset(folder)
    expected = replace(manifest, truth=replace(manifest.truth, model="truth/model.ply"))
    assert same_manifest(loaded.manifest, expected)  # exact: floats are not merely close
    assert loaded.root == folder
    assert list(loaded.images) == ["a", "b", "c"]  # rig order
    for name, image in images.items():
        assert loaded.images[name].dtype == np.float32
        assert loaded.images[name].tobytes() == image.tobytes()  # bit-identical
    for name, per_view in layers.items():
        for component, layer in per_view.items():
            assert loaded.truth_layer(name, component).tobytes() == layer.tobytes()
    model = trimesh.load_mesh(loaded.truth_model_path)
    np.testing.assert_allclose(np.sort(model.vertices, axis=0), np.sort(mesh.vertices, axis=0))
    assert loaded.truth_mesh().volume == pytest.approx(mesh.volume, rel=1e-6)
    assert sorted(p for p, _, _ in listing(folder) if (folder / p).is_file()) == sorted(
        ["dataset.toml", "images/a.tiff", "frames/b-view.tif", "images/c.tiff", "truth/model.ply"]
        + [f"truth/{v}_{c}.tiff" for v in ("a", "c") for c in COMPONENTS])
    assert sorted(os.listdir(tmp_path)) == ["ds"]  # no temporary folders left beside it


def test_tiff_bytes_encodes_each_image_under_its_key():
    """Encoded on threads: each key gets its own image's file, in the order given, the same
    bytes as tifffile writes alone; one image and none take the plain path."""
    import io

    from fsswarp.dataset import tiff_bytes

    rng = np.random.default_rng(3)
    images = {f"view{k}.tiff": rng.random((BINS, BEAMS), dtype=np.float32) * (k % 3) for k in range(12)}
    files = tiff_bytes(images)
    assert list(files) == list(images)
    for key, image in images.items():
        alone = io.BytesIO()
        tifffile.imwrite(alone, image, compression="zlib")
        assert files[key] == alone.getvalue()
        assert tifffile.imread(io.BytesIO(files[key])).tobytes() == image.tobytes()
    assert tiff_bytes({"one.tiff": images["view1.tiff"]}) == {"one.tiff": files["view1.tiff"]}
    assert tiff_bytes({}) == {}


def test_resaving_a_loaded_dataset_keeps_its_truth(tmp_path):
    import trimesh

    manifest = make_manifest(table=False)
    layers = {"b": {"ghost": np.full((BINS, BEAMS), 0.5, np.float32)}}
    save_dataset(Dataset(manifest, make_images(manifest)), tmp_path / "one", truth_layers=layers,
                 truth_mesh=trimesh.creation.box())
    again = save_dataset(load_dataset(tmp_path / "one"), tmp_path / "two")
    copy = load_dataset(again)
    assert copy.manifest == load_dataset(tmp_path / "one").manifest
    assert copy.truth_layer("b", "ghost").tobytes() == layers["b"]["ghost"].tobytes()
    assert copy.truth_model_path.read_bytes() == (tmp_path / "one/truth/model.ply").read_bytes()
    with pytest.raises(InputError, match="truth"):
        copy.truth_layer("a", "ghost")
    save_dataset(copy, again)  # in place: read everything, then replace the folder
    assert load_dataset(again).truth_layer("b", "ghost").tobytes() == layers["b"]["ghost"].tobytes()
    assert sorted(os.listdir(tmp_path)) == ["one", "two"]


def test_save_takes_any_valid_manifest(tmp_path):
    """Lists for tuples and radians that no degree value gives (atan2) are fine; such an angle
    reads back within an ulp."""
    base = make_manifest()
    heading = math.atan2(1.0, 3.0)
    view = View("a", position=[0.25, 0.5], heading=heading, roll=0.1)
    manifest = replace(base, rig=Rig((view,) + base.rig.views[1:], reference=1))
    loaded = load_dataset(save_dataset(Dataset(manifest, make_images(manifest)), tmp_path / "ds")).manifest
    assert loaded.rig.views[0].position == (0.25, 0.5)
    assert abs(loaded.rig.views[0].heading - heading) <= math.ulp(heading)
    assert loaded.rig.views[1:] == manifest.rig.views[1:]


def test_truth_layer_refuses_unknown_names(tmp_path):
    manifest = make_manifest()
    dataset = load_dataset(save_dataset(Dataset(manifest, make_images(manifest)), tmp_path / "ds"))
    with pytest.raises(InputError, match="component = 'shadow'"):
        dataset.truth_layer("a", "shadow")
    with pytest.raises(InputError, match="view = 'zz'"):
        dataset.truth_layer("zz", "object")
    with pytest.raises(InputError, match=r"a_object"):
        dataset.truth_layer("a", "object")
    with pytest.raises(InputError, match="not loaded from a folder"):
        Dataset(manifest, make_images(manifest)).truth_layer("a", "object")


def test_derived_results_are_computed_once_per_dataset_and_images_are_read_only():
    """The reconstruction loop keeps results derived from the images on the dataset: a key is
    computed once; another dataset (even of the same images) computes its own; the images
    can no longer change under a kept result."""
    manifest = make_manifest()
    images = make_images(manifest)
    dataset = Dataset(manifest, images)
    calls = []

    def compute(name):
        calls.append(name)
        return float(dataset.images[name].sum())

    first = dataset.derived(("sum", "a"), lambda: compute("a"))
    assert dataset.derived(("sum", "a"), lambda: compute("a")) == first == float(images["a"].sum())
    dataset.derived(("sum", "b"), lambda: compute("b"))
    assert calls == ["a", "b"]
    replace(dataset, root=None).derived(("sum", "a"), lambda: compute("a"))
    assert calls == ["a", "b", "a"]
    with pytest.raises(ValueError, match="read-only"):
        dataset.images["a"][0, 0] = 1.0


def test_scene_round_trip(tmp_path):
    target = Target(position=(0.1, 2.0, -0.3), mesh="meshes/rock.ply", scale=0.01,
                    rotation=(math.radians(90.0), 0.0, math.radians(-12.5)))
    manifest = make_manifest(target=target, images=False)
    path = save_scene(manifest, tmp_path / "scene.toml")
    import trimesh

    (tmp_path / "meshes").mkdir()
    trimesh.creation.box().export(tmp_path / "meshes/rock.ply")
    assert same_manifest(load_scene(path), manifest)
    assert load_scene(path).target.mesh_path(path.parent) == tmp_path / "meshes/rock.ply"
    assert sorted(os.listdir(tmp_path)) == ["meshes", "scene.toml"]

    builtin = replace(manifest, target=Target(position=(0.0, 2.0, -0.1), builtin="table"))
    assert load_scene(save_scene(builtin, tmp_path / "table.toml")) == builtin


def test_builtin_scenes_round_trip(tmp_path):
    from fsswarp.scenes import builtin_scene

    manifest = builtin_scene("coral-one")
    assert load_scene(save_scene(manifest, tmp_path / "coral.toml")) == manifest


def test_file_holds_short_degrees_and_defaults_apply():
    text = manifest_to_toml(make_manifest(table=False))
    assert "tilt_deg = 10.3\n" in text and "roll_deg = -45.0\n" in text and "azimuth_fov_deg = 28.8\n" in text
    table = tomllib.loads(text)
    for key in ("depth_sigma_m", "tilt_sigma_deg"):
        del table["surface"][key]
    for view in table["views"]:
        for key in ("depth_offset_m", "tilt_offset_deg", "optimize"):
            view.pop(key)
    del table["rig"]
    manifest = parse_manifest(table, file="x.toml")
    assert manifest.surface.depth_sigma == 0.05 and manifest.surface.tilt_sigma == math.radians(2.0)
    assert manifest.rig.reference == 0
    assert all(v.depth_offset == 0 and v.tilt_offset == 0 and v.optimize for v in manifest.rig.views)
    assert [image_file(v) for v in manifest.rig.views] == ["images/a.tiff", "frames/b-view.tif", "images/c.tiff"]


def test_manifest_equality_includes_beam_angles():
    a = make_manifest()
    angles = a.sonar.beam_angles.copy()
    angles[3] += 1e-9
    b = replace(a, sonar=replace(a.sonar, beam_angles=angles))
    assert a.sonar == b.sonar  # SonarSpec leaves the table out of its equality
    assert a != b


# --- property: manifest -> TOML -> manifest ----------------------------------------------

finite = dict(allow_nan=False, allow_infinity=False)
names = st.text(alphabet="abcXYZ019-_", min_size=1, max_size=6)


def degrees(lo, hi):
    return st.floats(lo, hi, **finite)


@st.composite
def manifests(draw) -> Manifest:
    """Random valid manifests whose angles come from degree values (as a file's do)."""
    rad = math.radians
    beams, bins = draw(st.integers(2, 12)), draw(st.integers(2, 64))
    range_min = draw(st.floats(0.0, 10.0, **finite))
    range_max = range_min + draw(st.floats(1e-3, 50.0, **finite))
    elevation = rad(draw(degrees(0.01, 179.0)))
    if draw(st.booleans()):
        steps = draw(st.lists(st.floats(0.1, 1.0, **finite), min_size=beams - 1, max_size=beams - 1))
        half = draw(degrees(0.5, 80.0))
        cum = np.concatenate([[0.0], np.cumsum(steps)])
        deg = [float(v) for v in -half + 2 * half * cum / cum[-1]]
        sonar = SonarSpec(beams=beams, bins=bins, azimuth_fov=rad(deg[-1] - deg[0]), elevation_fov=elevation,
                          range_min=range_min, range_max=range_max, beam_angles=np.array([rad(a) for a in deg]))
    else:
        sonar = SonarSpec(beams=beams, bins=bins, azimuth_fov=rad(draw(degrees(0.01, 179.0))),
                          elevation_fov=elevation, range_min=range_min, range_max=range_max)
    surface = SurfaceEstimate(depth=draw(st.floats(1e-4, 100.0, **finite)), tilt=rad(draw(degrees(-89.9, 89.9))),
                              depth_sigma=draw(st.floats(0.0, 1.0, **finite)),
                              tilt_sigma=rad(draw(degrees(0.0, 30.0))))
    view_names = draw(st.lists(names, min_size=1, max_size=4, unique=True))
    coord = st.floats(-100.0, 100.0, **finite)
    truth = draw(st.none() | st.builds(Truth, depth=st.floats(1e-4, 100.0, **finite),
                                       tilt=degrees(-89.9, 89.9).map(rad),
                                       model=st.sampled_from([None, "truth/model.ply"])))
    shallowest = min(surface.depth, truth.depth if truth is not None else math.inf, 1.0)
    offsets = st.floats(-shallowest, 1.0, exclude_min=True, **finite)  # every sonar below the surface
    views = tuple(View(name, position=(draw(coord), draw(coord)), heading=rad(draw(degrees(-360, 360))),
                       roll=rad(draw(degrees(-180, 180))), depth_offset=draw(offsets),
                       tilt_offset=rad(draw(degrees(-89.0, 89.0))), optimize=draw(st.booleans()),
                       image=draw(st.sampled_from([None, f"img/{name}.tif"])))
                  for name in view_names)
    target = None
    if draw(st.booleans()):
        source = draw(st.sampled_from([("mesh", "m.ply")] + [("builtin", b) for b in BUILTIN_TARGETS]))
        target = Target(position=(draw(coord), draw(coord), draw(st.floats(-100.0, -1e-6, **finite))),
                        scale=draw(st.floats(1e-6, 1e3, **finite)),
                        rotation=tuple(rad(draw(degrees(-360, 360))) for _ in range(3)), **dict([source]))
    return Manifest(sonar=sonar, surface=surface, rig=Rig(views, reference=draw(st.integers(0, len(views) - 1))),
                    truth=truth, target=target)


@settings(max_examples=80, deadline=None)
@given(manifests())
def test_manifest_toml_round_trip_is_exact(manifest):
    again = parse_manifest(tomllib.loads(manifest_to_toml(manifest)), file="prop.toml")
    assert same_manifest(again, manifest)


@settings(max_examples=80, deadline=None)
@given(st.floats(-1.5, 1.5, **finite), st.floats(-3.14, 3.14, **finite))
def test_any_radian_value_settles_after_one_trip(tilt, roll):
    """A radian value that no degree value maps to moves by at most an ulp, once."""
    base = make_manifest(table=False)
    manifest = replace(base, surface=replace(base.surface, tilt=tilt),
                       rig=Rig((replace(base.rig.views[0], roll=roll),) + base.rig.views[1:]))
    once = parse_manifest(tomllib.loads(manifest_to_toml(manifest)), file="x.toml")
    assert abs(once.surface.tilt - tilt) <= math.ulp(tilt)
    assert abs(once.rig.views[0].roll - roll) <= math.ulp(roll)
    twice = parse_manifest(tomllib.loads(manifest_to_toml(once)), file="x.toml")
    assert twice == once


# --- bad input: the cases ----------------------------------------------------------------

def dataset_table() -> dict:
    return {
        "sonar": {"beams": BEAMS, "bins": BINS, "azimuth_fov_deg": 28.8, "elevation_fov_deg": 14.0,
                  "range_min_m": 1.0, "range_max_m": 3.0},
        "surface": {"depth_m": 0.45, "tilt_deg": 10.5},
        "truth": {"depth_m": 0.43, "tilt_deg": 10.3},
        "rig": {"reference_view": "a"},
        "views": [
            {"name": "a", "position_m": [0.0, 0.0], "heading_deg": 0.0, "roll_deg": -45.0},
            {"name": "b", "position_m": [0.0, 4.0], "heading_deg": 180.0, "roll_deg": 22.5, "optimize": False},
            {"name": "c", "image": "images/c.tiff", "position_m": [0.5, 0.0], "heading_deg": 10.0,
             "roll_deg": 67.5, "depth_offset_m": 0.05, "tilt_offset_deg": 1.0},
        ],
    }


def scene_table() -> dict:
    table = dataset_table()
    del table["views"][2]["image"]
    table["target"] = {"builtin": "coral-one", "position_m": [0.0, 2.0, -0.1]}
    return table


def good_image() -> np.ndarray:
    return np.random.default_rng(3).random((BINS, BEAMS), dtype=np.float32)


@dataclass(frozen=True)
class Bad:
    """One kind of bad input: ``edit(table, folder)`` spoils a good dataset or scene; the error
    must name ``file`` (relative to the case folder), ``field`` and ``value``."""

    id: str
    edit: Callable[[dict, Path], None]
    field: str
    value: str | None = None
    file: str = "dataset.toml"
    scene: bool = False
    text: Callable[[str], str] | None = None  # edit of the TOML text, after writing


def _set(path: str, value):
    """An edit that sets ``a.b`` or ``views[1].c`` to ``value`` (None deletes)."""
    def edit(table: dict, folder: Path) -> None:
        node, parts = table, path.replace("]", "").replace("[", ".").split(".")
        for part in parts[:-1]:
            node = node[int(part)] if part.isdigit() else node[part]
        if value is None:
            del node[parts[-1]]
        else:
            node[parts[-1]] = value
    return edit


def _image(name: str, array=None, raw: bytes | None = None, pages: int = 0):
    """An edit that replaces (or, with no argument, deletes) ``images/<name>.tiff``; ``pages``
    appends that many good images as separate series (a reader of the first series alone
    would not notice the others)."""
    def edit(table: dict, folder: Path) -> None:
        path = folder / "images" / f"{name}.tiff"
        if raw is not None:
            path.write_bytes(raw)
        elif array is not None:
            tifffile.imwrite(path, array)
        elif pages:
            path.unlink()
            for _ in range(pages):
                tifffile.imwrite(path, good_image(), append=True)
        else:
            path.unlink()
    return edit


def _both(*edits):
    def edit(table, folder):
        for e in edits:
            e(table, folder)
    return edit


def _mesh_file(table, folder):
    import trimesh

    trimesh.creation.box().export(folder / "rock.ply")


nan_image = good_image()
nan_image[2, 3] = np.nan
skewed = beam_angles_deg()
skewed[4], skewed[5] = skewed[5], skewed[4]

BAD = [
    Bad("unknown-top-level-table", _set("extras", {"a": 1}), "extras", "{'a': 1}"),
    Bad("unknown-key-in-sonar", _set("sonar.bemas", 8), "sonar.bemas", "8"),
    Bad("unknown-key-in-a-view", _set("views[1].rol_deg", 5.0), "views[1].rol_deg", "5.0"),
    Bad("unknown-key-in-rig", _set("rig.reference", "a"), "rig.reference", "'a'"),
    Bad("table-not-a-table", _set("sonar", 3), "sonar", "3"),
    Bad("beams-not-an-integer", _set("sonar.beams", 8.0), "sonar.beams", "8.0"),
    Bad("beams-zero", _set("sonar.beams", 0), "sonar.beams", "0"),
    Bad("bool-as-number", _set("views[0].heading_deg", True), "views[0].heading_deg", "True"),
    Bad("string-as-number", _set("views[2].roll_deg", "abc"), "views[2].roll_deg", "'abc'"),
    Bad("nan", _set("surface.depth_m", math.nan), "surface.depth_m", "nan"),
    Bad("inf", _set("sonar.range_max_m", math.inf), "sonar.range_max_m", "inf"),
    Bad("range-max-not-above-min", _set("sonar.range_max_m", 0.5), "sonar.range_max_m", "0.5"),
    Bad("negative-depth", _set("surface.depth_m", -0.4), "surface.depth_m", "-0.4"),
    Bad("tilt-95-degrees", _set("surface.tilt_deg", 95.0), "surface.tilt_deg", "95"),
    Bad("negative-sigma", _set("surface.tilt_sigma_deg", -1.0), "surface.tilt_sigma_deg", "-1.0"),
    Bad("elevation-fov-180", _set("sonar.elevation_fov_deg", 180.0), "sonar.elevation_fov_deg", "180"),
    Bad("missing-sonar", _set("sonar", None), "sonar"),
    Bad("missing-surface-depth", _set("surface.depth_m", None), "surface.depth_m"),
    Bad("missing-view-name", _set("views[1].name", None), "views[1].name"),
    Bad("bad-view-name", _set("views[0].name", "a/b"), "views[0].name", "'a/b'"),
    Bad("duplicate-view-names", _set("views[2].name", "a"), "views[2].name", "'a'"),
    Bad("no-views", _set("views", []), "views", "[]"),
    Bad("reference-view-names-no-view", _set("rig.reference_view", "zz"), "rig.reference_view", "'zz'"),
    Bad("position-with-3-numbers", _set("views[0].position_m", [0.0, 0.0, 1.0]), "views[0].position_m",
        "[0.0, 0.0, 1.0]"),
    Bad("optimize-not-a-bool", _set("views[1].optimize", "no"), "views[1].optimize", "'no'"),
    Bad("beam-angles-wrong-length", _set("sonar.beam_angles_deg", beam_angles_deg(BEAMS - 1)),
        "sonar.beam_angles_deg", "7 angles"),
    Bad("beam-angles-not-increasing", _set("sonar.beam_angles_deg", skewed), "sonar.beam_angles_deg"),
    Bad("toml-syntax-error", lambda t, f: None, "line", text=lambda s: s.replace("[surface]", "[surface", 1)),
    Bad("image-path-leaves-folder", _set("views[2].image", "../c.tiff"), "views[2].image", "'../c.tiff'"),
    Bad("image-file-missing", _image("b"), "views[1].image", "'images/b.tiff'"),
    Bad("image-wrong-shape", _image("b", np.zeros((BINS, BEAMS + 1), np.float32)), "views[1].image",
        f"({BINS}, {BEAMS + 1})", file="images/b.tiff"),
    Bad("image-float64", _image("b", np.zeros((BINS, BEAMS), np.float64)), "views[1].image", "'float64'",
        file="images/b.tiff"),
    Bad("image-with-nan", _image("c", nan_image), "views[2].image", "1 NaN", file="images/c.tiff"),
    Bad("image-not-a-tiff", _image("a", raw=b"not a tiff at all"), "views[0].image", file="images/a.tiff"),
    Bad("image-of-two-pages", _image("a", pages=2), "views[0].image", "'2 pages'", file="images/a.tiff"),
    Bad("truth-model-missing", _set("truth.model", "truth/model.ply"), "truth.model", "'truth/model.ply'"),
    # scene files
    Bad("scene-mesh-and-builtin", _both(_mesh_file, _set("target.mesh", "rock.ply")), "target.mesh",
        "'rock.ply'", file="scene.toml", scene=True),
    Bad("scene-unknown-builtin", _set("target.builtin", "coral-three"), "target.builtin", "'coral-three'",
        file="scene.toml", scene=True),
    Bad("scene-without-truth", _set("truth", None), "truth", file="scene.toml", scene=True),
    Bad("scene-without-target", _set("target", None), "target", file="scene.toml", scene=True),
    Bad("scene-with-an-image", _set("views[0].image", "images/a.tiff"), "views[0].image", "'images/a.tiff'",
        file="scene.toml", scene=True),
    Bad("scene-mesh-file-missing", _both(_set("target.builtin", None), _set("target.mesh", "rock.ply")),
        "target.mesh", "'rock.ply'", file="scene.toml", scene=True),
    Bad("scene-target-above-surface", _set("target.position_m", [0.0, 2.0, 0.3]), "target.position_m", "0.3",
        file="scene.toml", scene=True),
    Bad("scene-scale-zero", _set("target.scale_m", 0), "target.scale_m", "0", file="scene.toml", scene=True),
    Bad("scene-unknown-key-in-target", _set("target.colour", "red"), "target.colour", "'red'",
        file="scene.toml", scene=True),
]
assert len({case.id for case in BAD}) == len(BAD)


def build_case(case: Bad, root: Path) -> Path:
    """Write the case into ``root/<id>``; returns the path to give ``fsswarp check``."""
    folder = root / case.id
    (folder / "images").mkdir(parents=True)
    table = scene_table() if case.scene else dataset_table()
    if case.scene:
        (folder / "images").rmdir()
    else:
        for name in ("a", "b", "c"):
            tifffile.imwrite(folder / "images" / f"{name}.tiff", good_image())
    case.edit(table, folder)
    text = tomli_w.dumps(table)
    if case.text is not None:
        text = case.text(text)
    path = folder / ("scene.toml" if case.scene else "dataset.toml")
    path.write_text(text)
    return path if case.scene else folder


def check_message(message: str, case: Bad, folder: Path) -> None:
    assert "\n" not in message and message.strip() == message and message
    assert str(folder / case.file) in message
    assert case.field in message
    if case.value is not None:
        assert case.value in message


@pytest.mark.parametrize("case", BAD, ids=lambda c: c.id)
def test_bad_input_is_refused_by_the_api(case, tmp_path):
    path = build_case(case, tmp_path)
    before = listing(tmp_path)
    with pytest.raises(InputError) as info:
        load_scene(path) if case.scene else load_dataset(path)
    check_message(str(info.value), case, tmp_path / case.id)
    assert listing(tmp_path) == before


@pytest.fixture(scope="module")
def cli_runs(tmp_path_factory):
    """``fsswarp check`` on every bad case, the runs in parallel (each starts Python)."""
    root = tmp_path_factory.mktemp("cli")
    paths = {case.id: build_case(case, root) for case in BAD}
    before = listing(root)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))

    def run(path: Path) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "fsswarp", "check", str(path)], capture_output=True,
                              text=True, timeout=120, cwd=root, env=env)

    with ThreadPoolExecutor(max_workers=max(2, os.cpu_count() or 2)) as pool:
        runs = dict(zip(paths, pool.map(run, paths.values())))
    return root, runs, before, listing(root)


@pytest.mark.parametrize("case", BAD, ids=lambda c: c.id)
def test_bad_input_is_refused_by_the_command_line(case, cli_runs):
    root, runs, before, after = cli_runs
    run = runs[case.id]
    assert "Traceback" not in run.stderr, run.stderr
    lines = run.stderr.splitlines()
    assert run.returncode == 2, run.stderr
    assert len(lines) == 1 and lines[0].strip(), run.stderr
    assert lines[0].startswith("fsswarp: error: ")
    check_message(lines[0].removeprefix("fsswarp: error: "), case, root / case.id)
    prefix = case.id + os.sep
    assert [e for e in after if e[0] == case.id or e[0].startswith(prefix)] == \
        [e for e in before if e[0] == case.id or e[0].startswith(prefix)]


def test_command_line_accepts_the_good_inputs(tmp_path):
    manifest = make_manifest()
    folder = save_dataset(Dataset(manifest, make_images(manifest)), tmp_path / "ds")
    scene = save_scene(make_manifest(target=Target(position=(0.0, 2.0, -0.1), builtin="table"), images=False),
                       tmp_path / "scene.toml")
    env = dict(os.environ, PYTHONPATH=str(REPO))
    for path in (folder, scene):
        run = subprocess.run([sys.executable, "-m", "fsswarp", "check", str(path)], capture_output=True,
                             text=True, timeout=120, env=env)
        assert run.returncode == 0, run.stderr


# --- saving: all or nothing --------------------------------------------------------------

def _spoil(images: dict, name: str, value):
    out = dict(images)
    if value is None:
        del out[name]
    else:
        out[name] = value
    return out


SAVE_FAILURES = {
    "image-with-nan": (lambda im: _spoil(im, "b", np.full((BINS, BEAMS), np.nan, np.float32)), None, "NaN"),
    "image-wrong-shape": (lambda im: _spoil(im, "a", np.zeros((BEAMS, BINS), np.float32)), None, "shape"),
    "image-float64": (lambda im: _spoil(im, "c", np.zeros((BINS, BEAMS))), None, "float64"),
    "image-missing": (lambda im: _spoil(im, "c", None), None, "no image"),
    "image-of-no-view": (lambda im: _spoil(im, "zz", np.zeros((BINS, BEAMS), np.float32)), None, "'zz'"),
    "truth-layer-unknown-component": (lambda im: im, {"a": {"shadow": np.zeros((BINS, BEAMS), np.float32)}},
                                      "'shadow'"),
    "truth-layer-wrong-shape": (lambda im: im, {"a": {"ghost": np.zeros((BINS, 2), np.float32)}}, "shape"),
    "truth-layer-of-no-view": (lambda im: im, {"zz": {}}, "'zz'"),
}


@pytest.mark.parametrize("kind", SAVE_FAILURES)
def test_failed_save_writes_nothing(kind, tmp_path):
    spoil, layers, text = SAVE_FAILURES[kind]
    manifest = make_manifest()
    with pytest.raises(InputError, match=text) as info:
        save_dataset(Dataset(manifest, spoil(make_images(manifest))), tmp_path / "ds", truth_layers=layers)
    assert "\n" not in str(info.value)
    assert os.listdir(tmp_path) == []  # neither the folder nor a temporary one beside it


def test_truth_needs_a_truth_table(tmp_path):
    import trimesh

    manifest = make_manifest(truth=False)
    with pytest.raises(InputError, match="truth"):
        save_dataset(Dataset(manifest, make_images(manifest)), tmp_path / "ds", truth_mesh=trimesh.creation.box())
    with_model = make_manifest()
    with_model = replace(with_model, truth=replace(with_model.truth, model="truth/model.ply"))
    with pytest.raises(InputError, match="truth.model"):
        save_dataset(Dataset(with_model, make_images(with_model)), tmp_path / "ds")
    assert os.listdir(tmp_path) == []


def test_save_refuses_an_unrelated_folder(tmp_path):
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "notes.txt").write_text("keep me")
    before = listing(tmp_path)
    manifest = make_manifest()
    with pytest.raises(InputError, match="not an fsswarp output"):
        save_dataset(Dataset(manifest, make_images(manifest)), folder)
    assert listing(tmp_path) == before
    assert (folder / "notes.txt").read_text() == "keep me"


def test_output_folder_under_a_file_is_an_input_error(tmp_path):
    from fsswarp.atomic import check_output_folder, output_folder, write_text

    (tmp_path / "file").write_text("a file")
    for path in (tmp_path / "file" / "out", tmp_path / "file" / "deeper" / "out"):
        with pytest.raises(InputError, match="cannot be created: .*file is not a folder"):
            check_output_folder(path, marker="x.json")
        with pytest.raises(InputError, match="cannot be created"):
            with output_folder(path, marker="x.json"):
                raise AssertionError("the block must not run")
    assert check_output_folder(tmp_path / "new" / "deeper", marker="x.json") == tmp_path / "new" / "deeper"
    with pytest.raises(InputError, match=r"x\.toml: cannot be written: .*file is not a folder"):
        write_text(tmp_path / "file" / "x.toml", "a = 1\n")
    assert sorted(os.listdir(tmp_path)) == ["file"]


@pytest.mark.parametrize("spoil, where, message", [
    ("negative-pixel", "images/a.tiff", "must be linear intensity >= 0"),
    ("truth-layer-garbage", "truth/a_ghost.tiff", ""),
    ("truth-layer-shape", "truth/a_ghost.tiff", "shape must be"),
])
def test_check_reads_every_image_and_truth_layer(tmp_path, spoil, where, message):
    """``fsswarp check`` refuses what the commands would: a negative pixel (intensities are
    linear, >= 0) and a truth layer that cannot be read or has the wrong shape, naming the
    file, with exit 2; the intact dataset reports its truth layers."""
    import tifffile

    manifest = make_manifest()
    layers = {"a": {"ghost": np.zeros((BINS, BEAMS), np.float32)}}
    folder = save_dataset(Dataset(manifest, make_images(manifest)), tmp_path / "ds", truth_layers=layers)
    done = subprocess.run([sys.executable, "-m", "fsswarp", "check", str(folder)], capture_output=True, text=True)
    assert done.returncode == 0 and "1 truth layers" in done.stdout, done.stderr
    path = folder / where
    if spoil == "negative-pixel":
        image = tifffile.imread(path)
        image[3, 2] = -1.0
        tifffile.imwrite(path, image)
    elif spoil == "truth-layer-garbage":
        path.write_bytes(b"not a tiff")
    else:
        tifffile.imwrite(path, np.zeros((BINS, 2), np.float32))
    done = subprocess.run([sys.executable, "-m", "fsswarp", "check", str(folder)], capture_output=True, text=True)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    assert str(path) in lines[0] and message in lines[0]


def test_scene_files_replace_scene_files_only(tmp_path):
    """save_scene (fsswarp scene --out) replaces an earlier scene file but refuses a dataset's
    manifest or any other file, which it would have overwritten silently."""
    manifest = make_manifest(target=Target(position=(0.0, 2.0, -0.1), builtin="table"), images=False)
    path = save_scene(manifest, tmp_path / "scene.toml")
    save_scene(manifest, path)  # an earlier scene file
    dataset = save_dataset(Dataset(make_manifest(), make_images(make_manifest())), tmp_path / "ds")
    for other in (dataset / "dataset.toml", tmp_path / "notes.toml"):
        if not other.exists():
            other.write_text("not = 'a scene'\n")
        before = other.read_bytes()
        with pytest.raises(InputError, match="exists and is not a scene file"):
            save_scene(manifest, other)
        assert other.read_bytes() == before


def test_outputs_follow_the_umask_like_any_other_file(tmp_path):
    """mkdtemp and mkstemp make 0700 folders and 0600 files; the outputs get the modes the
    user's umask gives a plain mkdir and open (0755 and 0644 under umask 022)."""
    from fsswarp.atomic import output_folder, write_text

    old = os.umask(0o022)
    try:
        with output_folder(tmp_path / "out", marker="x.json") as tmp:
            (tmp / "x.json").write_text("{}")
        write_text(tmp_path / "x.toml", "a = 1\n")
        os.umask(0o077)
        write_text(tmp_path / "private.toml", "a = 1\n")
    finally:
        os.umask(old)
    assert (tmp_path / "out").stat().st_mode & 0o777 == 0o755
    assert (tmp_path / "x.toml").stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "private.toml").stat().st_mode & 0o777 == 0o600


def test_an_output_given_as_a_link_goes_where_the_link_points(tmp_path):
    """--out a symbolic link to a folder (an output kept on another disk) writes into the
    folder it points to, and the link stays a link; replacing an earlier output there too."""
    from fsswarp.atomic import output_folder

    target = tmp_path / "disk" / "out"
    target.mkdir(parents=True)
    link = tmp_path / "out"
    link.symlink_to(target, target_is_directory=True)
    for text in ("{}", '{"again": 1}'):
        with output_folder(link, marker="x.json") as tmp:
            (tmp / "x.json").write_text(text)
        assert link.is_symlink() and (target / "x.json").read_text() == text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["disk", "out"]
    assert [p.name for p in (tmp_path / "disk").iterdir()] == ["out"]


def test_output_folder_refuses_the_current_folder_and_what_cannot_be_replaced(tmp_path, monkeypatch):
    """--out "." (or "", or a folder above it) would be renamed away from under the shell,
    and an existing folder that is not writable cannot be moved aside: both are refused
    before any work; a replacement that fails anyway leaves the old folder and no temporary
    one; a name too long is an InputError; write_bytes onto a folder names it."""
    from fsswarp import atomic
    from fsswarp.atomic import check_output_folder, output_folder, write_text

    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    for value in (".", "", str(here), str(tmp_path)):
        with pytest.raises(InputError, match="current folder"):
            check_output_folder(value, marker="x.json")
    with pytest.raises(InputError, match="cannot be used: File name too long"):
        check_output_folder(tmp_path / ("n" * 300), marker="x.json")
    locked = tmp_path / "locked"
    locked.mkdir()
    real_access = os.access
    monkeypatch.setattr(atomic.os, "access", lambda p, mode: Path(p) != locked and real_access(p, mode))
    with pytest.raises(InputError, match="not writable, so it cannot be replaced"):
        check_output_folder(locked, marker="x.json")
    monkeypatch.setattr(atomic.os, "access", real_access)
    real_replace = os.replace

    def refuse_the_old(src, dst):
        if Path(src) == locked:
            raise PermissionError(13, "Permission denied")
        return real_replace(src, dst)

    monkeypatch.setattr(atomic.os, "replace", refuse_the_old)
    with pytest.raises(InputError, match="cannot be replaced: Permission denied"):
        with output_folder(locked, marker="x.json") as tmp:
            (tmp / "x.json").write_text("{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["here", "locked"] and not any(locked.iterdir())
    with pytest.raises(InputError, match="is a folder"):
        write_text(locked, "a = 1\n")


@pytest.mark.parametrize("content, message", [(b"not a mesh", "cannot read mesh"),
                                              (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty double x\n"
                                               b"property double y\nproperty double z\nelement face 1\n"
                                               b"property list uchar int vertex_indices\nend_header\n"
                                               b"0 0 0\nnan 1 0\n0 0 1e39\n3 0 1 2\n", "has 2 vertices that are not"),
                                              (b"ply\nformat ascii 1.0\nend_header\n", "")])
def test_truth_mesh_names_an_unreadable_truth_model(tmp_path, content, message):
    import trimesh

    manifest = make_manifest()
    folder = save_dataset(Dataset(manifest, make_images(manifest)), tmp_path / "ds",
                          truth_mesh=trimesh.creation.box())
    (folder / "truth" / "model.ply").write_bytes(content)
    with pytest.raises(InputError, match=f"dataset.toml: truth.model = .*model.ply.*: {message}") as caught:
        load_dataset(folder).truth_mesh()
    assert "\n" not in str(caught.value)
    assert load_dataset(tmp_path / "ds").manifest == load_dataset(folder).manifest  # loading alone still works


def test_save_replaces_an_earlier_dataset(tmp_path):
    manifest = make_manifest()
    folder = save_dataset(Dataset(manifest, make_images(manifest, seed=1)), tmp_path / "ds")
    assert (folder / "frames/b-view.tif").is_file()
    smaller = replace(manifest, rig=Rig(manifest.rig.views[:1]))
    save_dataset(Dataset(smaller, make_images(smaller, seed=2)), folder)
    loaded = load_dataset(folder)
    assert loaded.manifest == smaller
    assert loaded.images["a"].tobytes() == make_images(smaller, seed=2)["a"].tobytes()
    assert not (folder / "frames").exists()  # nothing of the old dataset is left
    assert sorted(os.listdir(tmp_path)) == ["ds"]


def test_save_scene_refuses_a_manifest_that_is_no_scene(tmp_path):
    target = Target(position=(0.0, 2.0, -0.1), builtin="coral-two")
    for manifest, field in ((make_manifest(images=False), "target"),
                            (make_manifest(target=target), "views[1].image"),
                            (make_manifest(target=target, truth=False, images=False), "truth")):
        with pytest.raises(InputError, match=re.escape(field)):
            save_scene(manifest, tmp_path / "scene.toml")
    assert os.listdir(tmp_path) == []


def test_loaders_name_a_missing_manifest(tmp_path):
    with pytest.raises(InputError, match="no dataset.toml"):
        load_dataset(tmp_path)
    with pytest.raises(InputError, match="no such folder"):
        load_dataset(tmp_path / "nowhere")
    with pytest.raises(InputError, match="file not found"):
        load_manifest(tmp_path / "scene.toml")
    with pytest.raises(InputError, match="is a folder"):
        load_scene(tmp_path)


def test_a_long_value_keeps_its_end_in_the_message():
    """A long path is elided in the middle, so the file's name stays in the one line."""
    path = "/tmp/" + "deep/" * 30 + "none.ply"
    text = str(InputError("no such mesh file", field="--initial-model", value=path))
    assert text.startswith("--initial-model = '/tmp/deep/") and "none.ply'" in text
    assert "..." in text and len(text) < 100
    assert str(InputError("bad", field="x", value="short")) == "x = 'short': bad"


def test_json_number_writes_none_where_json_has_no_number():
    from fsswarp.atomic import json_number

    assert [json_number(v) for v in (1.5, np.float32(2.0), 0, math.nan, math.inf, -math.inf)] == \
        [1.5, 2.0, 0.0, None, None, None]
    assert type(json_number(np.float64(0.25))) is float
