"""The reference filter of change detection against its definition (fuser.change_reference)."""

from landmark_ros.fuser.change_reference import NoiseModel, ReferenceFilter, split_noise
import numpy as np
import pytest

S = 1_000_000_000


def _rotation(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s], [s, c]])


def test_split_noise_puts_the_range_share_on_the_major_axis():
    # A row 30 degrees off the x axis: range variance 0.04 along it, bearing 0.0025
    # across it, plus a dependent part that is correlated as a whole.
    U = _rotation(np.pi / 6)
    R_ind = U @ np.diag([0.04, 0.0025]) @ U.T
    P_dep = np.array([[0.001, 0.0002], [0.0002, 0.002]])
    W, C = split_noise((R_ind + P_dep)[None], P_dep[None], NoiseModel(5.0, 0.9, 0.5))
    assert W[0] == pytest.approx(U @ np.diag([0.004, 0.00125]) @ U.T, abs=1e-15)
    assert C[0] == pytest.approx(U @ np.diag([0.036, 0.00125]) @ U.T + P_dep, abs=1e-15)
    W, C = split_noise((R_ind + P_dep)[None], P_dep[None], NoiseModel(0.0, 0.9, 0.5))
    assert W[0] == pytest.approx(R_ind + P_dep) and not C.any()


def _rows(rng, count, sources, tau, R, fraction, start=0.0, period=0.5):
    """Rows of one landmark at the origin from ``sources`` in turn, GM noise per source."""
    W, C = (1.0 - fraction) * R, fraction * R
    state = {s: rng.multivariate_normal(np.zeros(2), C) for s in sources}
    last = {s: None for s in sources}
    rows = []
    for k in range(count):
        source = sources[k % len(sources)]
        t = start + k * period
        if last[source] is not None and tau > 0:
            phi = np.exp(-(t - last[source]) / tau)
            state[source] = phi * state[source] + rng.multivariate_normal(
                np.zeros(2), (1 - phi ** 2) * C)
        last[source] = t
        rows.append((source, t, state[source] + rng.multivariate_normal(np.zeros(2), W)))
    return rows


def _joint_innovations(rows, tau, R, fraction):
    """
    Return the definition: d2 of each row given the rows before it (universal kriging).

    ``z = 1 p + e`` with a flat prior on ``p`` and the joint covariance of ``e`` from
    the model; the innovation of row k is ``z_k`` minus its best linear unbiased
    prediction from the rows before, its covariance that of the prediction error.
    """
    W, C = (1.0 - fraction) * R, fraction * R
    n = len(rows)
    Sigma = np.zeros((2 * n, 2 * n))
    for i, (si, ti, _) in enumerate(rows):
        for j, (sj, tj, _) in enumerate(rows):
            block = np.zeros((2, 2))
            if i == j:
                block = W + C
            elif si == sj and tau > 0:
                block = np.exp(-abs(ti - tj) / tau) * C
            Sigma[2 * i:2 * i + 2, 2 * j:2 * j + 2] = block
    z = np.concatenate([r[2] for r in rows])
    A = np.tile(np.eye(2), (n, 1))
    d2 = [np.nan]
    for k in range(1, n):
        past, now = slice(0, 2 * k), slice(2 * k, 2 * k + 2)
        S_pp, S_kp = Sigma[past, past], Sigma[now, past]
        Ap = A[past]
        G = np.linalg.solve(S_pp, Ap)
        p_hat = np.linalg.solve(Ap.T @ G, G.T @ z[past])
        L = S_kp @ np.linalg.inv(S_pp)
        nu = z[now] - p_hat - L @ (z[past] - Ap @ p_hat)
        B = np.eye(2) - L @ Ap
        V = Sigma[now, now] - L @ S_kp.T + B @ np.linalg.inv(Ap.T @ G) @ B.T
        d2.append(float(nu @ np.linalg.solve(V, nu)))
    return np.array(d2)


def _filter_innovations(rows, tau, R, fraction, batch):
    """Return the filter's d2 of ``rows`` (landmark 7), fed ``batch`` rows at a time."""
    reference = ReferenceFilter(NoiseModel(tau, fraction, fraction), clip=1e9)
    out = []
    for begin in range(0, len(rows), batch):
        part = rows[begin:begin + batch]
        P = np.broadcast_to(R, (len(part), 2, 2)).copy()
        out.append(reference.innovations(
            np.full(len(part), 7), np.array([r[2] for r in part]), P, np.zeros_like(P),
            [r[0] for r in part], np.array([int(r[1] * S) for r in part])))
    return np.concatenate(out)


