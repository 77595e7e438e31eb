"""Unit tests of the personalization core on synthetic data with a known answer: deformation transfer,
eq. (3) weights, the position fit (eqs. 1-2) and its leave-one-out criterion, weights, rigid alignment."""

from __future__ import annotations

import numpy as np
import pytest
from forking import child_finishes
from scipy.spatial.transform import Rotation
from synthetic_meshes import grid_triangles

from usdface.errors import GeometryError
from usdface.personalize.align import (
    expression_weights,
    kabsch,
    rigid_align,
    rigid_transforms,
    rigid_transforms_sets,
)
from usdface.personalize.dt import PoissonSolver, deformation_transfer, eyelid_triangles, zip_loop
from usdface.personalize.fit import PositionFit, fit_blendshapes, regularization_weights
from usdface.personalize.weights import reestimate_weights


def bumpy_grid(nx=12, ny=10, seed=0):
    xs, ys = np.meshgrid(np.linspace(0, 0.1, nx), np.linspace(0, 0.08, ny))
    z = 0.01 * np.sin(30 * xs) * np.cos(25 * ys)
    pts = np.c_[xs.ravel(), ys.ravel(), z.ravel()]
    return pts, grid_triangles(nx, ny)


@pytest.fixture(scope="module")
def mesh():
    return bumpy_grid()


def test_dt_onto_the_same_neutral_reproduces_the_shapes(mesh):
    pts, tris = mesh
    rng = np.random.default_rng(1)
    smooth = np.sin(40 * pts[:, :1]) * np.cos(30 * pts[:, 1:2])
    deltas = np.stack([0.002 * smooth * rng.normal(size=3) for _ in range(4)])
    out = deformation_transfer(pts, deltas, pts, tris, eyelids=False)
    assert np.abs(out - deltas).max() < 1e-9


def test_dt_transfers_a_rigid_rotation_as_a_rotation(mesh):
    pts, tris = mesh
    R = Rotation.from_euler("z", 10, degrees=True).as_matrix()
    src_delta = (pts @ R.T - pts)[None]
    target = pts * [1.3, 0.8, 1.1] + 0.05                            # another "person"
    out = deformation_transfer(pts, src_delta, target, tris, eyelids=False)[0]
    moved = target + out
    c_m, c_t = moved.mean(0), target.mean(0)
    H = (target - c_t).T @ (moved - c_m)
    U, _, Vt = np.linalg.svd(H)
    R_fit = Vt.T @ U.T
    assert np.allclose(R_fit, R, atol=1e-6)
    assert np.abs((target - c_t) @ R.T + c_m - moved).max() < 1e-7   # rigid (screening leaves ~1e-8 m)


def test_partial_dt_keeps_fixed_vertices(mesh):
    pts, tris = mesh
    fixed = np.arange(0, 12)
    solver = PoissonSolver(pts, tris, fixed=fixed)
    deltas = np.zeros((1,) + pts.shape)
    deltas[0, :, 2] = 0.001 * pts[:, 0] / 0.1
    fixed_deltas = np.full((1, len(fixed), 3), 0.0005)
    out = deformation_transfer(pts, deltas, pts, tris, solver=solver, fixed_deltas=fixed_deltas)
    assert np.allclose(out[0, fixed], 0.0005)
    with pytest.raises(ValueError):
        solver.solve(np.tile(np.eye(3), (len(tris), 1, 1)))


