"""Tests of scanner_core.io.ply: round trips, empty clouds, malformed files, trimesh interop."""
from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_array_equal

from scanner_core.io.ply import read_ply, write_ply

FIELD_DTYPES = [np.float32, np.float64, np.int32, np.uint8, np.int16, np.uint16, np.uint32,
                np.int8]


@pytest.fixture
def cloud():
    rng = np.random.default_rng(1234)
    n = 257
    points = rng.uniform(-75.0, 75.0, size=(n, 3)).astype(np.float32)
    fields = {
        "quality": rng.uniform(0.0, 1.0, n).astype(np.float32),
        "frame_id": rng.integers(0, 100_000, n).astype(np.int32),
        "view": rng.integers(0, 3, n).astype(np.uint8),
        "t": rng.uniform(0.0, 10.0, n),  # float64
    }
    return points, fields


def test_round_trip_with_fields(tmp_path, cloud):
    points, fields = cloud
    path = write_ply(tmp_path / "cloud.ply", points, fields=fields, comments=["frame T", "mm"])
    got_points, got_fields = read_ply(path)
    assert got_points.dtype == np.float32 and got_points.shape == points.shape
    assert_array_equal(got_points, points)
    assert list(got_fields) == list(fields)
    for name, arr in fields.items():
        assert got_fields[name].dtype == arr.dtype, name
        assert_array_equal(got_fields[name], arr)
    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\ncomment frame T\n")


@pytest.mark.parametrize("dtype", FIELD_DTYPES)
def test_round_trip_every_field_dtype(tmp_path, dtype):
    points = np.arange(12, dtype=np.float64).reshape(4, 3)
    values = np.array([0, 1, 2, 100], dtype=dtype)
    write_ply(tmp_path / "c.ply", points, fields={"v": values})
    got_points, got_fields = read_ply(tmp_path / "c.ply")
    assert_array_equal(got_points, points.astype(np.float32))
    assert got_fields["v"].dtype == np.dtype(dtype)
    assert_array_equal(got_fields["v"], values)


def test_empty_cloud(tmp_path):
    path = write_ply(tmp_path / "empty.ply", np.zeros((0, 3)), fields={"q": np.zeros(0, np.float32)})
    points, fields = read_ply(path)
    assert points.shape == (0, 3) and points.dtype == np.float32
    assert fields["q"].shape == (0,)
    assert b"element vertex 0\n" in path.read_bytes()


def test_truncated_file_raises(tmp_path, cloud):
    points, fields = cloud
    path = write_ply(tmp_path / "cloud.ply", points, fields=fields)
    blob = path.read_bytes()
    path.write_bytes(blob[:-5])
    with pytest.raises(ValueError, match="truncated"):
        read_ply(path)


@pytest.mark.parametrize("blob, match", [
    (b"", "not a PLY"),
    (b"solid cube\nfacet normal 0 0 1\n", "not a PLY"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n", "end_header"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\n"
     b"end_header\n", "lacks properties"),
    (b"ply\nformat binary_middle_endian 1.0\nend_header\n", "format"),
    (b"ply\nelement vertex 0\nproperty float x\nend_header\n", "no format"),
    (b"ply\nformat ascii 1.0\nelement vertex two\nend_header\n", "element line"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n", "property line"),
    (b"ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\n"
     b"end_header\n", "no vertex element"),
    (b"ply\nformat binary_little_endian 1.0\nelement face 1\n"
     b"property list uchar int vertex_indices\nelement vertex 1\nproperty float x\n"
     b"property float y\nproperty float z\nend_header\n", "before the vertex element"),
])
def test_malformed_header_raises(tmp_path, blob, match):
    path = tmp_path / "bad.ply"
    path.write_bytes(blob)
    with pytest.raises(ValueError, match=match):
        read_ply(path)


def test_ascii_with_faces_after_vertices(tmp_path):
    path = tmp_path / "tri.ply"
    path.write_text("ply\nformat ascii 1.0\ncomment made by hand\nelement vertex 3\n"
                    "property double x\nproperty double y\nproperty double z\n"
                    "property uchar red\nelement face 1\nproperty list uchar int vertex_indices\n"
                    "end_header\n0 0 0 255\n1.5 0 0 10\n0 2.25 -1 0\n3 0 1 2\n")
    points, fields = read_ply(path)
    assert_array_equal(points, np.array([[0, 0, 0], [1.5, 0, 0], [0, 2.25, -1]], np.float32))
    assert_array_equal(fields["red"], np.array([255, 10, 0], np.uint8))


def test_big_endian_and_skipped_scalar_element(tmp_path):
    header = (b"ply\nformat binary_big_endian 1.0\nelement camera 2\nproperty float f\n"
              b"element vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
              b"property int id\nend_header\n")
    cam = np.array([1.0, 2.0], ">f4").tobytes()
    verts = np.array([(1, 2, 3, 7), (4, 5, 6, -1)],
                     dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("id", ">i4")]).tobytes()
    path = tmp_path / "be.ply"
    path.write_bytes(header + cam + verts)
    points, fields = read_ply(path)
    assert_array_equal(points, [[1, 2, 3], [4, 5, 6]])
    assert_array_equal(fields["id"], [7, -1])
    assert fields["id"].dtype == np.int32


