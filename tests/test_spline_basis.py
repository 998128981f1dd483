"""Basis functions: partition of unity, derivatives, spans at the ends."""

import numpy as np
import pytest

from volpuzzle.spline import basis


@pytest.mark.parametrize("p", [1, 2, 3, 5])
def test_partition_of_unity_and_derivative_sum(p):
    rng = np.random.default_rng(p)
    knots = np.r_[[0.0] * (p + 1), np.sort(rng.uniform(0, 1, 4)), [1.0] * (p + 1)]
    t = np.r_[rng.uniform(0, 1, 100), 0.0, 1.0]
    d = basis.basis_derivatives(knots, p, t, 1)
    np.testing.assert_allclose(d[:, 0].sum(1), 1.0, atol=1e-14)
    np.testing.assert_allclose(d[:, 1].sum(1), 0.0, atol=1e-10)
    m = basis.basis_matrix(knots, p, t, 1)
    np.testing.assert_allclose(m[0].sum(1), 1.0, atol=1e-14)
    assert np.all(m[0] >= 0)


def test_span_at_end_skips_empty_spans():
    knots = np.array([0, 0, 0, 0.5, 1, 1, 1.0])
    assert basis.find_span(knots, 2, [1.0])[0] == 3
    assert basis.last_span(knots, 2) == 3
    assert basis.find_span(knots, 2, [0.0])[0] == 2