@pytest.mark.parametrize("fixed", [False, True])
def test_dt_in_groups_of_shapes_is_the_transfer_of_every_shape_at_once(mesh, monkeypatch, fixed):
    """:meth:`PoissonSolver.solve_transfer` takes the shapes in groups within ``dt.SHAPE_BLOCK_BYTES`` (a
    74.5k-vertex capture's 51 shapes took ~1.1 GB at once): groups of one and of two shapes (five shapes,
    a screened and a pinned solver) give every shape's transfer of one group, to rounding."""
    from usdface.personalize import dt as dt_module

    pts, tris = mesh
    rng = np.random.default_rng(3)
    smooth = np.sin(40 * pts[:, :1]) * np.cos(30 * pts[:, 1:2])
    deltas = np.stack([0.002 * smooth * rng.normal(size=3) + 1e-4 * rng.normal(size=pts.shape)
                       for _ in range(5)])
    target = pts * [1.2, 0.9, 1.1] + 0.01
    idx = np.arange(0, 12) if fixed else None
    solver = PoissonSolver(target, tris, fixed=idx)
    kw = {"fixed_deltas": rng.normal(size=(5, 12, 3)) * 1e-4} if fixed else {}
    whole = deformation_transfer(pts, deltas, target, tris, solver=solver, eyelids=False, **kw)
    assert dt_module.SHAPE_BLOCK_BYTES >= 8 * 8 * 3 * len(tris) * len(deltas)    # the premise: one group
    for shapes in (1, 2):
        monkeypatch.setattr(dt_module, "SHAPE_BLOCK_BYTES", 8 * 8 * 3 * len(tris) * shapes)
        grouped = deformation_transfer(pts, deltas, target, tris, solver=solver, eyelids=False, **kw)
        np.testing.assert_allclose(grouped, whole, rtol=0, atol=1e-15)
    assert np.abs(whole).max() > 1e-3


def test_dt_of_no_shapes_is_an_empty_transfer(mesh):
    """Zero shapes (``source_deltas[0,n,3]``) transfer to ``[0,n,3]``, as before the shapes went through in
    groups (stop 51: the groups' loop ran no group and ``np.concatenate([])`` raised ``ValueError: need at
    least one array to concatenate``)."""
    pts, tris = mesh
    out = deformation_transfer(pts, np.zeros((0,) + pts.shape), pts * 1.1, tris, eyelids=False)
    assert out.shape == (0,) + pts.shape
    solver = PoissonSolver(pts * 1.1, tris)
    assert solver.solve_transfer(pts, np.zeros((0,) + pts.shape)).shape == (0,) + pts.shape


def test_zip_loop_and_eyelid_detection():
    # a ring of 8 points around an "eye" hole whose upper lid closes in the blink shape
    ang = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    ring = np.c_[np.cos(ang) * 0.015, np.sin(ang) * 0.005, np.zeros(8)]
    outer = np.c_[np.cos(ang) * 0.03, np.sin(ang) * 0.02, np.zeros(8)]
    pts = np.r_[ring, outer]
    tris = []
    for i in range(8):
        j = (i + 1) % 8
        tris += [[i, 8 + i, 8 + j], [i, 8 + j, j]]
    tris = np.array(tris)
    zipped = zip_loop(pts, np.arange(8))
    assert len(zipped) == 6                                           # an 8-gon needs n - 2 triangles
    blink = np.zeros((1,) + pts.shape)
    blink[0, 1:4, 1] = -0.0048                                        # upper lid down to the lower
    found = eyelid_triangles(pts, blink, tris, ["eyeBlinkLeft"])
    assert len(found) == 6 and set(found.ravel()) <= set(range(8))
    assert len(eyelid_triangles(pts, blink, tris, ["jawOpen"])) == 0     # no blink shape, no eyelids


def test_regularization_weights_eq3():
    deltas = np.zeros((2, 4, 3))
    deltas[0, :, 0] = [0.004, 0.002, 0.001, 0.0]
    D = regularization_weights(deltas)
    assert np.allclose(D[0, :3], [1, 2, 4])
    assert D[0, 3] == 1e5 and np.all(D[1] == 1e5)                    # clamped where nothing moves


def synthetic_fit_problem(seed=0, n=30, K=5, F=12, noise=0.0):
    rng = np.random.default_rng(seed)
    neutral = rng.normal(size=(n, 3)) * 0.05
    true = rng.normal(size=(K, n, 3)) * 0.003
    W = np.clip(rng.uniform(-0.3, 1, size=(F, K)), 0, 1)
    pts = neutral + np.einsum("fk,knc->fnc", W, true) + rng.normal(size=(F, n, 3)) * noise
    generic = true + rng.normal(size=true.shape) * 0.001
    return neutral, pts, W, true, generic


def test_fit_recovers_exact_shapes_without_noise():
    neutral, pts, W, true, generic = synthetic_fit_problem()
    D = regularization_weights(generic)
    B = fit_blendshapes(neutral, pts, W, generic, D, reg=1e-9)
    assert np.abs(B - true).max() < 1e-6
    # with the paper's balance it stays between the data and the prior
    Bp = fit_blendshapes(neutral, pts, W, generic, D, reg=1.0)
    assert np.abs(Bp - true).mean() < np.abs(generic - true).mean()


