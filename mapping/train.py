"""Hyperparameter training (paper section 3.2) and the learnt-parameter file.

The log marginal likelihood (eq. 9) is maximised over the kernel's log hyperparameters, first globally by
dual annealing (the paper's simulated annealing) then locally by L-BFGS-B with the analytic gradient
``d lml / d theta = 1/2 tr((a a^T - K^-1) dK/d theta)``, ``a = K^-1 y``.

The data are a subsample drawn from runs of consecutive scans spread over the recording
(:func:`training_scans`), shaped like the model that is used at prediction: ``n_problems`` query points
sampled along the beams of those scans, each with its ``k_occ`` occupied and
``k_free`` free neighbours (the free points projected for that query, eqs. 13-14), in coordinates centred on
the query. The objective is the sum of eq. (9) over these local problems, evaluated as one batched
computation. Centring matters for the non-stationary NN kernel (eq. 7), whose behaviour depends on the
distance from the coordinate origin: the map uses it in query-centred coordinates, and so does training.

Then alpha, beta and the mean's cap of the PLS link are fitted on the leave-one-out predictions of these
problems and more drawn the same way (eqs. 10-12, :mod:`mapping.pls`). Everything is stored in
:class:`GPParams` (JSON), reusable by later runs.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import optimize

from mapping.beams import Beams
from mapping.gppol import GaussianInputs
from mapping.kernels import Kernel, make_kernel
from mapping.neighbours import BeamIndex
from mapping.noisy_kernels import InputExpectation
from mapping.pls import fit_pls, loo_predictions, pls_probability

FloatArray = NDArray[np.float64]
PARAMS_FORMAT = "gpom-gp-params-1"


class ParamsFileError(ValueError):
    """A learnt-parameter file cannot be read (the pipeline turns it into a GpomError naming the file)."""


@dataclass(frozen=True)
class GPParams:
    """Everything prediction needs besides data: kernel (with hyperparameters), noise variance, PLS link."""

    kernel: Kernel
    noise_var: float
    alpha: float
    beta: float
    info: dict[str, Any] = field(default_factory=dict)
    mean_cap: float | None = None

    @property
    def prior_variance(self) -> float:
        """The latent prior variance ``k(x*, x*)``: the variance of a query no data reach. :mod:`mapping.core`
        solves every query in coordinates centred on it, so this is the kernel's diagonal at the origin for
        every query, also for the non-stationary NN kernel (eq. 7)."""
        return float(self.kernel.diag(np.zeros((1, 2)))[0])

    @property
    def unseen_probability(self) -> float:
        """p(occ) where no data reach: the link at mu = 0 and the prior variance k(x, x) plus the noise, as
        mapping.core answers a query without neighbours (the level unobserved space reads as)."""
        return float(pls_probability(0.0, self.prior_variance + self.noise_var, self.alpha, self.beta))

    def to_dict(self) -> dict[str, Any]:
        """The parameter file's content; ``unseen_probability`` is derived (not read back)."""
        return {
            "format": PARAMS_FORMAT,
            "kernel": self.kernel.name,
            "hyperparameters": self.kernel.as_dict(),
            "bounds": {k: list(b) for k, b in zip(self.kernel.names, self.kernel.bounds_values, strict=True)},
            "noise_var": self.noise_var,
            "pls": {"alpha": self.alpha, "beta": self.beta, "mean_cap": self.mean_cap},
            "unseen_probability": self.unseen_probability,
            "info": self.info,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> GPParams:
        try:
            if d.get("format") != PARAMS_FORMAT:
                raise ParamsFileError(f"not a GP parameter file (format {d.get('format')!r})")
            kernel = make_kernel(d["kernel"], dict(d["hyperparameters"]), d.get("bounds"))
            return cls(
                kernel=kernel,
                noise_var=float(d["noise_var"]),
                alpha=float(d["pls"]["alpha"]),
                beta=float(d["pls"]["beta"]),
                info=dict(d.get("info", {})),
                mean_cap=_mean_cap(d["pls"].get("mean_cap")),
            )
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, ParamsFileError):
                raise
            raise ParamsFileError(f"bad GP parameter file: {exc}") from None

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=2, default=float) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> GPParams:
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ParamsFileError(f"cannot read GP parameters: {exc}") from None
        return cls.from_dict(data)


