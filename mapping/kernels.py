"""Covariance functions behind one interface (after scikit-learn's ``gaussian_process.kernels``).

A kernel is called as ``k(X, Y=None)`` on (..., n, 2) and (..., m, 2) inputs (leading batch dimensions are
broadcast, so a batch of local problems is one call) and returns (..., n, m); ``diag(X)`` returns (..., n).
Hyperparameters are positive and exposed as ONE log-space vector ``theta`` with log-space ``bounds``
(P, 2), so optimisers work on an unconstrained-looking box. ``k(X, eval_gradient=True)`` also returns
d K / d theta (..., n, n, P) (analytic, checked against finite differences in the tests).

``packed()`` gives the kernel id and parameters read by the compiled core (:mod:`mapping.core`).

Kernels: the neural-network kernel of the paper (eq. 7, non-stationary), the squared exponential (eq. 18)
and the Matern 3/2 and 5/2 kernels (section 3.1 suggests the Matern family as sharp alternatives).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from mapping.core import KERNEL_MATERN32, KERNEL_MATERN52, KERNEL_NN, KERNEL_SE

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Kernel:
    """Base class: ``values`` are the hyperparameters (natural units, all > 0) named by ``names``."""

    values: tuple[float, ...]
    bounds_values: tuple[tuple[float, float], ...] = field(default=())

    name: ClassVar[str] = "kernel"
    names: ClassVar[tuple[str, ...]] = ()
    default_bounds: ClassVar[tuple[tuple[float, float], ...]] = ()
    stationary: ClassVar[bool] = True  # a function of x - y only

    def __post_init__(self) -> None:
        vals = tuple(float(v) for v in self.values)
        if len(vals) != len(self.names):
            raise ValueError(f"{self.name} kernel takes {len(self.names)} hyperparameters, got {len(vals)}")
        if any(not np.isfinite(v) or v <= 0 for v in vals):
            raise ValueError(f"{self.name} kernel hyperparameters must be finite and > 0, got {vals}")
        object.__setattr__(self, "values", vals)
        b = self.bounds_values or self.default_bounds
        object.__setattr__(self, "bounds_values", tuple((float(lo), float(hi)) for lo, hi in b))

    # -- hyperparameters -------------------------------------------------------------------------------
    @property
    def theta(self) -> FloatArray:
        """(P,) log hyperparameters."""
        return np.log(np.asarray(self.values))

    @property
    def bounds(self) -> FloatArray:
        """(P, 2) log-space bounds of ``theta``."""
        return np.log(np.asarray(self.bounds_values, dtype=np.float64))

    def with_theta(self, theta: FloatArray) -> Kernel:
        """A copy with log hyperparameters ``theta``."""
        return type(self)(tuple(np.exp(np.asarray(theta, dtype=np.float64))), self.bounds_values)

    def as_dict(self) -> dict[str, float]:
        return dict(zip(self.names, self.values, strict=True))

    @property
    def signal_var(self) -> float:
        return self.values[0] ** 2

    # -- evaluation ------------------------------------------------------------------------------------
    def __call__(
        self, X: FloatArray, Y: FloatArray | None = None, eval_gradient: bool = False
    ) -> FloatArray | tuple[FloatArray, FloatArray]:
        X = np.asarray(X, dtype=np.float64)
        if eval_gradient and Y is not None:
            raise ValueError("gradients are only available for k(X, X)")
        Y = X if Y is None else np.asarray(Y, dtype=np.float64)
        return self._eval(X, Y, eval_gradient)

    def diag(self, X: FloatArray) -> FloatArray:
        raise NotImplementedError

    def _eval(self, X: FloatArray, Y: FloatArray, eval_gradient: bool):
        raise NotImplementedError

    def packed(self) -> tuple[int, FloatArray]:
        """(kernel id, parameters) for :func:`mapping.core.predict_batch`."""
        raise NotImplementedError

    def of_difference(
        self, D: FloatArray, eval_gradient: bool = False
    ) -> FloatArray | tuple[FloatArray, FloatArray]:
        """A stationary kernel as a function of the difference ``x - y``: (...,) values for (..., 2)
        differences, and with ``eval_gradient`` the (..., P) gradient w.r.t. ``theta``."""
        if not self.stationary:
            raise ValueError(f"the {self.name} kernel is not stationary")
        D = np.asarray(D, dtype=np.float64)
        out = self._eval(D[..., None, :], np.zeros((1, D.shape[-1])), eval_gradient)
        if not eval_gradient:
            return out[..., 0, 0]
        return out[0][..., 0, 0], out[1][..., 0, 0, :]


def _sqdist(X: FloatArray, Y: FloatArray) -> FloatArray:
    d = X[..., :, None, :] - Y[..., None, :, :]
    return np.einsum("...d,...d->...", d, d)


@dataclass(frozen=True)
class NeuralNetworkKernel(Kernel):
    """Eq. (7): ``sf^2 asin(2 x~' S y~ / sqrt((1 + 2 x~' S x~)(1 + 2 y~' S y~)))`` with x~ = (1, x),
    S = diag(sigma_0^2, sigma^2, sigma^2). Hyperparameters (sigma_f, sigma_0, sigma)."""

    values: tuple[float, ...] = (1.0, 1.0, 3.0)
    name = "nn"
    stationary = False
    names = ("sigma_f", "sigma_0", "sigma")
    default_bounds = ((1e-2, 1e2), (1e-2, 1e4), (1e-2, 1e5))

    def _parts(self, X, Y):
        sf, s0, su = self.values
        c0, c1 = 2 * s0**2, 2 * su**2
        a = c0 + c1 * np.einsum("...id,...jd->...ij", X, Y)
        bx = 1 + c0 + c1 * np.einsum("...id,...id->...i", X, X)
        by = 1 + c0 + c1 * np.einsum("...id,...id->...i", Y, Y)
        root = np.sqrt(bx[..., :, None] * by[..., None, :])
        z = np.clip(a / root, -1.0, 1.0)
        return sf, c0, c1, a, bx, by, root, z

    def _eval(self, X, Y, eval_gradient):
        sf, c0, c1, _a, bx, by, root, z = self._parts(X, Y)
        K = sf**2 * np.arcsin(z)
        if not eval_gradient:
            return K
        dk_dz = sf**2 / np.sqrt(np.maximum(1 - z * z, 1e-300))
        xx = np.einsum("...id,...id->...i", X, X)
        xy = np.einsum("...id,...jd->...ij", X, Y)
        # z = a / sqrt(bx by); dz/dc = (da/dc) / root - z/2 (dbx/dc / bx + dby/dc / by)
        dz_dc0 = 1 / root - 0.5 * z * (1 / bx[..., :, None] + 1 / by[..., None, :])
        dz_dc1 = xy / root - 0.5 * z * (
            xx[..., :, None] / bx[..., :, None] + xx[..., None, :] / by[..., None, :]
        )
        grad = np.stack([2 * K, dk_dz * dz_dc0 * 2 * c0, dk_dz * dz_dc1 * 2 * c1], axis=-1)
        return K, grad

    def diag(self, X):
        X = np.asarray(X, dtype=np.float64)
        sf, s0, su = self.values
        b = 2 * s0**2 + 2 * su**2 * np.einsum("...id,...id->...i", X, X)
        return sf**2 * np.arcsin(b / (1 + b))

    def packed(self):
        sf, s0, su = self.values
        return KERNEL_NN, np.array([sf**2, 2 * s0**2, 2 * su**2])


@dataclass(frozen=True)
class SquaredExponentialKernel(Kernel):
    """Eq. (18) with L = l^2 I: ``sf^2 exp(-|x - y|^2 / (2 l^2))``; hyperparameters sigma_f, length_scale."""

    values: tuple[float, ...] = (1.0, 0.5)
    name = "se"
    names = ("sigma_f", "length_scale")
    default_bounds = ((1e-2, 1e2), (1e-3, 1e2))

    def _eval(self, X, Y, eval_gradient):
        sf, ell = self.values
        r2 = _sqdist(X, Y)
        K = sf**2 * np.exp(-0.5 * r2 / ell**2)
        if not eval_gradient:
            return K
        return K, np.stack([2 * K, K * r2 / ell**2], axis=-1)

    def diag(self, X):
        X = np.asarray(X, dtype=np.float64)
        return np.full(X.shape[:-1], self.values[0] ** 2)

    def packed(self):
        sf, ell = self.values
        return KERNEL_SE, np.array([sf**2, 1 / ell**2])


@dataclass(frozen=True)
class Matern32Kernel(Kernel):
    """Matern nu = 3/2: ``sf^2 (1 + u) exp(-u)``, u = sqrt(3) r / l; hyperparameters sigma_f, length_scale."""

    values: tuple[float, ...] = (1.0, 0.5)
    name = "matern32"
    names = ("sigma_f", "length_scale")
    default_bounds = ((1e-2, 1e2), (1e-3, 1e2))

    def _eval(self, X, Y, eval_gradient):
        sf, ell = self.values
        u = np.sqrt(3.0) * np.sqrt(np.maximum(_sqdist(X, Y), 0.0)) / ell
        e = np.exp(-u)
        K = sf**2 * (1 + u) * e
        if not eval_gradient:
            return K
        return K, np.stack([2 * K, sf**2 * u * u * e], axis=-1)

    def diag(self, X):
        X = np.asarray(X, dtype=np.float64)
        return np.full(X.shape[:-1], self.values[0] ** 2)

    def packed(self):
        sf, ell = self.values
        return KERNEL_MATERN32, np.array([sf**2, np.sqrt(3.0) / ell])


@dataclass(frozen=True)
class Matern52Kernel(Kernel):
    """Matern nu = 5/2: ``sf^2 (1 + u + u^2/3) exp(-u)``, u = sqrt(5) r / l."""

    values: tuple[float, ...] = (1.0, 0.5)
    name = "matern52"
    names = ("sigma_f", "length_scale")
    default_bounds = ((1e-2, 1e2), (1e-3, 1e2))

    def _eval(self, X, Y, eval_gradient):
        sf, ell = self.values
        u = np.sqrt(5.0) * np.sqrt(np.maximum(_sqdist(X, Y), 0.0)) / ell
        e = np.exp(-u)
        K = sf**2 * (1 + u + u * u / 3) * e
        if not eval_gradient:
            return K
        return K, np.stack([2 * K, sf**2 * e * u * u * (1 + u) / 3], axis=-1)

    def diag(self, X):
        X = np.asarray(X, dtype=np.float64)
        return np.full(X.shape[:-1], self.values[0] ** 2)

    def packed(self):
        sf, ell = self.values
        return KERNEL_MATERN52, np.array([sf**2, np.sqrt(5.0) / ell])


KERNELS: dict[str, type[Kernel]] = {
    "nn": NeuralNetworkKernel,
    "se": SquaredExponentialKernel,
    "matern32": Matern32Kernel,
    "matern52": Matern52Kernel,
}


def make_kernel(
    name: str,
    values: dict[str, float] | tuple[float, ...] | None = None,
    bounds: dict[str, tuple[float, float]] | None = None,
) -> Kernel:
    """The kernel called ``name`` (a key of :data:`KERNELS`) with hyperparameters ``values`` (by name or in
    order; defaults otherwise) and per-name ``bounds`` overriding the defaults."""
    if name not in KERNELS:
        raise ValueError(f"unknown kernel '{name}' (known: {', '.join(KERNELS)})")
    cls = KERNELS[name]
    proto = cls()
    if values is None:
        vals = proto.values
    elif isinstance(values, dict):
        unknown = set(values) - set(cls.names)
        if unknown:
            raise ValueError(f"{name} kernel has no hyperparameter(s) {sorted(unknown)} (has {cls.names})")
        vals = tuple(float(values.get(k, v)) for k, v in zip(cls.names, proto.values, strict=True))
    else:
        vals = tuple(values)
    b = dict(zip(cls.names, cls.default_bounds, strict=True))
    for k, v in (bounds or {}).items():
        if k not in b:
            raise ValueError(f"{name} kernel has no hyperparameter '{k}' (has {cls.names})")
        b[k] = (float(v[0]), float(v[1]))
    return cls(vals, tuple(b[k] for k in cls.names))