def test_position_fit_matches_direct_solve_and_brute_force_loo():
    neutral, pts, W, true, generic = synthetic_fit_problem(noise=0.0005, F=8)
    D = regularization_weights(generic)
    pf = PositionFit(neutral, pts, W, generic, D)
    for reg in (1e-3, 0.1, 3.0):
        assert np.allclose(pf.solve(reg), fit_blendshapes(neutral, pts, W, generic, D, reg), atol=1e-12)
    reg = 0.05
    brute = []
    for i in range(len(W)):
        keep = np.arange(len(W)) != i
        B = fit_blendshapes(neutral, pts[keep], W[keep], generic, D, reg)
        brute.append(np.mean((pts[i] - neutral - np.einsum("k,knc->nc", W[i], B)) ** 2))
    assert np.isclose(pf.loo_error(reg), np.mean(brute), rtol=1e-8)


@pytest.mark.parametrize("reduced", [True, False])
def test_reduced_basis_fit_equals_the_full_k_by_k_systems(monkeypatch, reduced):
    """Rank-deficient weights (a repeated frame, a shape never excited): the r x r push-through solve (or,
    above REDUCED_MAX_RANK, the K x K path), the hat-matrix LOO and the data share equal the direct K x K
    formulas of eqs. (1)+(2) written out here."""
    import usdface.personalize.fit as fit_module
    from usdface.personalize.fit import data_share, loo_residuals

    monkeypatch.setattr(fit_module, "REDUCED_MAX_RANK", 1.0 if reduced else 0.0)
    neutral, pts, W, true, generic = synthetic_fit_problem(noise=0.0005, F=9, K=6)
    W[:, 5] = 0.0
    W[8] = W[2]
    D = regularization_weights(generic)
    reg = 0.02
    n, K = D.shape[1], D.shape[0]
    A = np.broadcast_to(W.T @ W, (n, K, K)).copy()
    A[:, np.arange(K), np.arange(K)] += reg * D.T ** 2
    R = pts - neutral
    rhs = np.einsum("fk,fnc->nkc", W, R) + reg * D.T[:, :, None] ** 2 * generic.transpose(1, 0, 2)
    direct = np.linalg.solve(A, rhs).transpose(1, 0, 2)
    assert np.abs(fit_blendshapes(neutral, pts, W, generic, D, reg) - direct).max() < 1e-12
    hat = np.einsum("fk,nkl,gl->nfg", W, np.linalg.inv(A), W)                    # W A^-1 W^T per vertex
    fitted = np.einsum("fk,knc->fnc", W, direct)
    e = (R - fitted) / (1 - np.einsum("nff->fn", hat))[:, :, None]
    assert np.abs(loo_residuals(neutral, pts, W, generic, D, reg) - e).max() < 1e-12
    Pw = np.clip(W + 0.05, 0, 1)                                                 # predict with other weights
    brute = []
    for i in range(len(W)):
        A_i = A - np.einsum("k,l->kl", W[i], W[i])[None]
        b_i = np.linalg.solve(A_i, rhs - np.einsum("k,nc->nkc", W[i], R[i]))
        brute.append(R[i] - np.einsum("k,nkc->nc", Pw[i], b_i))
    pred = loo_residuals(neutral, pts, W, generic, D, reg, predict_weights=Pw)
    assert np.abs(pred - np.array(brute)).max() < 1e-10
    share = np.einsum("nkl,lj->nkj", np.linalg.inv(A), W.T @ W).diagonal(axis1=1, axis2=2)
    assert np.abs(data_share(W, D, reg) - share).max() < 1e-10
    assert np.abs(PositionFit(neutral, pts, W, generic, D).data_share(reg) - share).max() < 1e-10
    assert np.all(share[:, 5] < 1e-12)                                         # never excited: all prior


def test_reestimate_weights_recovers_true_weights_within_bounds():
    neutral, pts, W, true, generic = synthetic_fit_problem(F=20)
    noisy = np.clip(W + np.random.default_rng(3).normal(0, 0.05, W.shape), 0, 1)
    est = reestimate_weights(neutral, true, pts, noisy, anchor=1e-12, iterations=3000)
    assert np.abs(est - W).max() < 1e-3
    assert est.min() >= 0 and est.max() <= 1
    anchored = reestimate_weights(neutral, true, pts, noisy, anchor=1e3)
    assert np.abs(anchored - noisy).max() < 1e-3                      # a strong anchor keeps the phone's


