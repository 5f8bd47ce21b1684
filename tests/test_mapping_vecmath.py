"""The vectorisable exponential of the GPPOL kernel blocks against numpy's."""

from __future__ import annotations

import numba as nb
import numpy as np

from mapping.vecmath import EXP_UNDERFLOW, exp_nonpositive


@nb.njit(cache=True)
def _exp_all(x: np.ndarray, out: np.ndarray) -> None:
    for i in range(x.shape[0]):
        out[i] = exp_nonpositive(x[i])


def _exp(x: np.ndarray) -> np.ndarray:
    out = np.empty_like(x)
    _exp_all(np.ascontiguousarray(x, dtype=np.float64), out)
    return out


def test_exp_nonpositive_matches_numpy_to_a_few_ulp() -> None:
    rng = np.random.default_rng(0)
    x = -np.concatenate(
        [np.linspace(0.0, 2.0, 200_001), np.geomspace(1e-300, 708.0, 200_001), rng.uniform(0, 708, 100_000)]
    )
    got, want = _exp(x), np.exp(x)
    ulp = np.abs(got - want) / np.spacing(want)
    assert ulp.max() <= 4, f"{ulp.max()} ulp at x = {x[np.argmax(ulp)]}"
    assert _exp(np.array([0.0, -0.0]))[0] == 1.0 and _exp(np.array([-0.0]))[0] == 1.0


def test_exp_nonpositive_underflows_to_zero_and_never_grows() -> None:
    below = np.array([EXP_UNDERFLOW - 1e-9, -709.0, -745.2, -1e4, -1e300])
    assert (_exp(below) == 0.0).all()
    x = -np.sort(np.random.default_rng(1).uniform(0, 720, 100_000))  # from 0 down
    y = _exp(np.ascontiguousarray(x))
    assert (np.diff(y) <= 0).all()
