"""Every input wrong in the ways users get it wrong: one message naming the
file and the problem, exit code 2, and nothing written (issue 29).

Each case copies the 16-image sample (symlinks for the images), spoils one
input and runs ``obliq-colmap register`` as a user does. The cases stop
before any image is processed, so the module is fast.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from obliq_colmap.cadastre.read import Feature, parse_feature
from obliq_colmap.cli import main
from obliq_colmap.errors import InputError

SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "oblique_small"


def _scene(tmp_path: Path) -> Path:
    scene = tmp_path / "scene"
    (scene / "images").mkdir(parents=True)
    for image in (SAMPLE / "images").iterdir():
        (scene / "images" / image.name).symlink_to(image)
    shutil.copytree(SAMPLE / "priors", scene / "priors")
    shutil.copy(SAMPLE / "cadastre.geojson", scene / "cadastre.geojson")
    return scene


def _run(scene: Path, out: Path, *extra: str) -> int:
    """The command's exit code (argparse and option errors exit directly)."""
    try:
        return _main(scene, out, *extra)
    except SystemExit as exc:
        return int(exc.code)


def _main(scene: Path, out: Path, *extra: str) -> int:
    return main(
        [
            "register",
            "--image_path", str(scene / "images"),
            "--cadastre_path", str(scene / "cadastre.geojson"),
            "--input_path", str(scene / "priors"),
            "--output_path", str(out),
            "--no_progress",
            *extra,
        ]
    )  # fmt: skip


def _map(scene: Path, edit) -> None:
    path = scene / "cadastre.geojson"
    doc = json.loads(path.read_text())
    path.write_text(json.dumps(edit(doc)))


def _lonlat_keeping_crs(doc: dict) -> dict:
    """The map reprojected to longitude / latitude, its 'crs' member (EPSG:25832)
    left as it was."""
    import pyproj

    to_lonlat = pyproj.Transformer.from_crs("EPSG:25832", "EPSG:4326", always_xy=True)

    def move(c):
        if isinstance(c[0], (int, float)):
            return list(to_lonlat.transform(c[0], c[1]))
        return [move(v) for v in c]

    for f in doc["features"]:
        f["geometry"]["coordinates"] = move(f["geometry"]["coordinates"])
    return doc


def _shift_map(doc: dict, dx: float) -> dict:
    def shift(c):
        return (
            [c[0] + dx, *c[1:]]
            if isinstance(c[0], (int, float))
            else [shift(v) for v in c]
        )

    for f in doc["features"]:
        f["geometry"]["coordinates"] = shift(f["geometry"]["coordinates"])
    return doc


def _fisheye_priors(scene: Path) -> None:
    rec = pycolmap.Reconstruction(str(scene / "priors"))
    for cid, cam in list(rec.cameras.items()):
        rec.cameras[cid] = pycolmap.Camera(
            model="OPENCV_FISHEYE",
            width=cam.width,
            height=cam.height,
            params=[
                cam.params[0],
                cam.params[0],
                cam.params[1],
                cam.params[2],
                0,
                0,
                0,
                0,
            ],
            camera_id=cid,
        )
    rec.write(str(scene / "priors"))


def _rename_images(scene: Path) -> None:
    for image in (scene / "images").iterdir():
        image.rename(image.with_name("x_" + image.name))


def _truncate_images(scene: Path) -> None:
    for image in (scene / "images").iterdir():
        data = image.read_bytes()
        image.unlink()  # a link to the sample's image: never write through it
        image.write_bytes(data[: int(0.4 * len(data))])


CASES = {
    "missing image folder": (
        lambda s: shutil.rmtree(s / "images"),
        "images",
        (),
    ),
    "image names not in the priors": (_rename_images, "images", ()),
    "every image truncated": (
        _truncate_images,
        "none of its 16 images can be read",
        (),
    ),
    "missing map": (lambda s: (s / "cadastre.geojson").unlink(), "cadastre", ()),
    "map not JSON": (
        lambda s: (s / "cadastre.geojson").write_text("{not json"),
        "not valid JSON",
        (),
    ),
    "map of lines": (
        lambda s: _map(
            s,
            lambda d: {
                **d,
                "features": [
                    {
                        "type": "Feature",
                        "properties": {},
                        "geometry": {
                            "type": "LineString",
                            "coordinates": [
                                [500000.0, 5600000.0],
                                [500010.0, 5600000.0],
                            ],
                        },
                    }
                ]
                * 20,
            },
        ),
        "20 with geometry type 'LineString'",
        (),
    ),
    "longitude/latitude crs over projected coordinates": (
        lambda s: _map(s, lambda d: {**d, "crs": "EPSG:4326"}),
        "longitude/latitude but its coordinates",
        (),
    ),
    "longitude/latitude under a projected crs member": (
        lambda s: _map(s, _lonlat_keeping_crs),
        "look like longitude/latitude",
        (),
    ),
    "map 500 km from the cameras": (
        lambda s: _map(s, lambda d: _shift_map(d, 500_000.0)),
        "cadastre",
        (),
    ),
    "priors with non-perspective cameras": (_fisheye_priors, "OPENCV_FISHEYE", ()),
    "missing priors": (lambda s: shutil.rmtree(s / "priors"), "priors", ()),
    "an option out of range": (
        lambda s: None,
        "--prior_position_sigma",
        ("--prior_position_sigma", "-1"),
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_is_one_line_exit_2_and_nothing_written(tmp_path, capsys, case):
    spoil, expected, extra = CASES[case]
    scene = _scene(tmp_path)
    spoil(scene)
    out = tmp_path / "out"
    before = sorted(p.name for p in tmp_path.iterdir())
    assert _run(scene, out, *extra) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and expected in err[0], err
    assert "Traceback" not in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written


def test_an_existing_output_is_untouched(tmp_path, capsys):
    scene = _scene(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    assert _run(scene, out) == 2
    assert "not empty" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["mine.txt"]


_coord = st.one_of(st.floats(-1e7, 1e7), st.sampled_from([float("nan"), float("inf")]))
_ring = st.lists(st.tuples(_coord, _coord).map(list), min_size=0, max_size=6)
_geometry = st.one_of(
    st.none(),
    st.fixed_dictionaries(
        {
            "type": st.sampled_from(
                ["Polygon", "MultiPolygon", "Point", "LineString", "x"]
            )
        },
        optional={
            "coordinates": st.one_of(_ring, st.lists(_ring, max_size=3), st.integers())
        },
    ),
)
_feature = st.one_of(
    st.integers(),
    st.fixed_dictionaries(
        {"type": st.just("Feature"), "geometry": _geometry},
        optional={
            "properties": st.one_of(
                st.none(),
                st.dictionaries(
                    st.sampled_from(["id", "height"]),
                    st.one_of(
                        st.text(max_size=3), st.floats(), st.integers(), st.none()
                    ),
                ),
            )
        },
    ),
)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(raw=_feature)
def test_the_feature_parser_never_fails_but_with_a_named_input_error(raw):
    """Whatever a feature holds, parsing it gives a footprint, a reason to
    skip it, or an InputError naming the file: never another exception."""
    path = Path("map.geojson")
    try:
        out = parse_feature(path, 7, raw)
    except InputError as exc:
        assert exc.path == path and "feature 7" in str(exc)
        return
    assert isinstance(out, (Feature, str))
    if isinstance(out, Feature):
        assert np.all(np.isfinite(np.asarray(out.geometry.bounds)))
