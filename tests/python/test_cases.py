"""The layered-bar cases of matlearn.cases (paper Fig. 17): built specs only, no simulation."""
import numpy as np

from matlearn import cases


def _coarse_cell_soft_fraction(spec, coarse_cells):
    """Soft-material volume fraction of the truth inside each cell of the coarse model's grid."""
    kw = spec.kwargs
    fine = kw["truth_mesh"]
    E = np.asarray(kw["truth_material"].youngs_modulus)
    V = np.asarray(fine.vertices)
    lo, hi = V.min(axis=0), V.max(axis=0)
    c = V[fine.tets].mean(axis=1)
    idx = np.floor((c - lo) / (hi - lo) * np.asarray(coarse_cells)).astype(int)
    key = np.ravel_multi_index(idx.T, coarse_cells)
    vol = np.asarray(fine.rest_volumes)
    soft = np.bincount(key, vol * (E < 1e6), minlength=np.prod(coarse_cells))
    return soft / np.bincount(key, vol, minlength=np.prod(coarse_cells))


def test_layered_bar_alternates_one_fine_cell_per_layer():
    spec = cases.layered_bar()
    kw = spec.kwargs
    fine, coarse = kw["truth_mesh"], kw["model_mesh"]
    assert coarse.num_tets * 8 == fine.num_tets  # coarsened by 2 along each axis
    E = np.asarray(kw["truth_material"].youngs_modulus)
    assert set(np.unique(E)) == {1e5, 1e7}
    V = np.asarray(fine.vertices)
    z = V[fine.tets].mean(axis=1)[:, 2]
    slab = np.floor((z - V[:, 2].min()) / (np.ptp(V[:, 2]) / 4)).astype(int)
    for k in range(4):  # one material per fine slab, alternating from slab to slab
        assert np.unique(E[slab == k]).size == 1
        if k:
            assert E[slab == k][0] != E[slab == k - 1][0]
    # every coarse cell holds exactly one layer of each material (half the volume soft)
    np.testing.assert_allclose(_coarse_cell_soft_fraction(spec, (4, 2, 2)), 0.5, atol=1e-12)


def test_layered_bar_halves_is_kept_as_an_extra_row():
    spec = cases.layered_bar_halves()
    assert spec.name == "layered_bar_halves" and spec.name not in cases.TARGET_ERROR
    frac = _coarse_cell_soft_fraction(spec, (4, 1, 2))
    assert set(np.round(frac, 12)) == {0.0, 1.0}  # each coarse cell is of one material
    assert cases.layered_bar_halves in cases.ALL and cases.layered_bar in cases.ALL
