"""Tests of landmark_ros.eval.exercises against the textbook's figures."""

from pathlib import Path
import subprocess
import sys

from landmark_ros.eval import exercises
import numpy as np
import pytest


REPO_ROOT = Path(__file__).resolve().parents[2]
ATOL = 1e-8

M1 = [2.44943102, 5.72815634]
P_M1_EXACT = [[0.58879177, -0.13171532], [-0.13171532, 0.30120823]]
P_M1 = [[0.94677477, -0.23978943], [-0.23978943, 0.94322523]]
P12 = [5.34676389, -0.64196257, 1.6]
P12_COV = [[0.38248035, 0.24115, 0.01283925],
           [0.24115, 1.16751965, 0.10693528],
           [0.01283925, 0.10693528, 0.05]]
Z = [3.94880545, 0.58862004]
P_Z = [[1.31374309, -0.02614814], [-0.02614814, 0.08555399]]
P_Z_TEXTBOOK = [[1.41886714, 0.01057848], [0.01057848, 0.07881227]]
M2 = [3.05042514, 6.70185272]
P_M2 = [[0.84693794, 0.4333316], [0.4333316, 0.81306206]]
M_FUSED = [2.58757252, 6.15534036]
P_FUSED = [[0.37966125, 0.07773125], [0.07773125, 0.36999739]]


def close(actual, expected):
    np.testing.assert_allclose(actual, expected, rtol=0.0, atol=ATOL)


def run_module(*args, prelude=None):
    """
    Run ``python -m landmark_ros.eval.exercises`` (or a prelude, then ``main``).

    Parameters
    ----------
    *args : str
        Command-line arguments.
    prelude : str, optional
        Python statements run before ``main`` in the child interpreter.

    Returns
    -------
    subprocess.CompletedProcess
        With text ``stdout`` and ``stderr``.

    """
    if prelude is None:
        command = [sys.executable, '-m', 'landmark_ros.eval.exercises', *args]
    else:
        code = (prelude + '\nimport sys\nfrom landmark_ros.eval.exercises import main\n'
                'sys.exit(main(sys.argv[1:]))\n')
        command = [sys.executable, '-c', code, *args]
    # cwd = repo root puts the source tree first on sys.path.
    return subprocess.run(command, cwd=REPO_ROOT, capture_output=True, text=True,
                          timeout=120)


@pytest.fixture(scope='module')
def results():
    return exercises.solve()


def test_case1_exact_pose(results):
    close(results['case1']['m1'], M1)
    close(results['case1']['P_m1'], P_M1_EXACT)


def test_case2_uncertain_pose(results):
    close(results['case2']['m1'], M1)
    close(results['case2']['P_m1'], P_M1)


@pytest.mark.parametrize('method', ['between', 'composition'])
def test_case3_relative_pose(results, method):
    p12, cov = results['case3'][method]
    close(p12, P12)
    close(cov, P12_COV)


def test_case3_methods_agree(results):
    assert results['case3']['max_abs_difference'] < 1e-12


def test_case4_predicted_observation(results):
    close(results['case4']['z'], Z)
    close(results['case4']['P_z'], P_Z)


def test_case4_textbook_figure_reproduced(results):
    case = results['case4']
    close(case['P_z_textbook'], P_Z_TEXTBOOK)
    # Same chain, Jacobian evaluated at q instead of the world difference: correct.
    close(case['P_z_at_q'], P_Z)
    # q and the world difference have the same length and differ by R2's heading.
    assert np.hypot(*case['q']) == pytest.approx(np.hypot(*case['d_world']), abs=1e-12)
    assert case['heading_offset'] == pytest.approx(-results['inputs']['p2'][2], abs=1e-12)


def test_case4_monte_carlo(results):
    case = results['case4']
    P_z = np.asarray(P_Z)
    textbook = np.asarray(P_Z_TEXTBOOK)
    norm = np.sqrt(np.outer(np.diag(P_z), np.diag(P_z)))

    # Near-linear regime (covariances scaled by 0.01): MC equals the first-order P_z
    # within sampling error (about 0.003 here, normalised), and the textbook's
    # figure is 0.08 to 0.11 away in every entry.
    small = case['mc_small']
    assert small['samples'] >= 100_000
    P_small = small['P_z'] / small['scale']
    assert np.max(np.abs(P_small - P_z) / norm) < 0.02
    assert np.min(np.abs(P_small - textbook) / norm) > 0.05

    # Full scale: linearisation error of up to ~14 % (bearing variance), but every
    # entry is nearer the correct P_z than the textbook's and the correlation sign
    # is the correct one.
    P_full = case['mc']['P_z']
    assert np.all(np.abs(P_full - P_z) < np.abs(P_full - textbook))
    assert np.max(np.abs(P_full - P_z) / norm) < 0.2
    assert P_full[0, 1] < 0.0 < textbook[0, 1]


def test_case5_second_landmark_and_fusion(results):
    case = results['case5']
    close(case['m2'], M2)
    close(case['P_m2'], P_M2)
    close(case['m_fused'], M_FUSED)
    close(case['P_fused'], P_FUSED)


def test_solve_is_reproducible():
    a = exercises.solve(mc_samples=1000, seed=3)['case4']['mc']['P_z']
    b = exercises.solve(mc_samples=1000, seed=3)['case4']['mc']['P_z']
    np.testing.assert_array_equal(a, b)


def test_report_formats_8_decimals(results):
    text = exercises.format_report(results)
    assert '[[ 0.94677477, -0.23978943],' in text
    assert '[ 2.44943102,  5.72815634]' in text


def test_cli_prints_key_numbers():
    proc = run_module()
    assert proc.returncode == 0, proc.stderr
    expected = [M1, P_M1_EXACT, P_M1, P12, P12_COV, Z, P_Z, P_Z_TEXTBOOK, M2, P_M2,
                M_FUSED, P_FUSED]
    for value in expected:
        for number in np.ravel(value):
            assert f'{number:.8f}' in proc.stdout, number
    for label in ('1.', '2.', '3.', '4.', '5.', "method='between'",
                  "method='composition'", 'textbook', 'Monte Carlo'):
        assert label in proc.stdout


def test_cli_plot_writes_png(tmp_path):
    pytest.importorskip('matplotlib')
    path = tmp_path / 'exercises.png'
    proc = run_module('--plot', str(path))
    assert proc.returncode == 0, proc.stderr
    assert path.is_file()
    data = path.read_bytes()
    assert len(data) > 1000
    assert data.startswith(b'\x89PNG\r\n\x1a\n')


def test_cli_plot_without_matplotlib(tmp_path):
    path = tmp_path / 'exercises.png'
    # A None entry in sys.modules makes every import of matplotlib fail.
    proc = run_module('--plot', str(path), prelude="import sys\nsys.modules['matplotlib'] = None")
    assert proc.returncode == exercises.EXIT_NO_MATPLOTLIB, proc.stderr
    assert 'matplotlib' in proc.stderr
    assert 'landmark_ros[plot]' in proc.stderr
    assert f'{M_FUSED[0]:.8f}' in proc.stdout
    assert not path.exists()