def test_reestimate_weights_reaches_the_bounded_optimum_in_its_default_iterations():
    """With its default iterations, on shapes that are far from orthogonal (a pair 80 % alike, the Gram
    matrix's condition ~60), the re-estimation is the exact anchored, bounded least squares
    (:func:`usdface.bounded_lsq.box_least_squares`) to within 1e-3, 1/40 of the phone's weight noise (it is
    ~2e-4 away; without the accelerated steps it stopped 2-6e-3 short)."""
    from usdface.bounded_lsq import box_least_squares

    neutral, pts, W, true, generic = synthetic_fit_problem(F=20)
    rng = np.random.default_rng(3)
    true = true.copy()
    true[1] = 0.8 * true[0] + 0.2 * true[1]
    pts = neutral + np.einsum("fk,knc->fnc", W, true) + rng.normal(size=pts.shape) * 1e-4
    noisy = np.clip(W + rng.normal(0, 0.05, W.shape), 0, 1)
    B, r = true.reshape(len(true), -1), (pts - neutral).reshape(len(pts), -1)
    for anchor in (1e-6, 1e-5):
        G, c = B @ B.T + anchor * np.eye(len(B)), r @ B.T + anchor * noisy
        exact, converged = box_least_squares(G, c, 0.0, 1.0, np.linalg.solve(G, c.T).T)
        assert converged.all()
        assert np.abs(reestimate_weights(neutral, true, pts, noisy, anchor=anchor) - exact).max() < 1e-3


def test_reestimate_weights_repeated_frames_solved_once_equal_frame_by_frame():
    """Frames that pose the same problem (a repeated frame with the same bounds) are iterated once and
    copied; a repeat with other bounds (held at its phone's weight elsewhere) is its own problem: every
    frame's weights equal those of the frame solved alone, for every vertex set and prior width."""
    from usdface.personalize.weights import reestimate_weights_batched

    neutral, pts, W, true, generic = synthetic_fit_problem(F=6)
    rep = [0, 1, 2, 1, 3, 0, 4, 5, 1]
    pts, W = pts[rep], np.clip(W[rep] + 0.02, 0, 1)
    lo, hi = np.zeros(W.shape), np.ones(W.shape)
    lo[3, 2] = hi[3, 2] = W[3, 2]                                   # frame 3 repeats frame 1, other bounds
    probs = [(neutral[:15], generic[:, :15], pts[:, :15]), (neutral[15:], generic[:, 15:], pts[:, 15:])]
    anchors = np.array([[1e-6, 1e-5], [2e-6, 3e-5]])
    got = reestimate_weights_batched(probs, W, anchors, lower=lo, upper=hi, iterations=80)   # [H,S,F,K]
    for a, b in ((1, 8), (0, 5)):                                  # repeats (rounding aside: the same)
        assert np.abs(got[:, :, a] - got[:, :, b]).max() < 1e-12
    assert np.abs(got[:, :, 3] - got[:, :, 1]).max() > 1e-6
    for f in range(len(W)):
        alone = reestimate_weights_batched([(n0, d, p[[f]]) for n0, d, p in probs], W[[f]], anchors,
                                           lower=lo[[f]], upper=hi[[f]], iterations=80)
        assert np.abs(alone[:, :, 0] - got[:, :, f]).max() < 1e-12


def test_rigid_align_recovers_transform_despite_outliers():
    rng = np.random.default_rng(5)
    ref = rng.normal(size=(200, 3)) * 0.05
    R = Rotation.from_euler("xyz", [1.0, -0.5, 0.8], degrees=True).as_matrix()
    t = np.array([0.001, -0.002, 0.0005])
    frame = (ref - t) @ R                                              # so that R frame + t = ref
    frame[:20] += 0.01                                                 # 10 % outliers (a moving region)
    aligned, R_est, t_est = rigid_align(frame[None], ref, np.arange(200))
    assert np.allclose(R_est[0], R, atol=1e-6)
    assert np.abs(aligned[0, 20:] - ref[20:]).max() < 1e-6
    R_k, _ = kabsch(frame[None], ref)
    assert np.isclose(np.linalg.det(R_k[0]), 1.0)