def _mean_cap(value: Any) -> float | None:
    """A parameter file's ``pls.mean_cap``: absent or null (files written before the cap) is uncapped."""
    if value is None:
        return None
    cap = float(value)
    if not (math.isfinite(cap) and cap > 0):
        raise ValueError(f"pls.mean_cap must be a positive number or null, got {value!r}")
    return cap


def sample_training_queries(beams: Beams, n: int, seed: int = 0, beyond: float = 0.15) -> FloatArray:
    """(n, 2) query points along random beams: uniform over ``[0, 1 + beyond]`` of each beam's length (so
    some lie just behind its endpoint) plus 5 cm of Gaussian jitter."""
    rng = np.random.default_rng(seed)
    if len(beams) == 0:
        return np.zeros((0, 2))
    b = rng.integers(0, len(beams), size=n)
    t = rng.uniform(0.0, 1.0 + beyond, size=n)
    t = np.where(beams.is_hit[b], t, np.minimum(t, 1.0))
    p = beams.origins_xy_m[b] + t[:, None] * (beams.ends_xy_m[b] - beams.origins_xy_m[b])
    return p + rng.normal(scale=0.05, size=p.shape)


def kernel_matrix(
    kernel: Kernel,
    X: FloatArray,
    cov: FloatArray | None = None,
    expectation: InputExpectation | None = None,
    eval_gradient: bool = False,
) -> FloatArray | tuple[FloatArray, FloatArray]:
    """K (..., n, n) of the training inputs: points X (GPFOL), or Gaussians N(X, cov (..., n, 2, 2))
    integrated by ``expectation`` (GPPOL, :mod:`mapping.noisy_kernels`)."""
    if cov is None:
        return kernel(X, eval_gradient=eval_gradient)
    return (expectation or InputExpectation()).matrix(kernel, X, cov, eval_gradient)


def log_marginal_likelihood(
    kernel: Kernel,
    X: FloatArray,
    y: FloatArray,
    noise_var: float,
    eval_gradient: bool = False,
    noise_gradient: bool = False,
    cov: FloatArray | None = None,
    expectation: InputExpectation | None = None,
) -> float | tuple[float, FloatArray]:
    """Sum over the local problems X (Q, n, 2), y (Q, n) of eq. (9), and its gradient w.r.t. ``kernel.theta``
    (with ``noise_gradient``, also w.r.t. ``log noise_var``, appended). GPPOL: the inputs are Gaussians with
    covariances ``cov`` (Q, n, 2, 2), the kernel integrated over them by ``expectation``.

    Returns -inf (and a zero gradient) when a covariance matrix is not positive definite."""
    n = X.shape[-2]
    if eval_gradient:
        K, dK = kernel_matrix(kernel, X, cov, expectation, eval_gradient=True)
    else:
        K = kernel_matrix(kernel, X, cov, expectation)
    K = K + noise_var * np.eye(n)
    try:
        L = np.linalg.cholesky(K)
    except np.linalg.LinAlgError:
        size = kernel.theta.shape[0] + int(noise_gradient)
        return (-np.inf, np.zeros(size)) if eval_gradient else -np.inf
    Kinv = np.linalg.inv(K)
    a = np.einsum("...ij,...j->...i", Kinv, y)
    logdet = 2.0 * np.log(np.einsum("...ii->...i", L)).sum(axis=-1)
    lml = -0.5 * np.einsum("...i,...i->...", y, a) - 0.5 * logdet - 0.5 * n * np.log(2 * np.pi)
    total = float(lml.sum())
    if not eval_gradient:
        return total
    inner = a[..., :, None] * a[..., None, :] - Kinv
    grad = 0.5 * np.einsum("...ij,...ijp->...p", inner, dK).reshape(-1, dK.shape[-1]).sum(axis=0)
    if noise_gradient:  # dK / d log(noise_var) = noise_var I
        grad = np.r_[grad, 0.5 * noise_var * np.einsum("...ii->...", inner).sum()]
    return total, grad


