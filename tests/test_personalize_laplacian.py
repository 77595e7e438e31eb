"""Hable's Laplacian-regularised fit: solved to the minimiser of its energy; its weight by its own CV."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve
from test_personalize_prior import grid_mesh

from usdface.mesh import uniform_laplacian
from usdface.personalize.fit import regularization_weights
from usdface.personalize.laplacian import LaplacianFit


def direct_solve(neutral, tris, points, W, T, D, reg, mu):
    """The same energy's normal equations as one sparse system over (shape, vertex), solved directly."""
    K, n = T.shape[:2]
    L = uniform_laplacian(tris, n)
    LtL = (L.T @ L).tocsr()
    A = sp.kron(sp.csr_matrix(W.T @ W), sp.identity(n)) + sp.diags((reg * D ** 2).ravel()) \
        + mu * sp.kron(sp.identity(K), LtL)
    R = points - neutral[None]
    rhs = np.einsum("fk,fnc->knc", W, R) + (reg * D ** 2)[:, :, None] * T \
        + mu * np.stack([LtL @ T[j] for j in range(K)])
    X = spsolve(A.tocsc(), rhs.reshape(K * n, 3))
    return X.reshape(K, n, 3)


def problem(seed=0):
    rng = np.random.default_rng(seed)
    neutral, tris = grid_mesh(10, 9)
    K, n, F = 4, len(neutral), 7
    true = rng.normal(size=(K, n, 3)) * 0.002
    T = true + rng.normal(size=true.shape) * 0.0005
    T[:, :6] = 0.0                                          # static vertices: eq. (3) clamps D there
    W = rng.uniform(0, 1, size=(F, K))
    pts = neutral + np.einsum("fk,knc->fnc", W, true) + rng.normal(size=(F, n, 3)) * 1e-4
    return neutral, tris, pts, W, T, true


def test_laplacian_fit_reaches_the_direct_solution():
    neutral, tris, pts, W, T, _ = problem()
    D = regularization_weights(T)
    for reg, mu in ((1.0, 0.03), (1e-3, 0.3)):
        lf = LaplacianFit(neutral, tris, T, D, laplacian_weight=mu)
        X = lf.solve(pts, W, reg)
        ref = direct_solve(neutral, tris, pts, W, T, D, reg, mu)
        assert np.abs(X - ref).max() < 1e-9, (reg, mu, lf.info)


def test_laplacian_weight_is_chosen_by_its_own_cross_validation():
    """The weight is the grid point of least K-fold CV error of the Laplacian fit itself, and that score is
    a real held-out error (reproduced by direct solves of each fold)."""
    neutral, tris, pts, W, T, true = problem(1)
    rng = np.random.default_rng(2)
    W = rng.uniform(0, 1, size=(12, 4))
    pts = neutral + np.einsum("fk,knc->fnc", W, true) + rng.normal(size=(12, len(neutral), 3)) * 3e-4
    D = regularization_weights(T)
    lf = LaplacianFit(neutral, tris, T, D)
    cv = lf.choose_weight(pts, W, 1e-3)
    assert cv["mu"] == cv["grid"][int(np.argmin(cv["cv_rmse_mm"]))] and lf.mu == cv["mu"]
    # the score is a real held-out error: refitting fold 0 by hand at the chosen weight reproduces it
    fold = np.arange(len(W)) % 3
    sse = 0.0
    for k in range(3):
        X = direct_solve(neutral, tris, pts[fold != k], W[fold != k], T, D, 1e-3, cv["mu"])
        sse += np.sum((pts[fold == k] - neutral - np.einsum("fk,knc->fnc", W[fold == k], X)) ** 2)
    assert np.isclose(np.sqrt(sse / pts.size) * 1000, min(cv["cv_rmse_mm"]), rtol=1e-4)


def test_the_weight_cross_validation_shows_its_progress(monkeypatch, capsys):
    """Stop 43: ``fit --method laplacian`` spent ~26 CPU-s on dev3 in one silent step (``fit laplacian``),
    nearly all of it in the weight's cross-validation. Each weight's fits are a step of their own now."""
    from test_personalize_inputs import tiny_capture

    from usdface import progress
    from usdface.personalize.api import fit_personalized_shapes
    from usdface.personalize.laplacian import LAPLACIAN_GRID

    monkeypatch.setenv("USDFACE_PROGRESS", "plain")
    monkeypatch.setenv("USDFACE_PROGRESS_DELAY", "0")
    monkeypatch.setattr(progress, "_ENABLED", True)
    fit_personalized_shapes(tiny_capture(), method="laplacian")
    err = capsys.readouterr().err
    for i, mu in enumerate(LAPLACIAN_GRID, 1):
        assert f"laplacian weight [{i}/{len(LAPLACIAN_GRID)}] mu {mu:g}: all frames + 3 folds" in err, err


def test_the_vertex_major_solver_reaches_the_direct_solution_from_any_start():
    """Stop 53: the solver works vertex-major ([n,3,K]) and skips the Laplacian products at mu = 0. From no
    start, from a warm start (left untouched) and at mu = 0 it still lands within 1e-9 m of a direct sparse
    solve of the same energy."""
    neutral, tris, pts, W, T, true = problem(3)
    D = regularization_weights(T)
    for reg, mu in ((1.0, 0.0), (1e-3, 0.0), (1e-3, 0.03), (1e-2, 0.3)):
        ref = direct_solve(neutral, tris, pts, W, T, D, reg, mu)
        for x0 in (None, true.copy()):
            lf = LaplacianFit(neutral, tris, T, D, laplacian_weight=mu)
            keep = None if x0 is None else x0.copy()
            X = lf.solve(pts, W, reg, x0=x0)
            assert X.shape == T.shape and X.flags.c_contiguous
            assert np.abs(X - ref).max() < 1e-9, (reg, mu, lf.info)
            if x0 is not None:
                assert np.array_equal(x0, keep)