def test_expression_weights_align_a_frame_on_what_its_expression_leaves_still():
    """A frame that alone shows a shape whose personal part is a rigid-looking shift of its region (a jaw
    pushed further forward than the prior's): its residual from the prediction is that shift there and noise
    elsewhere. Unweighted, the robust alignment moves the frame to absorb it (the region is most of the
    vertices that move); weighted by the inverse of each vertex's expected residual variance the frame stays
    put, and a true rigid head motion of a frame is still recovered."""
    rng = np.random.default_rng(3)
    n = 300
    neutral = rng.normal(size=(n, 3)) * 0.03
    jaw = np.arange(n) < 180                                                 # the shape's region
    prior = np.zeros((2, n, 3))
    prior[0, jaw] = [0.0, 0.0, 0.004]                                        # the prior's jaw forward
    prior[1, ~jaw] = rng.normal(size=((~jaw).sum(), 3)) * 0.002              # another shape elsewhere
    W = np.array([[1.0, 0.0], [0.0, 1.0]])
    noise = rng.normal(size=(2, n, 3)) * 1e-4
    person = prior.copy()
    person[0, jaw] += [0.0, 0.0, 0.0015]                                     # the person: 1.5 mm further
    frames = neutral + np.einsum("fk,knc->fnc", W, person) + noise
    target = neutral + np.einsum("fk,knc->fnc", W, prior)                    # the prediction: the prior's
    base = expression_weights(W, prior, frames - target)
    assert base.shape == (2, n) and np.isclose(base.mean(), 1.0)
    assert base[0, jaw].max() < 0.1 * base[0, ~jaw].min()               # the shape's region: little weight
    assert np.allclose(base[1, jaw], base[1, 0]) and base[1, 0] >= base[1].max()  # frame 1: the jaw still
    _, t0 = rigid_transforms(frames, target, np.arange(n))
    _, t1 = rigid_transforms(frames, target, np.arange(n), weights=base)
    assert np.linalg.norm(t0[0]) > 3e-4                                      # moved to absorb the jaw
    assert np.linalg.norm(t1[0]) < 0.1 * np.linalg.norm(t0[0])              # stays (nearly) where scanned
    R = Rotation.from_euler("xyz", [0.8, -0.4, 0.3], degrees=True).as_matrix()
    moved = frames.copy()
    moved[1] = (frames[1] - [0.001, 0.0, 0.0]) @ R                           # head motion in frame 1
    R1, _ = rigid_transforms(moved, target, np.arange(n), weights=base)
    assert np.degrees(np.arccos(np.clip((np.trace(R1[1] @ R.T) - 1) / 2, -1, 1))) < 0.05   # of 0.95 deg


def test_kabsch_of_a_mirrored_frame_is_the_best_proper_rotation():
    """Static vertices whose best orthogonal fit is a reflection (a near-flat forehead patch, a mirrored
    scan): the rotation stays proper and is the weighted least-squares optimum among rotations (scipy's
    ``align_vectors``, Markley's solution), the smallest singular direction turned (any other turned column
    also gives a proper rotation, a worse one)."""
    rng = np.random.default_rng(9)
    src = rng.normal(size=(40, 3)) * [0.05, 0.03, 0.004]              # a thin patch
    dst = src * [1.0, 1.0, -1.0] @ Rotation.from_euler("xyz", [5, -3, 20], degrees=True).as_matrix().T
    w = rng.uniform(0.5, 1.5, size=40)
    R_k, t_k = kabsch(src[None], dst, w[None])
    assert np.isclose(np.linalg.det(R_k[0]), 1.0)
    cs, cd = np.average(src, axis=0, weights=w), np.average(dst, axis=0, weights=w)
    best, _ = Rotation.align_vectors(dst - cd, src - cs, weights=w)
    np.testing.assert_allclose(R_k[0], best.as_matrix(), atol=1e-9)
    np.testing.assert_allclose(t_k[0], cd - R_k[0] @ cs, atol=1e-12)


def test_poisson_solver_reports_disconnected_free_part():
    pts, tris = bumpy_grid(4, 4)
    extra = np.array([[100.0, 0, 0], [101, 0, 0], [100, 1, 0]])
    pts2 = np.r_[pts, extra]
    tris2 = np.r_[tris, [[16, 17, 18]]]
    with pytest.raises((GeometryError, RuntimeError)):
        PoissonSolver(pts2, tris2, fixed=[0]).solve(np.tile(np.eye(3), (len(tris2), 1, 1)),
                                                    fixed_points=pts2[[0]])