def train_hyperparameters(
    kernel: Kernel,
    X: FloatArray,
    y: FloatArray,
    noise_var: float,
    maxfun: int = 300,
    maxiter: int = 100,
    seed: int = 0,
    learn_noise: bool = False,
    noise_bounds: tuple[float, float] = (1e-4, 1.0),
    cov: FloatArray | None = None,
    expectation: InputExpectation | None = None,
) -> tuple[Kernel, float, dict[str, Any]]:
    """Maximise eq. (9) over the kernel's log hyperparameters (and ``log sigma_n^2`` if ``learn_noise``)
    within their bounds: dual annealing with ``maxfun`` evaluations (0 skips it), then L-BFGS-B with the
    analytic gradient. GPPOL: ``cov`` (Q, n, 2, 2) and ``expectation`` as in :func:`log_marginal_likelihood`.
    Returns the trained kernel, the noise variance and a summary."""
    npts = X.shape[0] * X.shape[1]
    p = kernel.theta.shape[0]
    bounds = kernel.bounds
    x0 = kernel.theta
    if learn_noise:
        bounds = np.vstack([bounds, np.log(np.asarray(noise_bounds, dtype=np.float64))])
        x0 = np.r_[x0, np.log(noise_var)]
    calls = {"anneal": 0, "lbfgs": 0}

    def split(x: FloatArray) -> tuple[Kernel, float]:
        return kernel.with_theta(x[:p]), (float(np.exp(x[p])) if learn_noise else noise_var)

    def neg(x: FloatArray) -> float:
        calls["anneal"] += 1
        k, nv = split(x)
        v = log_marginal_likelihood(k, X, y, nv, cov=cov, expectation=expectation)
        return 1e10 if not np.isfinite(v) else -v / npts

    def neg_grad(x: FloatArray) -> tuple[float, FloatArray]:
        calls["lbfgs"] += 1
        k, nv = split(x)
        v, g = log_marginal_likelihood(
            k, X, y, nv, eval_gradient=True, noise_gradient=learn_noise, cov=cov, expectation=expectation
        )
        if not np.isfinite(v):
            return 1e10, np.zeros_like(x)
        return -v / npts, -g / npts

    t0 = time.perf_counter()
    x0 = np.clip(x0, bounds[:, 0], bounds[:, 1])
    start = x0
    if maxfun > 0:
        res = optimize.dual_annealing(
            neg, bounds=bounds, maxfun=maxfun, seed=seed, no_local_search=True, x0=x0
        )
        start = res.x if res.fun <= neg(x0) else x0
    res = optimize.minimize(
        neg_grad, x0=start, jac=True, method="L-BFGS-B", bounds=bounds, options={"maxiter": maxiter}
    )
    best = res.x if np.isfinite(res.fun) else start
    trained, nv = split(best)
    info = {
        "lml_per_point": float(-res.fun),
        "anneal_evaluations": calls["anneal"],
        "lbfgs_evaluations": calls["lbfgs"],
        "train_seconds": time.perf_counter() - t0,
        "points": int(npts),
        "problems": int(X.shape[0]),
    }
    return trained, nv, info


