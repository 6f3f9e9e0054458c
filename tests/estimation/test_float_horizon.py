"""The float64 horizon of an unstable linear plant (estimation.lti.float_horizon) and the
run it refuses (``run.rounds`` past it is a one-line error, exit 2)."""

import math

import numpy as np

from estimation.lti import FLOAT_SIGNAL_LIMIT, float_horizon
from tests.conftest import SCENARIOS, rse


def test_scalar_growth_gives_the_analytic_horizon():
    # |1.2^k| * 1 <= 1e150  <=>  k <= 150 ln 10 / ln 1.2 = 1894.4
    assert float_horizon(np.array([[1.2]]), x_norm=1.0, max_rounds=10_000) == math.floor(150 * math.log(10) / math.log(1.2))
    assert float_horizon(np.array([[1.2]]), x_norm=1e10, max_rounds=10_000) == math.floor(140 * math.log(10) / math.log(1.2))
    # capped: a shorter horizon is safe
    assert float_horizon(np.array([[1.2]]), x_norm=1.0, max_rounds=300) == 300


def test_stable_and_marginal_plants_never_overflow():
    assert float_horizon(np.diag([0.5, 0.9]), x_norm=1.0, max_rounds=10**6) == 10**6
    # a Jordan block on the unit circle grows like k, far below the limit
    assert float_horizon(np.array([[1.0, 1.0], [0.0, 1.0]]), x_norm=1.0, max_rounds=20_000) == 20_000
    # already past the limit at round 0
    assert float_horizon(np.eye(2), x_norm=10 * FLOAT_SIGNAL_LIMIT, max_rounds=10) == 0


def test_a_run_past_the_horizon_of_an_unstable_plant_is_refused(tmp_path):
    # mitra_cells: rho = 1.2, |x0| = 0.41: the state passes 1e150 after 1895 rounds
    p = rse("simulate", str(SCENARIOS / "mitra_cells.toml"), "--set", "run.rounds=30000", "--set", "expect=[]",
            "--no-progress", "--no-rerun", "--out", str(tmp_path / "run"))
    assert p.returncode == 2, p.stdout + p.stderr
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "run.rounds" in lines[0] and "safe horizon 1895" in lines[0], p.stderr
    assert "RuntimeWarning" not in p.stdout + p.stderr


def test_a_block_diagonal_plant_gives_the_dense_horizon_block_by_block():
    # 40 decoupled blocks of sizes 1..3, states shuffled: split into blocks grouped by
    # size, the horizon is the dense computation's
    import scipy.linalg as sl

    from estimation.lti import decoupled_groups

    def dense(A, x_norm, max_rounds, norm):
        budget, P, log_scale = np.log(FLOAT_SIGNAL_LIMIT / x_norm), np.eye(A.shape[0]), 0.0
        for k in range(1, max_rounds + 1):
            P = A @ P
            nP = np.linalg.norm(P, norm)
            log_scale += np.log(nP)
            P /= nP
            if log_scale > budget:
                return k - 1
        return max_rounds

    rng = np.random.default_rng(0)
    for _ in range(5):
        sizes = rng.integers(1, 4, size=40)
        A = sl.block_diag(*[rng.normal(size=(s, s)) * 0.7 for s in sizes])
        perm = rng.permutation(A.shape[0])
        A = A[np.ix_(perm, perm)]
        groups = decoupled_groups(A)
        assert sorted(g.shape[1] for g in groups for _ in range(g.shape[0])) == sorted(sizes.tolist())
        for norm in ("fro", 2):  # Frobenius: the blocks' squares add up; 2-norm: the largest block's
            expected = dense(A, 1.0, 20_000, norm)
            assert expected < 20_000
            assert float_horizon(A, x_norm=1.0, max_rounds=20_000, norm=norm) == expected


def test_dense_needs_no_scipy_for_a_dense_matrix():
    """The monitor's image has no scipy: its dashboard calls ``lti.dense`` on the plant's
    (dense, small) ``A``, which must not import scipy."""
    import subprocess
    import sys

    code = ("import sys; sys.modules['scipy'] = None\n"
            "import numpy as np\n"
            "from estimation.lti import dense\n"
            "print(dense(np.diag([1, 2])).tolist())\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[[1.0, 0.0], [0.0, 2.0]]"