def test_position_fit_batched_predictions_reuse_and_short_grid_search():
    """The fit's exact speed-ups: prior widths' predictions in one product equal separate calls (and the
    module-level LOO); set_points / set_prior are no-ops only for what the fit already holds; the short
    re-tune grid evaluated in one batch finds what the coarse-then-fine search finds."""
    from usdface.personalize.crossval import _minimise_log
    from usdface.personalize.fit import loo_residuals

    neutral, pts, W, true, generic = synthetic_fit_problem(noise=0.0005, F=9, K=6)
    D = regularization_weights(generic)
    pf = PositionFit(neutral, pts, W, generic, D)
    reg = 0.02
    sets = np.stack([np.clip(W + s, 0, 1) for s in (0.0, 0.03, 0.07)])            # [S,F,K]
    many = pf.loo_residuals(reg, predict_weights=sets)
    for Pw, got in zip(sets, many, strict=True):
        assert np.abs(got - pf.loo_residuals(reg, predict_weights=Pw)).max() < 1e-15
        assert np.abs(got - loo_residuals(neutral, pts, W, generic, D, reg, predict_weights=Pw)).max() < 1e-12
    v = np.arange(5)
    part = pf.loo_residuals(reg, predict_weights=sets, vertices=v, loo=pf.loo_residuals(reg)[:, v])
    assert np.abs(part - many[:, :, v]).max() < 1e-15
    moved = pts.copy()
    pf.set_points(moved)                                                       # the same frames: no-op
    assert np.allclose(pf.solve(reg), fit_blendshapes(neutral, pts, W, generic, D, reg), atol=1e-12)
    moved[0] += 0.001                                                          # changed in place: seen
    pf.set_points(moved)
    assert np.allclose(pf.solve(reg), fit_blendshapes(neutral, moved, W, generic, D, reg), atol=1e-12)
    pf.set_prior(generic)                                                      # the prior it holds
    other = generic * 0.5
    pf.set_prior(other)
    assert np.allclose(pf.solve(reg), fit_blendshapes(neutral, moved, W, other, D, reg), atol=1e-12)

    def err(x):
        x = np.asarray(x, dtype=np.float64)
        return (x + 2.37) ** 2 + 0.1 * np.sin(3 * x)

    grid = np.log10(0.004) + np.array([-1.0, 0.0, 1.0])
    one_batch = _minimise_log(err, grid, 4)                                      # coarse + fine at once
    separate = _minimise_log(err, grid, 4, errs=err(grid))                       # coarse given: two steps
    assert abs(one_batch[0] - separate[0]) < 1e-12 and abs(one_batch[1] - separate[1]) < 1e-12


def test_the_reg_search_finds_a_parabolas_vertex_and_never_returns_a_worse_point():
    """``_minimise_log`` (the choice of ``reg``): on an error that is a parabola in ``log10 reg`` the vertex
    through the best fine point's neighbours is the exact minimum; on any error the point returned is no
    worse than every point the search evaluated (coarse and fine grids). Both on the full REG_GRID (coarse,
    then a fine grid) and on a short grid (one batched union grid)."""
    from usdface.personalize.crossval import REG_GRID, _minimise_log

    seen = []

    def parabola(x):
        x = np.asarray(x, dtype=np.float64)
        seen.append(x)
        return 2.0 + 0.3 * (x + 1.63) ** 2                   # above the nearest coarse point

    for grid in (REG_GRID, np.log10(0.004) + np.array([-1.0, 0.0, 1.0])):
        best, err, _ = _minimise_log(parabola, grid, 4)
        assert best == pytest.approx(-1.63, abs=1e-9) and err == pytest.approx(2.0, abs=1e-12)

    def bumpy(x):
        x = np.asarray(x, dtype=np.float64)
        seen.append(x)
        return (x + 2.3) ** 2 + 0.2 * np.sin(13 * x)

    for grid in (REG_GRID, np.log10(0.004) + np.array([-1.0, 0.0, 1.0])):
        seen.clear()
        best, err, _ = _minimise_log(bumpy, grid, 4)
        tried = np.concatenate(seen)
        assert err == pytest.approx(float(bumpy(np.array([best]))[0]), abs=1e-15)
        assert err <= bumpy(tried).min() + 1e-15