def training_scans(scan_ids: NDArray, n_scans: int, windows: int = 1) -> NDArray[np.int64]:
    """The ``n_scans`` of the distinct, sorted ``scan_ids`` that training reads: ``windows`` runs of
    consecutive scans (as equal as can be) whose starts are spread evenly over the recording (1: the first
    ``n_scans``). Consecutive scans keep each local problem a neighbourhood of one scan and its neighbours
    in time; several runs let the hyperparameters see more of the scene than its first metres."""
    ids = np.unique(np.asarray(scan_ids, dtype=np.int64))
    if ids.size <= n_scans:
        return ids
    windows = max(1, min(int(windows), int(n_scans)))
    sizes = np.full(windows, n_scans // windows)
    sizes[: n_scans % windows] += 1
    starts = np.linspace(0, ids.size - sizes[-1], windows).round().astype(np.int64)
    picked = np.concatenate([np.arange(a, a + m) for a, m in zip(starts, sizes, strict=True)])
    return ids[np.unique(np.clip(picked, 0, ids.size - 1))]


def _local_problems(
    index: BeamIndex, queries: FloatArray, k_occ: int, k_free: int, inputs: tuple[Any, Any] | None
) -> tuple[FloatArray, FloatArray | None, FloatArray]:
    """The local problems of ``queries``: inputs X (Q, n, 2), their covariances (Q, n, 2, 2) when ``inputs``
    (the training beams' endpoint and free-segment Gaussians) are given (GPPOL, else None) and labels y."""
    if inputs is None:
        X, y, _ = index.local_problems(queries, k_occ, k_free)
        return X, None, y
    X, cov, y, _ = index.local_gaussians(queries, k_occ, k_free, *inputs)
    return X, cov, y


#: Offset of the seed of the link's extra problems from the training seed (a stream of its own).
_LINK_SEED = 1_000_003


def train_gp(
    beams: Beams,
    kernel_name: str = "nn",
    kernel_values: dict[str, float] | None = None,
    kernel_bounds: dict[str, tuple[float, float]] | None = None,
    noise_var: float = 0.1,
    k_occ: int = 15,
    k_free: int = 15,
    n_scans: int = 50,
    n_problems: int = 64,
    maxfun: int = 300,
    maxiter: int = 100,
    seed: int = 0,
    index_cell_m: float | None = None,
    learn_noise: bool = False,
    inputs: GaussianInputs | None = None,
    windows: int = 1,
    link_problems: int | None = None,
) -> GPParams:
    """Learn kernel hyperparameters and the PLS link from ``n_scans`` distinct scans of ``beams`` in
    ``windows`` runs of consecutive scans (:func:`training_scans`; 1: the first ``n_scans``). With
    ``inputs`` (the beams' input Gaussians) the GPPOL model is trained: eq. (9) and the leave-one-out PLS
    fit (eqs. 10-12) with the kernel integrated over the inputs.

    The link is fitted on the leave-one-out predictions of ``link_problems`` local problems (None: the
    ``n_problems`` of training): the training problems plus fresh ones from the same scans. Its three
    constants cost little to fit on many more points than the hyperparameters, and the mean's cap
    (:func:`mapping.pls.fit_pls`) turns on likelihood differences a small sample does not resolve."""
    scans = training_scans(beams.scan_index, n_scans, windows)
    keep = np.isin(beams.scan_index, scans)
    train_beams = beams.subset(keep)
    index = BeamIndex.build(train_beams, index_cell_m, index_cell_m)
    train_inputs = None if inputs is None else (inputs.moments.subset(keep), inputs.free().subset(keep))
    expectation = None if inputs is None else inputs.expectation
    X, cov, y = _local_problems(
        index, sample_training_queries(train_beams, n_problems, seed), k_occ, k_free, train_inputs
    )
    if X.shape[0] == 0:
        raise ValueError(f"no training neighbourhood with {k_occ} + {k_free} neighbours in its scans")
    kernel = make_kernel(kernel_name, kernel_values, kernel_bounds)
    if expectation is not None:
        expectation.check(kernel)
    trained, nv, info = train_hyperparameters(
        kernel,
        X,
        y,
        noise_var,
        maxfun,
        maxiter,
        seed,
        learn_noise=learn_noise,
        cov=cov,
        expectation=expectation,
    )
    extra = 0 if link_problems is None else link_problems - n_problems
    if extra > 0:
        more = sample_training_queries(train_beams, extra, seed + _LINK_SEED)
        X2, cov2, y2 = _local_problems(index, more, k_occ, k_free, train_inputs)
        X, y = np.concatenate([X, X2]), np.concatenate([y, y2])
        cov = None if cov is None else np.concatenate([cov, cov2])
    mu, var = loo_predictions(trained, X, y, nv, cov, expectation)
    alpha, beta, mean_cap = fit_pls(mu, var, y)
    info["link_problems"] = int(X.shape[0])
    info.update(
        {"scans": [int(scans[0]), int(scans[-1])], "n_scans": len(scans), "windows": windows, "seed": seed}
    )
    if expectation is not None:
        info["inputs"] = {"method": expectation.method, "level": expectation.level}
    return GPParams(trained, nv, alpha, beta, info, mean_cap)
