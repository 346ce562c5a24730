"""Distillation into the 6-6-6-3 MLP (learning/distill.py): training + export to the C++
evaluator (batch norm folded into the linear layers) reproduces a smooth correction on held-out
samples, and the agreement metric of `compare` is the relative L2 error it states."""
import numpy as np

from matlearn.learning.distill import compare, train_mlp
from matlearn.learning.io import mlp_correction


def _data(n, seed):
    rng = np.random.default_rng(seed)
    Fh = 1 + 0.1 * rng.standard_normal((n, 3))
    Fhd = 0.5 * rng.standard_normal((n, 3))
    # A smooth stress correction (Pa) with a mild stretch-rate part, as distillation sees.
    Y = 2e4 * np.tanh(3 * (Fh - 1)) + 500.0 * Fhd
    return np.concatenate([Fh, Fhd], axis=1), Y


def test_trained_mlp_exported_to_cpp_matches_smooth_target_on_held_out_samples():
    X, Y = _data(3000, 0)
    Xh, Yh = _data(1000, 1)
    exported, info = train_mlp(X, Y, epochs=80, batch=256, lr=1e-2, seed=0)
    mc = mlp_correction(exported)
    held = compare(None, mc, Xh, Yh, repeats=0)
    train = compare(None, mc, X, Y, repeats=0)
    # Stated tolerance: 5 % relative L2 error on held-out samples, close to the training error.
    assert held["relative_error"] < 0.05, held
    assert held["relative_error"] < 1.5 * train["relative_error"] + 0.01
    # compare() reports || pred - Y || / || Y - mean(Y) || over all components.
    pred = np.asarray(mc.evaluate(np.ascontiguousarray(Xh[:, :3]), np.ascontiguousarray(Xh[:, 3:]))[0])
    want = np.linalg.norm(pred - Yh) / np.linalg.norm(Yh - Yh.mean(0))
    np.testing.assert_allclose(held["relative_error"], want, rtol=1e-12)
