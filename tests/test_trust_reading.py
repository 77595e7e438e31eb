"""The implant's trust raised by the capture's test frames' reading of each shape's personalization scale
(:func:`usdface.transfer.trust.raised_by_reading`)."""

from __future__ import annotations

import numpy as np

from usdface.transfer.trust import WITHHELD, raised_by_reading


def test_the_trust_is_only_raised_and_never_past_the_fitted_shape():
    """Every output at least the trust and at most 1 (or the trust where it is above); a reading below the
    trust leaves it."""
    rng = np.random.default_rng(0)
    trust = rng.uniform(0, 1, 200)
    reading = rng.normal(1.0, 1.0, 200)
    out = raised_by_reading(trust, reading, rng.uniform(0.0, 0.1, 200) ** 2)
    assert np.all(out >= trust) and np.all(out <= np.maximum(trust, 1.0))
    low = reading < trust
    np.testing.assert_array_equal(out[low], trust[low])


def test_an_uninformative_reading_never_raises_however_far_it_lies():
    """A reading whose bound at a full personalization would not clear 0 (``z sd >= 1``, the test frames show
    the shape weakly) leaves the trust, even at 50 times the fitted scale; the same reading at a small spread
    raises it to 1."""
    trust = np.zeros(10)
    reading = np.full(10, 50.0)
    sd = np.full(10, 0.6)                       # z = 2.58 at 5 % over 10 shapes: z sd = 1.55
    np.testing.assert_array_equal(raised_by_reading(trust, reading, sd ** 2), trust)
    np.testing.assert_array_equal(raised_by_reading(trust, reading, (sd / 10) ** 2), np.ones(10))
    # a shape the test frames do not show (infinite variance) is left too
    assert raised_by_reading(np.zeros(1), np.ones(1), np.full(1, np.inf))[0] == 0.0


def test_no_more_than_the_level_of_captures_has_any_shape_raised_past_its_scale():
    """The bound is one-sided and Bonferroni over the shapes tested: over 4000 simulated captures of 40
    untrusted shapes, each read at its true scale ``c`` (0-1) with a Gaussian error of its stated spread,
    no more than 5 % (up to the simulation's error) have any shape's trust raised above its ``c``; shapes
    already trusted fully are not tested, so they do not widen the others' bound."""
    rng = np.random.default_rng(1)
    n, K = 4000, 40
    c = rng.uniform(0, 1, (n, K))
    sd = rng.uniform(0.01, 0.4, (n, K))
    reading = c + sd * rng.normal(size=(n, K))
    past = np.array([np.any(raised_by_reading(np.zeros(K), reading[i], sd[i] ** 2) > c[i] + 1e-12)
                     for i in range(n)])
    assert past.mean() < 0.05 + 3 * np.sqrt(0.05 * 0.95 / n), past.mean()
    # one untrusted shape beside 39 trusted ones: tested alone (z = 1.645), not among 40 (z = 3.02)
    trust = np.ones(K)
    trust[0] = 0.0
    out = raised_by_reading(trust, np.full(K, 0.9), np.full(K, 0.1 ** 2))
    np.testing.assert_allclose(out[0], 0.9 - 1.6448536 * 0.1, atol=1e-6)


def test_a_shape_the_trust_keeps_nearer_the_person_is_not_raised():
    """A trust at or above :data:`WITHHELD` (the shape kept nearer the person's than the generic) stays as
    it is under a sure reading of 1; the one below it is raised, and only it counts in the Bonferroni."""
    trust = np.array([WITHHELD, 0.8, 0.1])
    out = raised_by_reading(trust, np.ones(3), np.full(3, 0.01 ** 2))
    np.testing.assert_array_equal(out[:2], trust[:2])
    np.testing.assert_allclose(out[2], 1.0 - 1.6448536 * 0.01, atol=1e-6)
