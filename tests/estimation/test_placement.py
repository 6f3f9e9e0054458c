"""Single-input pole placement without scipy.signal: the numbers of scipy.signal.place_poles."""

import subprocess
import sys

import numpy as np
import pytest
from scipy.signal import place_poles as scipy_place_poles

from estimation.placement import place_poles


def _cases():
    rng = np.random.default_rng(7)
    for n in range(1, 8):
        for trial in range(6):
            A = rng.normal(size=(n, n))
            B = rng.normal(size=(n, 1))
            if trial % 2 and n > 1:  # complex pairs among the poles
                m = n // 2
                re, im = -rng.uniform(0.5, 3.0, m), rng.uniform(0.5, 20.0, m)
                poles = np.concatenate([re + 1j * im, re - 1j * im, -rng.uniform(0.5, 3.0, n - 2 * m)])
            else:
                poles = -rng.uniform(0.5, 3.0, n)
            yield A, B, poles


@pytest.mark.parametrize("case", list(_cases()), ids=lambda c: f"n{c[0].shape[0]}-{'c' if np.iscomplexobj(c[2]) else 'r'}")
def test_single_input_gain_equals_scipys(case):
    A, B, poles = case
    ours, theirs = place_poles(A, B, poles), scipy_place_poles(A, B, poles)
    assert np.array_equal(ours.gain_matrix, theirs.gain_matrix)
    assert np.array_equal(ours.computed_poles, theirs.computed_poles)


def test_the_lee_kim_shim_observers_are_placed_as_scipy_places_them():
    from estimation.lee_kim_shim import design, shifted_poles
    from estimation.lti import three_inertia

    p = three_inertia()
    des = design(p.A, p.B, p.banks)
    for ob in des.observers:
        A_o, C_o = ob.W_i @ p.A @ ob.V_i, ob.C @ ob.V_i
        L = np.real(scipy_place_poles(A_o.T, C_o.T, shifted_poles(A_o, real_part=-1.0)).gain_matrix.T)
        assert np.array_equal(ob.L, L)


def test_errors_are_scipys():
    A, B = np.eye(2), np.ones((2, 1))
    with pytest.raises(ValueError, match="repeated"):
        place_poles(A, B, [-1.0, -1.0])
    with pytest.raises(ValueError, match="conjugates"):
        place_poles(np.zeros((2, 2)), B, [-1.0 + 1j, -2.0])
    # an uncontrollable pair (A = I): both give the same wrong poles (numpy < 2.4: its
    # solve goes through the numerically singular matrix) or both raise the same error
    # (numpy 2.4 finds the matrix singular)

    def outcome(place):
        try:
            return "placed", place(A, B, [-1.0, -2.0]).computed_poles
        except ValueError as exc:
            return "raised", str(exc)

    ours, theirs = outcome(place_poles), outcome(scipy_place_poles)
    assert ours[0] == theirs[0]
    if ours[0] == "placed":
        assert np.array_equal(ours[1], theirs[1]) and not np.allclose(ours[1], [-2.0, -1.0])
    else:
        assert ours[1] == theirs[1] and "can't be placed" in ours[1]


def test_more_inputs_go_to_scipy():
    rng = np.random.default_rng(1)
    A, B = rng.normal(size=(4, 4)), rng.normal(size=(4, 2))
    poles = np.array([-1.0, -2.0, -3.0, -4.0])
    assert np.allclose(place_poles(A, B, poles).gain_matrix, scipy_place_poles(A, B, poles).gain_matrix)


def test_building_lee_kim_shim_does_not_import_scipy_signal():
    code = ("import sys\nfrom scenarios.loader import load\nfrom scenarios.build import build\n"
            "build(load('scenarios/lee_kim_shim.toml')[0])\nprint('scipy.signal' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
