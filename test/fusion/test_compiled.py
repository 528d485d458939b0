"""The split-CI fold of ``fusion.compiled`` against numpy's (``source_sums.fold_numpy``)."""

import os
from pathlib import Path
import re
import subprocess
import sys

from hypothesis import given, settings, strategies as st
from landmark_ros.core.gaussian import split_covariance_intersection_omega
from landmark_ros.fusion import compiled, source_sums
import numpy as np
import pytest


def sums_of(seed, landmarks, width):
    """Return ``sums, lo, hi`` of random sources (some with indefinite ``Q`` parts)."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(1, width + 1, landmarks)
    sums = np.zeros((counts.sum(), 9))
    for j, n in enumerate(rng.integers(1, 4, len(sums)).tolist()):
        A = rng.normal(0.0, 0.3, (n, 2, 2)) * 10.0 ** rng.uniform(-3, 3)
        R = A @ np.swapaxes(A, 1, 2) + 1e-4 * np.eye(2)
        B = rng.normal(0.0, 0.2, (n, 2, 2))
        R_dep = rng.uniform(0.0, 0.8, (n, 1, 1)) * (
            R if rng.uniform() < 0.7 else B @ np.swapaxes(B, 1, 2) * R[:, :1, :1])
        sums[j] = source_sums.terms(rng.normal(0.0, 5.0, (n, 2)), R, R_dep).sum(axis=0)
    hi = np.cumsum(counts)
    slots = np.random.default_rng(seed).permutation(len(sums))    # table rows in any order
    table = np.full((len(sums) + 3, compiled.COLUMNS), np.nan)
    table[slots, :9] = sums
    table[:, compiled.DIRTY] = 1.0      # no kept fold yet
    return table, slots, hi - counts, hi


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), landmarks=st.integers(1, 6), width=st.integers(1, 6),
       independent=st.booleans())
def test_the_plain_python_fold_is_numpys_bit_for_bit(seed, landmarks, width, independent):
    # The functions numba compiles, run as plain Python: the same IEEE operations.
    pairs = sums_of(seed, landmarks, width)
    np.testing.assert_array_equal(compiled.fold_python(*pairs, independent=independent),
                                  source_sums.fold_numpy(*pairs, independent=independent))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), width=st.integers(1, 8), rounds=st.integers(1, 4))
def test_a_kept_fold_redone_from_the_first_change_is_the_whole_fold(seed, width, rounds):
    # Change some sources' sums (marked dirty) between folds: the plain Python fold,
    # which starts from the first place that changed, gives numpy's whole fold.
    table, slots, lo, hi = sums_of(seed, 5, width)
    rng = np.random.default_rng(seed)
    for _ in range(rounds):
        np.testing.assert_array_equal(compiled.fold_python(table, slots, lo, hi),
                                      source_sums.fold_numpy(table, slots, lo, hi))
        assert not table[slots, compiled.DIRTY].any()     # each fold kept
        changed = slots[rng.uniform(size=len(slots)) < 0.3]
        R = np.eye(2) * 10.0 ** rng.uniform(-2, 2, (len(changed), 1, 1))
        table[changed, :9] += source_sums.terms(rng.normal(size=(len(changed), 2)), R, 0.3 * R)
        table[changed, compiled.DIRTY] = 1.0


@pytest.mark.parametrize('independent', [False, True])
def test_the_compiled_fold_is_numpys_bit_for_bit_or_absent(independent):
    pairs = sums_of(3, 400, 7)
    expected = source_sums.fold_numpy(*pairs, independent)
    if compiled.load():
        np.testing.assert_array_equal(compiled.fold(*pairs, independent), expected)
    else:   # numba missing or turned off: the numpy fold serves, nothing else
        assert compiled.fold(*pairs, independent) is None and not compiled.ready()
    np.testing.assert_array_equal(source_sums.fold(*pairs, independent).m, expected[:, :2])


def test_turned_off_by_the_environment_and_never_waited_for():
    # In a fresh interpreter: a map is built and used at once, whatever numba does;
    # LANDMARK_ROS_NUMBA=0 keeps numba out of the process.
    script = (
        'import sys, threading\n'
        'from landmark_ros.fusion import compiled\n'
        'from landmark_ros.fusion.landmark_map import LandmarkMap\n'
        'm = LandmarkMap(); m.update([1, 1], [[0, 0], [0, 0.1]], [[[1, 0], [0, 1]]] * 2)\n'
        'loader = compiled._state["thread"]\n'
        'assert loader.daemon and loader is not threading.current_thread()\n'
        'print(len(m), compiled.load(120), "numba" in sys.modules)\n')
    for value, numba_loaded in (('0', False), ('1', None)):
        env = dict(os.environ, LANDMARK_ROS_NUMBA=value)
        out = subprocess.run([sys.executable, '-c', script], env=env, capture_output=True,
                             text=True, check=True, timeout=300).stdout.split()
        assert out[0] == '1'
        if numba_loaded is False:
            assert out[1:] == ['False', 'False']
        else:
            assert out[1] == out[2]     # ready exactly when numba could be loaded


def test_the_scalar_weight_search_stays_inside_a_collapsed_bracket():
    # test_fusion's case (scales 1e-12 to 1e12, the slope rounding noise): the scalar
    # search gives core.gaussian's weight.
    P1i = np.array([[285288441006.45984, 444295202210.24756],
                    [444295202210.24756, 691958552321.5609]])
    P2i = np.array([[977237220955.8112, 0.0], [0.0, 1000.0]])
    P1d = np.array([[9.965365501409348e-06, -2.1774718636614557e-05],
                    [-2.1774718636614557e-05, 4.757862925559931e-05]])
    P2d = 1.0232929922807536e-12 * np.eye(2)
    omega = split_covariance_intersection_omega(P1i, P1d, P2i, P2d)
    packed = [np.array([0.0, 0.0, *P_ind[[0, 0, 1], [0, 1, 1]], *P_dep[[0, 0, 1], [0, 1, 1]]])
              for P_ind, P_dep in ((P1i, P1d), (P2i, P2d))]
    assert compiled._omega_of(*packed, compiled._limits()) == omega


def test_only_the_compiled_module_imports_numba():
    package = Path(compiled.__file__).resolve().parents[1]
    importers = sorted(str(path.relative_to(package)) for path in package.rglob('*.py')
                       if re.search(r'^\s*(import numba|from numba)', path.read_text(), re.M))
    assert importers == ['fusion/compiled.py']


def test_the_compiled_accumulation_is_add_at_bit_for_bit_or_absent():
    # Repeated slots: each slot's rows added one after the other, as np.add.at does.
    rng = np.random.default_rng(4)
    table = rng.normal(0.0, 1.0, (50, compiled.COLUMNS)) * 10.0 ** rng.uniform(-8, 8, (50, 1))
    slots = rng.integers(0, 50, 2000)
    added = rng.normal(0.0, 1.0, (2000, 9)) * 10.0 ** rng.uniform(-8, 8, (2000, 1))
    want = table.copy()
    for j in range(9):
        np.add.at(want[:, j], slots, added[:, j])
    if compiled.load():
        assert compiled.accumulate(table, slots, added)
        np.testing.assert_array_equal(table, want)
    else:
        assert not compiled.accumulate(table, slots, added)
