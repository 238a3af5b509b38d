"""Property tests of the transform and grid maths (Hypothesis)."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from gtgen.geometry import (
    apply,
    invert,
    make_transform,
    matrix_to_quat,
    quat_to_matrix,
    quat_to_yaw,
    rpy_to_quat,
    slerp,
    yaw_transform,
)
from gtgen.grids import bilinear, cell_centers, xy_to_index

angles = st.floats(-np.pi, np.pi, allow_nan=False)


@given(angles, st.floats(-1.4, 1.4), angles)
def test_quaternion_roundtrip(roll, pitch, yaw):
    q = rpy_to_quat(roll, pitch, yaw)
    R = quat_to_matrix(q)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    q2 = matrix_to_quat(R)
    assert min(np.abs(q - q2).max(), np.abs(q + q2).max()) < 1e-9
    assert abs(np.angle(np.exp(1j * (quat_to_yaw(q) - yaw)))) < 1e-9


@given(angles, st.floats(-1.4, 1.4), angles, st.lists(st.floats(-100, 100), min_size=3, max_size=3))
def test_invert_is_inverse(roll, pitch, yaw, t):
    T = make_transform(quat_to_matrix(rpy_to_quat(roll, pitch, yaw)), np.array(t))
    np.testing.assert_allclose(T @ invert(T), np.eye(4), atol=1e-9)


@given(angles, angles, st.floats(0, 1))
def test_slerp_endpoints_and_unit_norm(y0, y1, a):
    q0, q1 = rpy_to_quat(0, 0, y0)[None], rpy_to_quat(0, 0, y1)[None]
    np.testing.assert_allclose(np.abs(np.sum(slerp(q0, q1, np.array([0.0])) * q0)), 1, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(slerp(q0, q1, np.array([1.0])) * q1)), 1, atol=1e-9)
    assert abs(np.linalg.norm(slerp(q0, q1, np.array([a]))) - 1) < 1e-9


@settings(max_examples=200)
@given(st.integers(1, 600), st.sampled_from([0.1, 0.2, 0.8, 1.0]), st.data())
def test_cell_centre_and_index_agree(size, res, data):
    """SPEC section 3: cell (i, j) centre = (-L/2 + (i + .5) r, ...); index 0 at the most negative x."""
    i = data.draw(st.integers(0, size - 1))
    c = cell_centers(size, res)
    assert abs(c[i] - (-size * res / 2 + (i + 0.5) * res)) < 1e-9
    ii, jj = xy_to_index(np.array([c[i]]), np.array([c[0]]), size, res)
    assert (ii[0], jj[0]) == (i, 0)
    bad_i, _ = xy_to_index(np.array([size * res]), np.array([0.0]), size, res)
    assert bad_i[0] == -1


@given(angles, st.floats(-50, 50), st.floats(-50, 50))
def test_yaw_transform_moves_points(yaw, x, y):
    T = yaw_transform(x, y, 1.0, yaw)
    p = apply(T, np.array([[1.0, 0.0, 0.0]]))[0]
    np.testing.assert_allclose(p, [x + np.cos(yaw), y + np.sin(yaw), 1.0], atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 9), st.integers(1, 9), st.integers(0, 2**32 - 1), st.sampled_from([np.float32, np.float64]))
def test_bilinear_with_nan_outside_gives_the_bits_of_map_coordinates(n, m, seed, dtype):
    """The gathering sampler of float grids (outside="nan") against scipy's order-1
    map_coordinates, its oracle: the same values to the bit at cell centres, just off them,
    halfway, beyond the outer centres, at NaN coordinates, next to NaN and infinite cells."""
    from scipy.ndimage import map_coordinates

    rng = np.random.default_rng(seed)
    g = rng.normal(0, 100, (3, n, m)).astype(dtype)
    g[rng.random(g.shape) < 0.15] = np.nan
    g[rng.random(g.shape) < 0.05] = np.inf
    size = 64
    r = rng.integers(-1, n + 1, size) + rng.choice([0.0, 0.5, 0.25, 1e-12, -1e-12, 0.7], size)
    c = rng.integers(-1, m + 1, size) + rng.choice([0.0, 0.5, 0.75, 1e-12, -1e-12, 0.3], size)
    r[:8] = rng.uniform(-1, n, 8)
    r[8], c[9], r[10], c[10] = np.nan, np.nan, np.inf, -np.inf
    got = bilinear(g, r.reshape(8, 8), c.reshape(8, 8))
    want = np.stack([map_coordinates(x, [r, c], order=1, mode="constant", cval=np.nan, prefilter=False) for x in g])
    assert got.dtype == want.dtype and got.shape == (3, 8, 8)
    assert np.array_equal(got.reshape(3, -1), want, equal_nan=True)
    import gtgen.grids as grids_module

    chunk, grids_module.GATHER_CHUNK = grids_module.GATHER_CHUNK, 5  # passes of a few points: the same values
    try:
        assert np.array_equal(bilinear(g, r, c), want, equal_nan=True)
    finally:
        grids_module.GATHER_CHUNK = chunk


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 9), st.integers(1, 9), st.integers(0, 2**32 - 1), st.sampled_from([np.float32, np.float64]))
def test_bilinear_on_a_grid_of_coordinates_equals_the_general_sampler(n, m, seed, dtype):
    """The separable pass (rows x cols of coordinates, edge cells extended) against
    map_coordinates on the same coordinate pairs (its oracle), inside and beyond the grid."""
    rng = np.random.default_rng(seed)
    g = rng.normal(0, 10, (2, n, m)).astype(dtype)
    r, c = rng.uniform(-2, n + 1, 7), rng.uniform(-2, m + 1, 5)
    r[:2], c[:2] = (0, n - 1), (0, m - 1)  # the outer centres exactly
    fast = bilinear(g, r[:, None], c[None, :], outside="edge")
    R, C = np.broadcast_arrays(r[:, None], c[None, :])
    general = bilinear(g, R.copy(), C.copy(), outside="edge")
    assert fast.shape == general.shape == (2, 7, 5) and fast.dtype == general.dtype
    np.testing.assert_allclose(fast, general, rtol=0, atol=1e-4 if dtype == np.float32 else 1e-10)


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 40), st.integers(0, 4), st.integers(0, 2**32 - 1), st.sampled_from([np.float32, np.float64]))
def test_finite_rows_and_all_columns_equal_numpys_row_reductions(n, k, seed, dtype):
    """The column-by-column row tests against NumPy's ``all(axis=1)`` and boolean indexing
    (their oracles), with NaN and infinite values, no rows and no columns."""
    from gtgen.geometry import all_columns, finite_rows

    rng = np.random.default_rng(seed)
    pts = rng.normal(0, 1e3, (n, k)).astype(dtype)
    pts[rng.random(pts.shape) < 0.1] = np.nan
    pts[rng.random(pts.shape) < 0.05] = -np.inf
    ok = np.isfinite(pts)
    assert np.array_equal(all_columns(ok), np.all(ok, axis=1))
    got, want = finite_rows(pts), pts[np.all(ok, axis=1)]
    assert got.dtype == want.dtype and got.shape == want.shape and np.array_equal(got, want)