def test_opens_in_trimesh(tmp_path, cloud):
    trimesh = pytest.importorskip("trimesh")
    points, fields = cloud
    path = write_ply(tmp_path / "cloud.ply", points, fields=fields)
    loaded = trimesh.load(path)
    assert isinstance(loaded, trimesh.PointCloud)
    assert_array_equal(np.asarray(loaded.vertices, dtype=np.float32), points)


@pytest.mark.parametrize("points, fields, match", [
    (np.zeros((4, 2)), None, "`points` must be"),
    (np.zeros(3), None, "`points` must be"),
    (np.zeros((4, 3)), {"q": np.zeros(5)}, r"`fields\['q'\]` must have shape \(4,\)"),
    (np.zeros((4, 3)), {"q": np.zeros(4, np.int64)}, "PLY cannot store"),
    (np.zeros((4, 3)), {"x": np.zeros(4)}, "clashes"),
    (np.zeros((4, 3)), {"a b": np.zeros(4)}, "single printable"),
])
def test_write_validates(tmp_path, points, fields, match):
    with pytest.raises(ValueError, match=match):
        write_ply(tmp_path / "c.ply", points, fields=fields)
    assert list(tmp_path.iterdir()) == []


def test_failed_write_keeps_old_file(tmp_path, monkeypatch):
    path = write_ply(tmp_path / "c.ply", np.ones((2, 3)))
    before = path.read_bytes()

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr("scanner_core.fileio.os.replace", boom)
    with pytest.raises(OSError, match="disk full"):
        write_ply(path, np.zeros((5, 3)))
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["c.ply"]


def test_comment_with_newline_rejected(tmp_path):
    with pytest.raises(ValueError, match="`comments`"):
        write_ply(tmp_path / "c.ply", np.zeros((1, 3)), comments=["a\nend_header"])


def test_non_finite_points_are_refused(tmp_path):
    with pytest.raises(ValueError, match="must be finite"):
        write_ply(tmp_path / "nan.ply", np.array([[0.0, np.nan, 1.0]], np.float32))
    assert not (tmp_path / "nan.ply").exists()


def test_normals_and_nan_fields_round_trip_in_order(tmp_path):
    """cloud.ply's layout: x y z nx ny nz sensor_x sensor_y sensor_z frame_id quality; a NaN
    normal (no viewpoint) is stored as it is, while NaN coordinates are refused above."""
    names = ["nx", "ny", "nz", "sensor_x", "sensor_y", "sensor_z"]
    fields = {name: np.array([0.0, np.nan, 1.0], np.float32) for name in names}
    fields |= {"frame_id": np.array([1, 2, 3], np.int32), "quality": np.full(3, 200, np.float32)}
    path = write_ply(tmp_path / "cloud.ply", np.zeros((3, 3)), fields=fields)
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    assert [line.split()[-1] for line in header.splitlines() if line.startswith("property")] \
        == ["x", "y", "z", *fields]
    _, got = read_ply(path)
    for name, values in fields.items():
        assert_array_equal(got[name], values)