def test_position_fit_repeated_frames_and_kept_residuals():
    """Frames repeated to the bit (a capture app's kept scan) are evaluated once: the criteria still equal
    brute-force leave-one-frame-out refits (each copy left out alone, its twin kept), for either prior of
    the blend; the residuals kept for the next call at the same reg are dropped when the frames or the
    prior change."""
    neutral, pts, W, true, generic = synthetic_fit_problem(noise=0.0005, F=8, K=6)
    rep = [0, 1, 2, 2, 3, 4, 5, 0, 6, 7, 2]
    pts, W = pts[rep], W[rep]
    D = regularization_weights(generic)
    alt = 0.5 * generic
    pf = PositionFit(neutral, pts, W, generic, D, alt_deltas=alt)
    reg = 0.05

    def brute(prior, P):
        out = []
        for i in range(len(W)):
            keep = np.arange(len(W)) != i
            B = fit_blendshapes(neutral, P[keep], W[keep], prior, D, reg)
            out.append(P[i] - neutral - np.einsum("k,knc->nc", W[i], B))
        return np.array(out)                                                    # [F,n,3]

    e_main, e_alt = brute(generic, pts), brute(alt, pts)
    assert np.abs(pf.loo_residuals(reg) - e_main).max() < 1e-12
    first, inverse = pf.frame_groups()
    assert first.tolist() == [0, 1, 2, 4, 5, 6, 8, 9]
    assert first[inverse].tolist() == [0, 1, 2, 2, 4, 5, 6, 0, 8, 9, 2]
    other = np.clip(W + 0.03, 0, 1)                  # predictions with other weights: repeats computed once
    pred = pf.loo_residuals(reg, predict_weights=other)
    for i in range(len(W)):
        keep = np.arange(len(W)) != i
        B = fit_blendshapes(neutral, pts[keep], W[keep], generic, D, reg)
        assert np.abs(pred[i] - (pts[i] - neutral - np.einsum("k,knc->nc", other[i], B))).max() < 1e-12
    target = pts - pf.loo_residuals(reg)               # the alignment's: repeats have the same targets
    R, t = rigid_transforms(pts, target, np.arange(len(neutral)), groups=False)     # every frame on its own
    R2, t2 = rigid_transforms(pts, target, np.arange(len(neutral)), groups=pf.frame_groups())
    assert np.array_equal(R, R2) and np.array_equal(t, t2)             # the groups given: the same transforms
    assert np.allclose(pf.loo_frame_errors(reg), np.mean(e_main ** 2, axis=(1, 2)), rtol=1e-8, atol=0)
    mix = pf.loo_errors_mix([reg], (0.0, 1.0))[:, 0]
    assert np.allclose(mix, [np.mean(e_alt ** 2), np.mean(e_main ** 2)], rtol=1e-8, atol=0)
    kept = pf.loo_residuals(reg)
    assert pf.loo_residuals(reg) is kept and not kept.flags.writeable
    pf.set_prior_mix(0.0)                                                       # another prior: recomputed
    assert np.abs(pf.loo_residuals(reg) - e_alt).max() < 1e-12
    moved = pts.copy()
    moved[3] += 0.001                                                           # frame 3 no longer repeats 2
    pf.set_points(moved)
    assert np.abs(pf.loo_residuals(reg) - brute(alt, moved)).max() < 1e-12


