"""The same backward-Euler step built on pbatoolkit (Q-Minh/PhysicsBasedAnimationToolkit) as a
peer for forward_step.py: pbat's C++ computes the stable neo-Hookean gradient and SPD-projected
Hessian, the system is solved with pbat's Eigen simplicial LDL^T (its only sparse direct
solver without MKL). pbat has no co-rotated law, so this peer runs for neo-Hookean only.
Returns None from `make_peer` when pbatoolkit is not installed.
"""
from __future__ import annotations

import numpy as np


def make_peer(vertices, tets, mu, lam, mass_dofs, alpha_mass, alpha_stiffness, fixed, h, gravity,
              max_newton=8, tol=1e-7):
    try:
        import pbatoolkit as pbat
    except ImportError:
        return None
    return PbatStepper(pbat, vertices, tets, mu, lam, mass_dofs, alpha_mass, alpha_stiffness,
                       fixed, h, gravity, max_newton, tol)


class PbatStepper:
    def __init__(self, pbat, vertices, tets, mu, lam, mass_dofs, alpha_mass, alpha_stiffness,
                 fixed, h, gravity, max_newton, tol):
        fem = pbat.pbat.fem
        self.fem, self.linalg = fem, pbat.pbat.math.linalg
        self.X = np.asarray(vertices, float)
        self.E = np.ascontiguousarray(np.asarray(tets, np.int64).T)
        XT = np.ascontiguousarray(self.X.T)
        n = len(self.X)
        self.el = fem.Element.Tetrahedron
        self.wg = np.ravel(fem.mesh_quadrature_weights(self.E, XT, self.el, order=1, quadrature_order=1))
        self.eg = np.ravel(fem.mesh_quadrature_elements(self.E, self.wg[None, :]))
        self.GNeg = fem.shape_function_gradients(self.E, XT, element=self.el, order=1, dims=3,
                                                 quadrature_order=1)
        self.mug = np.broadcast_to(mu, (self.E.shape[1],)).astype(float)[self.eg]
        self.lamg = np.broadcast_to(lam, (self.E.shape[1],)).astype(float)[self.eg]
        self.mass = np.asarray(mass_dofs, float)
        self.aM, self.aK, self.h = alpha_mass, alpha_stiffness, h
        self.g = np.asarray(gravity, float)
        self.max_newton, self.tol = max_newton, tol
        self.size = np.linalg.norm(np.ptp(self.X, axis=0))
        free = np.ones(3 * n, bool)
        free[(3 * np.asarray(fixed)[:, None] + np.arange(3)).ravel()] = False
        self.free = free
        self.x = self.X.copy()
        self.v = np.zeros_like(self.X)
        self.solver = None
        self.iterations = 0

    def _grad_hess(self, x):
        fem = self.fem
        _, g, H = fem.hyper_elastic_potential(
            E=self.E, n_nodes=len(self.X), eg=self.eg, wg=self.wg, GNeg=self.GNeg, mug=self.mug,
            lambdag=self.lamg, x=np.ravel(x), energy=fem.HyperElasticEnergy.StableNeoHookean,
            flags=fem.ElementElasticityComputationFlags.Gradient
            | fem.ElementElasticityComputationFlags.Hessian,
            spd_correction=fem.HyperElasticSpdCorrection.Absolute, element=self.el, order=1, dims=3)
        return g, H

    def step(self, f_ext):
        import scipy.sparse as sp

        n, h = len(self.X), self.h
        x0, v0 = self.x, self.v
        v = v0.copy().reshape(-1)
        v[~self.free] = 0.0
        fconst = np.asarray(f_ext, float).reshape(-1) + self.mass * np.tile(self.g, n)
        v_ref = 1e-6 * self.size / h
        for it in range(self.max_newton):
            g, H = self._grad_hess(x0.reshape(-1) + h * v)
            f = -g - self.aK * (H @ v) - self.aM * self.mass * v
            r = (self.mass * (v - v0.reshape(-1)) - h * (f + fconst))[self.free]
            A = ((h * h + h * self.aK) * H + sp.diags((1 + h * self.aM) * self.mass)).tocsc()
            A = A[self.free][:, self.free].tocsc()
            if self.solver is None:
                self.solver = self.linalg.SimplicialLdlt_Csc_AMD()
                self.solver.analyze(A)
            self.solver.factorize(A)
            dv = np.asarray(self.solver.solve(-r)).reshape(-1)
            v[self.free] += dv
            self.iterations = it + 1
            if np.linalg.norm(dv) <= self.tol * (np.linalg.norm(v[self.free]) + v_ref):
                break
        self.v = v.reshape(n, 3)
        self.x = x0 + h * self.v
