"""The eyelid repair's spread (usdface.transfer.eyelids._spread_corrections): each lid vertex near corrections
takes their weighted mean times the fade, capped by the shape's own offset there. Its sums over the
(correction, lid vertex) pairs are one sparse product (issue 12: the twice-subdivided head's lid has 28M
pairs); these tests hold it to the formula computed the long way (every distance, dense) and to the bits of a
per-column bincount, which is what the repair computed before."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.spatial import cKDTree

from usdface.transfer import eyelids
from usdface.transfer.correspond import ramp_down


def _case(seed: int = 3, n: int = 900, shapes: int = 3, corrections: int = 300):
    """A lid patch ``x0[n,3]`` (metres, 30 mm square, slightly curved), shapes ``out[J,n,3]`` that move every
    vertex but a few, and corrections at random (shape, vertex) pairs."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform(-0.015, 0.015, size=(n, 2))
    x0 = np.column_stack([uv, 0.02 * (uv ** 2).sum(axis=1)])
    out = rng.normal(scale=1e-3, size=(shapes, n, 3))
    out[1, rng.choice(n, 40, replace=False)] = 0.0            # vertices shape 1 does not move
    near = np.sort(rng.choice(n, n - 100, replace=False))
    pick = np.unique(rng.choice(shapes * near.size, corrections, replace=False))
    js, ks = pick // near.size, pick % near.size
    correction = rng.normal(scale=2e-4, size=(js.size, 3))
    return x0, out, near, js, ks, correction


def _long_way(out, x0, near, js, ks, correction, radius):
    """The spread by its definition, every (correction, near vertex) distance formed densely."""
    out = out.copy()
    reach = 1.25 * radius
    for j in np.unique(js):
        mine = np.flatnonzero(js == j)
        c = correction[mine]
        m = np.linalg.norm(c, axis=1)
        d = np.linalg.norm(x0[near][:, None, :] - x0[near[ks[mine]]][None], axis=-1)      # [k, P]
        mag = np.linalg.norm(out[j, near], axis=1)
        moves = (mag > 0)[:, None]
        w = ramp_down(d, 0.0, radius) * m * moves                                          # 0 beyond radius
        fade = np.where(d <= radius, 1.0, ramp_down(d, radius, reach)) * m * moves
        total = w.sum(axis=1)
        v = np.flatnonzero(total > 0)
        step = (w @ c)[v] / total[v, None] * (w.max(axis=1)[v] / fade.max(axis=1)[v])[:, None]
        cap = np.minimum(1.0, mag[v] / np.maximum(np.linalg.norm(step, axis=1), 1e-300))
        out[j, near[v]] += step * cap[:, None]
    return out


@pytest.mark.parametrize("chunk", [eyelids.SPREAD_CHUNK, 37])
def test_the_spread_is_its_formula_computed_the_long_way(monkeypatch, chunk):
    """Every output offset within 1e-12 of the dense formula (sums in another order), whether the
    corrections are spread 256 or 37 at a time."""
    monkeypatch.setattr(eyelids, "SPREAD_CHUNK", chunk)
    x0, out, near, js, ks, correction = _case()
    radius = 0.006
    got = out.copy()
    eyelids._spread_corrections(got, x0, near, js, ks, correction, radius, cKDTree(x0[near]))
    want = _long_way(out, x0, near, js, ks, correction, radius)
    assert not np.array_equal(got, out)                        # (it moved something)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want - out).max())


def test_the_sparse_product_adds_the_pairs_in_their_order():
    """The spread's sums rely on scipy's COO product adding ``a[p] x own[fr[p]]`` to row ``to[p]`` pair by
    pair, in the pairs' order: bit for bit the per-column ``bincount`` of those products (what the repair
    summed before, so its output did not change), signed zeros included."""
    rng = np.random.default_rng(7)
    pairs, rows, cols = 200_000, 5_000, 300
    to, fr = rng.integers(0, rows, pairs), rng.integers(0, cols, pairs)
    a = rng.random(pairs) * 10.0 ** rng.integers(-6, 0, pairs)
    a[::17] = 0.0
    own = np.column_stack([np.ones(cols),
                           rng.normal(size=(cols, 3)) * 10.0 ** rng.integers(-6, -2, (cols, 1))])
    got = coo_matrix((a, (to, fr)), shape=(rows, cols)) @ own
    for c in range(4):
        want = np.bincount(to, weights=a * own[fr, c], minlength=rows)
        assert got[:, c].tobytes() == want.tobytes()


def test_the_ramp_computed_in_its_input_gives_the_same_bits():
    """``ramp_down(x, lo, hi, overwrite=True)`` (the spread's weights, computed in the pairs' distances) is
    the plain ramp to the bit - below ``lo``, above ``hi``, at both ends and between - and is ``x`` itself."""
    rng = np.random.default_rng(11)
    lo, hi = 0.0075, 1.25 * 0.0075
    ends = [0.0, lo, hi, np.nextafter(lo, 1), np.nextafter(hi, 0)]
    x = np.concatenate([rng.uniform(0.0, 0.012, 10_000), ends])
    for a, b in [(lo, hi), (0.0, lo)]:
        want = ramp_down(x, a, b)
        work = x.copy()
        got = ramp_down(work, a, b, overwrite=True)
        assert got is work
        assert got.tobytes() == want.tobytes()