def test_fits_on_several_threads_leave_the_hosts_blas_threads_as_they_were():
    """Each fit limited BLAS to one thread with its own threadpool_limits and put back what it found; on
    threads side by side (a host's pool, a Dask worker's threads) the last one out put back another's 1,
    and the host's numpy stayed single-threaded for good."""
    import threading

    from threadpoolctl import threadpool_info

    from usdface.personalize.api import single_threaded_blas

    def counts():
        return [d["num_threads"] for d in threadpool_info() if d["user_api"] == "blas"]

    before = counts()
    if max(before, default=1) < 2:
        pytest.skip("the host's BLAS runs one thread already: nothing to put back")
    first_in, second_in, go = threading.Event(), threading.Event(), threading.Event()

    @single_threaded_blas
    def first():
        first_in.set()
        second_in.wait(5)

    @single_threaded_blas
    def second():
        second_in.set()
        go.wait(5)

    one = threading.Thread(target=first)
    one.start()
    first_in.wait(5)
    two = threading.Thread(target=second)      # enters while the first is inside: finds BLAS at 1
    two.start()
    one.join()                                 # the first leaves first (it put back the host's counts),
    go.set()
    two.join()                                 # then the second (it put back the 1 it found)
    assert counts() == before


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="fork")
def test_a_fit_in_a_child_forked_while_another_thread_sets_the_blas_limit():
    """A host forking (``multiprocessing``'s default on Linux) while one of its threads held the limit's lock
    (setting the thread counts; making a new ThreadpoolController after imports takes milliseconds): the
    child's first fit waited for good on a lock held by a thread it does not have."""
    from usdface.personalize import api

    def block():
        with api.one_blas_thread():
            pass

    assert child_finishes(block, lambda: api._ONE_BLAS_THREAD._lock), \
        "the forked child waited for good on the BLAS limit's lock"



@pytest.mark.parametrize("first_on", ["main", "thread"])
def test_a_fit_on_any_thread_runs_with_one_blas_thread(first_on):
    """threadpoolctl lets only the first thread that set OpenBLAS's thread count (while it lives) set it
    again: after a personalize on a host's main thread, one on the host's worker thread (a thread pool, a
    DCC's background job) ran with the multi-threaded BLAS (its fit 4-6x slower on a busy machine), and a
    long-lived pool thread that went first did the same to the main thread's. Each thread sees one BLAS
    thread inside, and the host's counts are back after each."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from threadpoolctl import threadpool_info

    from usdface.personalize.api import single_threaded_blas

    def counts():
        return [d["num_threads"] for d in threadpool_info() if d["user_api"] == "blas"]

    before = counts()
    if max(before, default=1) < 2:
        pytest.skip("the host's BLAS runs one thread already: no limit to see")

    @single_threaded_blas
    def inside():
        return counts(), threading.current_thread().name

    with ThreadPoolExecutor(1) as pool:        # its thread lives on between the calls, as a host's pool
        on_thread = lambda: pool.submit(inside).result()   # noqa: E731
        calls = [inside, on_thread] if first_on == "main" else [on_thread, inside]
        for call in calls:
            seen, name = call()
            assert max(seen) == 1, f"BLAS ran {seen} threads inside a fit on {name}"
            assert counts() == before


def test_rigid_transforms_of_several_vertex_sets_side_by_side_are_each_sets_own_to_the_bit():
    """The alignment test's half-face fits run side by side (one batched 3x3 SVD an iteration): each vertex
    set gets the transforms :func:`rigid_transforms` gives it alone, with and without repeated frames and
    prior weights, sets of different sizes (odd and even, for the median)."""
    rng = np.random.default_rng(5)
    F, n = 7, 40
    ref = rng.normal(size=(n, 3))
    rot = Rotation.from_rotvec(rng.normal(scale=0.05, size=(F, 3))).as_matrix()
    pts = np.einsum("fij,nj->fni", rot, ref) + rng.normal(scale=0.01, size=(F, 1, 3))
    pts += rng.normal(scale=1e-3, size=pts.shape)
    pts[3] = pts[1]                                             # a repeated frame
    target = pts + rng.normal(scale=1e-3, size=pts.shape)
    target[3] = target[1]
    base = rng.uniform(0.5, 1.5, size=(F, n))
    base[3] = base[1]
    sets = [np.arange(0, 17), np.arange(10, 40), np.flatnonzero(np.arange(n) % 3 == 0), np.arange(n) < 25]
    for groups in (False, ((np.array([0, 1, 2, 4, 5, 6])), np.array([0, 1, 2, 1, 3, 4, 5]))):
        for weights in (None, base):
            together = rigid_transforms_sets(pts, target, sets, groups=groups, weights=weights)
            for vertices, (R, t) in zip(sets, together, strict=True):
                alone = rigid_transforms(pts, target, vertices, groups=groups,
                                         weights=None if weights is None
                                         else weights[:, np.flatnonzero(vertices) if vertices.dtype == bool
                                                      else vertices])
                assert np.array_equal(R, alone[0]) and np.array_equal(t, alone[1])
    # no set (every half-face too small): no transforms, as a loop over no sets (an IndexError before)
    assert rigid_transforms_sets(pts, target, [], groups=False) == []
