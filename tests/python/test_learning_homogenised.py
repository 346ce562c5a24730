"""bench/learning_table.homogenised_modulus: the truth's Young's modulus log-averaged over each
tet of a coarser mesh of the same body (the layered-bar reference column)."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))

from learning_table import homogenised_modulus  # noqa: E402

from matlearn import meshes  # noqa: E402


def test_cells_of_one_material_keep_it():
    # fine 4x2x4 cells, coarse 2x1x2: the bottom half (z < 0) soft, the top stiff, so every
    # coarse tet lies in one material and must get exactly its modulus
    fine = meshes.bar(0.12, 0.02, 0.02, cells=(4, 2, 4))
    coarse = meshes.bar(0.12, 0.02, 0.02, cells=(2, 1, 2))
    zf = np.asarray(fine.vertices)[fine.tets].mean(axis=1)[:, 2]
    E = np.where(zf > 0, 1e7, 1e5)
    Ec = homogenised_modulus(fine, E, coarse, samples=64)
    zc = np.asarray(coarse.vertices)[coarse.tets].mean(axis=1)[:, 2]
    np.testing.assert_allclose(Ec, np.where(zc > 0, 1e7, 1e5), rtol=1e-12)


def test_mixed_tet_gets_the_geometric_mean():
    # one coarse cell over two fine layers (z < 0 soft, z > 0 stiff): each coarse tet's log E is
    # log(1e5) + (its volume fraction above z = 0) * log(100); the tets tile the cube, so the
    # volume-weighted mean of that fraction is 1/2 (an arithmetic mean of E would give ~0.85)
    fine = meshes.bar(0.02, 0.02, 0.02, cells=(2, 2, 2))
    coarse = meshes.bar(0.02, 0.02, 0.02, cells=(1, 1, 1))
    zf = np.asarray(fine.vertices)[fine.tets].mean(axis=1)[:, 2]
    E = np.where(zf > 0, 1e7, 1e5)
    Ec = homogenised_modulus(fine, E, coarse, samples=4000)
    frac = (np.log(Ec) - np.log(1e5)) / np.log(100.0)
    assert np.all((frac > 0.0) & (frac < 1.0))
    vol = np.asarray(coarse.rest_volumes)
    assert abs(np.sum(vol * frac) / vol.sum() - 0.5) < 0.02
