"""ParaView time series: .pvd index and per-frame .vtu with deformed points and data."""
import meshio
import numpy as np
import pytest

from matlearn import meshes
from matlearn.vtk_output import write_time_series


def test_time_series_points_and_data(tmp_path):
    mesh = meshes.bar(cells=(2, 1, 1))
    n, m = mesh.num_vertices, mesh.num_tets
    times = np.array([0.0, 0.015, 0.04])
    X = mesh.vertices[None] + np.arange(3)[:, None, None] * np.array([0.0, 0.01, 0.0])
    speed = np.random.default_rng(0).normal(size=(3, n))
    region = np.arange(m) % 2  # constant over frames
    pvd = write_time_series(tmp_path / "out", mesh, times, X, point_data={"speed": speed},
                            cell_data={"region": region, "energy": np.ones((3, m)) * times[:, None]})
    text = pvd.read_text()
    assert text.count("<DataSet") == 3 and 'timestep="0.015"' in text
    f2 = meshio.read(tmp_path / "out" / "frame_00002.vtu")
    np.testing.assert_allclose(f2.points, X[2])
    np.testing.assert_allclose(f2.point_data["displacement"], X[2] - mesh.vertices)
    np.testing.assert_allclose(f2.point_data["speed"], speed[2])
    np.testing.assert_array_equal(f2.cells_dict["tetra"], mesh.tets)
    np.testing.assert_array_equal(f2.cell_data["region"][0], region)
    np.testing.assert_allclose(f2.cell_data["energy"][0], 0.04)


def test_shape_errors(tmp_path):
    mesh = meshes.bar(cells=(1, 1, 1))
    X = np.stack([mesh.vertices] * 2)
    with pytest.raises(ValueError, match="X: expected shape"):
        write_time_series(tmp_path, mesh, [0.0, 0.1, 0.2], X)
    with pytest.raises(ValueError, match="point_data"):
        write_time_series(tmp_path, mesh, [0.0, 0.1], X, point_data={"a": np.zeros(3)})