@pytest.mark.parametrize('tau, fraction, sources, batch', [
    (0.0, 0.0, ['a'], 1), (0.0, 0.0, ['a', 'b'], 3),
    (8.0, 0.9, ['a'], 1), (8.0, 0.9, ['a', 'b', 'c'], 1), (3.0, 0.6, ['a', 'b'], 4)])
def test_innovations_are_those_of_the_joint_gaussian_model(tau, fraction, sources, batch):
    rng = np.random.default_rng(3)
    R = np.array([[0.02, 0.004], [0.004, 0.01]])
    rows = _rows(rng, 14, sources, tau, R, fraction)
    want = _joint_innovations(rows, tau, R, fraction)
    got = _filter_innovations(rows, tau, R, fraction, batch)
    # Each source's first row is white only for the filter's start (a new source block).
    assert np.isnan(got[0]) and np.isnan(want[0])
    assert got[1:] == pytest.approx(want[1:], rel=1e-6)


def test_correlated_rows_give_white_chi_square_innovations_only_when_modelled():
    # Rows every 0.5 s from three sources in turn, 0.9 of the variance correlated over
    # 8 s: the filter's d2 average 2 and a source's consecutive d2 (lag 3) are
    # uncorrelated; with the white model (tau 0, the mutation) they are correlated.
    rng = np.random.default_rng(11)
    R = np.diag([0.01, 0.002])
    modelled, white = [], []
    for _ in range(40):
        rows = _rows(rng, 120, ['a', 'b', 'c'], 8.0, R, 0.9)
        modelled.append(_filter_innovations(rows, 8.0, R, 0.9, 5)[4:])
        white.append(_filter_innovations(rows, 0.0, R, 0.0, 5)[4:])

    def lag3(runs):
        return np.corrcoef(np.concatenate([d[:-3] for d in runs]),
                           np.concatenate([d[3:] for d in runs]))[0, 1]
    assert np.mean(np.concatenate(modelled)) == pytest.approx(2.0, abs=0.1)
    assert abs(lag3(modelled)) < 0.05
    assert lag3(white) > 0.3


def test_a_wild_row_does_not_move_the_reference_and_reset_restarts_it():
    reference = ReferenceFilter(NoiseModel(), clip=13.8)
    P = np.broadcast_to(0.01 * np.eye(2), (3, 2, 2)).copy()
    z = np.array([[0.0, 0.0], [0.1, 0.0], [3.0, 0.0]])
    d2 = reference.innovations(np.array([1, 1, 1]), z, P, 0 * P, ['a'] * 3,
                               np.array([1, 2, 3]) * S)
    assert np.isnan(d2[0]) and d2[1] == pytest.approx(0.5) and d2[2] > 13.8
    assert reference.x[reference.slots[1]] == pytest.approx([0.05, 0.0])
    reference.reset([1])
    assert np.isnan(reference.innovations(np.array([1]), z[2:], P[:1], 0 * P[:1], ['a'],
                                          np.array([4 * S]))[0])


def test_white_rows_in_one_batch_equal_one_at_a_time_with_wild_rows():
    """Several landmarks, several rows past the clip each: a batch equals rows one by one."""
    rng = np.random.default_rng(21)
    n = 400
    ids = rng.integers(0, 5, n)
    P = np.array([[0.02, 0.004], [0.004, 0.01]]) * rng.uniform(0.5, 2.0, (n, 1, 1))
    z = rng.multivariate_normal([0.0, 0.0], np.diag([0.02, 0.01]), n)
    z[rng.random(n) < 0.05] += 5.0                        # wild rows, some in a row
    z[[30, 31, 32]] += 5.0
    stamps = np.arange(n) * S
    whole = ReferenceFilter(NoiseModel(), clip=13.8)
    got = whole.innovations(ids, z, P, 0 * P, ['a'] * n, stamps)
    single = ReferenceFilter(NoiseModel(), clip=13.8)
    want = np.concatenate([single.innovations(ids[k:k + 1], z[k:k + 1], P[k:k + 1],
                                              0 * P[k:k + 1], ['a'], stamps[k:k + 1])
                           for k in range(n)])
    assert np.isnan(got).sum() == 5 and (want[np.isfinite(want)] > 13.8).sum() > 20
    np.testing.assert_allclose(got, want, rtol=1e-9)
    for landmark_id in range(5):
        a, b = whole.slots[landmark_id], single.slots[landmark_id]
        np.testing.assert_allclose(whole.x[a], single.x[b], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(whole.X[a], single.X[b], rtol=1e-9, atol=1e-15)
