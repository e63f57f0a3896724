"""IV4 baseline: Ljung's four-stage instrumental-variable method and its two-mass conversion.

Model structure (ARX polynomials in the delay operator ``q^-1``)::

    A(q) y(t) = B(q) u(t) + v(t)
    A = [1, a_1, ..., a_na]                      (length na + 1)
    B = [0] * nk + [b_0, ..., b_(nb-1)]          (length nk + nb)

so that ``scipy.signal.lfilter(B, A, u)`` simulates the noise-free output. ``v`` may be
coloured: plain least squares (:func:`arx`) is then biased, the instrumental-variable
estimate (:func:`iv4`) is not.

IV4 (Ljung, *System Identification*, 2nd ed., sec. 15.3; MATLAB ``iv4``):

1. least squares (ARX) estimate ``A1, B1``;
2. IV with instruments from the noise-free simulation ``x = B1/A1 u`` of that model;
3. AR model ``L(q) w = e`` of order ``na + nb`` for the residuals ``w = A2 y - B2 u``;
4. IV on the data, regressors and instruments all prefiltered by ``L``, the instruments
   simulated from the stage-2 model.

Stages 2-4 are then repeated with the latest model ("iterated IV4", as the paper's
references do) until the relative parameter change is below ``tol`` or ``max_iter``.

The two-mass application (:func:`identify_iv4`) identifies the resonance model
``A(q) w_M = B(q) x`` from the integrated interval-mean motor torque ``x`` (the rigid-body
integrator is known and moved to the input) to the measured motor speed ``w_M``, and
:func:`two_mass_from_discrete` converts it to ``J_sigma``, ``V_J``, ``f_e`` (exactly for
zero-order-hold data). See ``docs/iv4.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import expm, solve_toeplitz
from scipy.signal import lfilter

from sim import two_mass_derived
from training._checks import as_signal

__all__ = [
    "ARXResult",
    "IV4Result",
    "IV4TwoMass",
    "TwoMassEstimate",
    "arx",
    "iv4",
    "two_mass_from_discrete",
    "mean_torque",
    "identify_iv4",
]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ARXResult:
    """A discrete polynomial model ``A(q) y = B(q) u + v``.

    Attributes:
        A: ``na + 1`` coefficients ``[1, a_1, ..., a_na]`` of ``q^0 .. q^-na``.
        B: ``nk + nb`` coefficients ``[0]*nk + [b_0 .. b_(nb-1)]`` of ``q^0 .. q^-(nk+nb-1)``.
        nk: input delay in samples.
        noise_variance: variance of the equation error ``A y - B u - E c`` (ARX) or of the
            whitened error ``L (A y - B u - E c)`` (IV4), in squared units of ``y``.
        exog_coef: coefficients ``c`` of the extra regressor columns ``E`` (``exog``), shape ``p``.
    """

    A: FloatArray
    B: FloatArray
    nk: int
    noise_variance: float
    exog_coef: FloatArray = field(default_factory=lambda: np.zeros(0))

    @property
    def na(self) -> int:
        return len(self.A) - 1

    @property
    def nb(self) -> int:
        return len(self.B) - self.nk

    @property
    def theta(self) -> FloatArray:
        """Parameter vector ``[a_1 .. a_na, b_0 .. b_(nb-1)]`` (length ``na + nb``)."""
        return np.concatenate([self.A[1:], self.B[self.nk :]])

    def simulate(self, u: ArrayLike, exog: ArrayLike | None = None) -> FloatArray:
        """Noise-free output ``(B u + E c)/A`` (zero initial state), shape of ``u``."""
        rhs = lfilter(self.B, [1.0], np.asarray(u, dtype=np.float64))
        if exog is not None and self.exog_coef.size:
            rhs = rhs + np.asarray(exog, dtype=np.float64) @ self.exog_coef
        return lfilter([1.0], self.A, rhs)


@dataclass(frozen=True)
class IV4Result(ARXResult):
    """IV4 estimate; adds the iteration count, convergence flag and the noise prefilter.

    Attributes:
        iterations: how many passes of stages 2-4 ran (1 = plain, non-iterated IV4).
        converged: relative parameter change of the last pass below ``tol``.
        L: ``ar_order + 1`` coefficients ``[1, l_1, ...]`` of the whitening prefilter.
    """

    iterations: int = 0
    converged: bool = False
    L: FloatArray = field(default_factory=lambda: np.ones(1))


# ----------------------------------------------------------------------------- checks


def _as_order(x: Any, name: str, minimum: int) -> int:
    if isinstance(x, bool) or not isinstance(x, (int, np.integer)):
        raise TypeError(f"{name}: expected an int, received {type(x).__name__}")
    if x < minimum:
        raise ValueError(f"{name}: expected an int >= {minimum}, received {x}")
    return int(x)


def _check_data(u: ArrayLike, y: ArrayLike, na: Any, nb: Any, nk: Any) -> tuple[FloatArray, FloatArray, int, int, int]:
    u_arr, y_arr = as_signal("u", u), as_signal("y", y)
    if u_arr.shape != y_arr.shape:
        raise ValueError(f"u and y: expected the same length, received {u_arr.size} and {y_arr.size}")
    na_i, nb_i, nk_i = _as_order(na, "na", 0), _as_order(nb, "nb", 1), _as_order(nk, "nk", 0)
    n_par = na_i + nb_i
    n_min = 2 * (max(na_i, nk_i + nb_i - 1) + n_par) + 10
    if u_arr.size < n_min:
        raise ValueError(
            f"u, y: expected at least {n_min} samples for na={na_i}, nb={nb_i}, nk={nk_i}, received {u_arr.size}"
        )
    return u_arr, y_arr, na_i, nb_i, nk_i


def _check_exog(exog: ArrayLike | None, n: int) -> FloatArray:
    if exog is None:
        return np.zeros((n, 0))
    E = np.asarray(exog, dtype=np.float64)
    if E.ndim == 1:
        E = E[:, None]
    if E.ndim != 2 or E.shape[0] != n:
        raise ValueError(f"exog: expected shape ({n}, p), received {E.shape}")
    if not np.all(np.isfinite(E)):
        raise ValueError("exog: expected finite values, received NaN/inf")
    return E


# ----------------------------------------------------------------------------- core


def _regressors(y: FloatArray, u: FloatArray, na: int, nb: int, nk: int, start: int) -> FloatArray:
    """Regression matrix, rows ``t = start .. N-1``: ``[-y(t-1)..-y(t-na), u(t-nk)..u(t-nk-nb+1)]``.

    Shape ``(N - start) x (na + nb)``; ``start >= max(na, nk + nb - 1)``.
    """
    n = y.size
    cols = [-y[start - i : n - i] for i in range(1, na + 1)]
    cols += [u[start - nk - j : n - nk - j] for j in range(nb)]
    return np.stack(cols, axis=1)


def _polys(theta: FloatArray, na: int, nb: int, nk: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``A``, ``B`` and the exog coefficients from ``theta = [a.., b.., c..]``."""
    A = np.concatenate([[1.0], theta[:na]])
    B = np.concatenate([np.zeros(nk), theta[na : na + nb]])
    return A, B, theta[na + nb :]


def _stabilize(A: FloatArray) -> FloatArray:
    """Reflect poles outside the unit circle into it (instrument generation must not diverge)."""
    if A.size <= 1:
        return A
    poles = np.roots(A)
    outside = np.abs(poles) > 1.0
    if not np.any(outside):
        return A
    poles[outside] = 1.0 / np.conj(poles[outside])
    return np.real(np.poly(poles))


def _solve(Z: FloatArray, Phi: FloatArray, Y: FloatArray) -> FloatArray:
    """IV solution of ``Z^T Phi theta = Z^T Y`` via QR of both matrices.

    With ``Z = Q_z R_z`` and ``Phi = Q_p R_p``: ``theta = R_p^-1 (Q_z^T Q_p)^-1 Q_z^T Y``, so
    the condition number enters once, not squared (smooth, nearly collinear regressors).
    Columns are scaled to unit norm first. ``Z = Phi`` gives least squares.
    """
    scale = np.linalg.norm(Phi, axis=0)
    scale[scale == 0.0] = 1.0
    zscale = np.linalg.norm(Z, axis=0)
    zscale[zscale == 0.0] = 1.0
    Qp, Rp = np.linalg.qr(Phi / scale)
    if Z is Phi:
        c = Qp.T @ Y
    else:
        Qz, _ = np.linalg.qr(Z / zscale)
        c, *_ = np.linalg.lstsq(Qz.T @ Qp, Qz.T @ Y, rcond=None)
    sol, *_ = np.linalg.lstsq(Rp, c, rcond=None)
    return sol / scale


def _ar_fit(w: FloatArray, order: int) -> tuple[FloatArray, float]:
    """Yule-Walker AR model ``L(q) w = e`` (minimum phase). Returns ``L`` (``order+1``) and var(e)."""
    w = w - np.mean(w)
    n = w.size
    r = np.array([np.dot(w[: n - k], w[k:]) / n for k in range(order + 1)])
    if r[0] <= 0.0:
        return np.ones(1), 0.0
    r[1:] *= 1.0 - 1e-10  # tiny regularisation: keeps the Toeplitz system positive definite
    l = solve_toeplitz(r[:order], -r[1 : order + 1])
    L = np.concatenate([[1.0], l])
    return L, float(r[0] + np.dot(l, r[1 : order + 1]))


def arx(u: ArrayLike, y: ArrayLike, na: int, nb: int, nk: int = 1, *, exog: ArrayLike | None = None) -> ARXResult:
    """Least-squares (ARX) estimate of ``A(q) y = B(q) u + E c + e``.

    Args:
        u: input, shape ``N``.
        y: output, shape ``N``.
        na, nb, nk: orders (``na >= 0``, ``nb >= 1``, ``nk >= 0``).
        exog: optional extra regressors ``E`` (shape ``N x p``, already lagged as wanted), each
            with one static coefficient (e.g. a friction or offset term).

    Returns:
        :class:`ARXResult` with ``noise_variance`` = variance of the equation error.
        Consistent only when ``v`` is white; biased for coloured noise.
    """
    u_a, y_a, na, nb, nk = _check_data(u, y, na, nb, nk)
    E = _check_exog(exog, u_a.size)
    start = max(na, nk + nb - 1)
    Phi = np.hstack([_regressors(y_a, u_a, na, nb, nk, start), E[start:]])
    Y = y_a[start:]
    theta = _solve(Phi, Phi, Y)
    A, B, c = _polys(theta, na, nb, nk)
    return ARXResult(A=A, B=B, nk=nk, noise_variance=float(np.var(Y - Phi @ theta)), exog_coef=c)


def _instrument(u: FloatArray, E: FloatArray, A: FloatArray, B: FloatArray, c: FloatArray) -> FloatArray:
    """Noise-free simulation ``x = (B u + E c) / A`` of a model (A stabilised)."""
    return lfilter([1.0], _stabilize(A), lfilter(B, [1.0], u) + E @ c)


def _iv4_pass(
    u: FloatArray, y: FloatArray, E: FloatArray, theta: FloatArray, na: int, nb: int, nk: int, ar_order: int
) -> tuple[FloatArray, FloatArray, float]:
    """Stages 3-4 with the instruments and residuals of model ``theta``. Returns theta, L, var."""
    start = max(na, nk + nb - 1)
    A, B, c = _polys(theta, na, nb, nk)
    # stage 3: AR model of the equation error of the model
    w = lfilter(A, [1.0], y) - lfilter(B, [1.0], u) - E @ c
    L, _ = _ar_fit(w[start:], ar_order)
    # stage 4: instruments from the model, everything prefiltered by L
    x = _instrument(u, E, A, B, c)
    yf, uf, xf = (lfilter(L, [1.0], s) for s in (y, u, x))
    Ef = lfilter(L, [1.0], E, axis=0) if E.shape[1] else E
    start4 = start + ar_order
    Phi = np.hstack([_regressors(yf, uf, na, nb, nk, start4), Ef[start4:]])
    Z = np.hstack([_regressors(xf, uf, na, nb, nk, start4), Ef[start4:]])
    theta_new = _solve(Z, Phi, yf[start4:])
    e = yf[start4:] - Phi @ theta_new
    return theta_new, L, float(np.var(e))


def iv4(
    u: ArrayLike,
    y: ArrayLike,
    na: int,
    nb: int,
    nk: int = 1,
    *,
    max_iter: int = 10,
    tol: float = 1e-7,
    ar_order: int | None = None,
    exog: ArrayLike | None = None,
) -> IV4Result:
    """Iterated four-stage instrumental-variable estimate of ``A(q) y = B(q) u + E c + v``.

    Args:
        u: input, shape ``N`` (must be (nearly) uncorrelated with the noise ``v``, i.e. open loop).
        y: output, shape ``N``.
        na, nb, nk: orders (``na >= 0``, ``nb >= 1``, ``nk >= 0``).
        max_iter: maximum number of passes of stages 2-4 (``1`` = MATLAB's one-pass ``iv4``).
        tol: stop when ``|theta_new - theta_old| <= tol * (1 + |theta_old|)`` (Euclidean norms).
        ar_order: order of the stage-3 noise AR model; default ``na + nb``.
        exog: optional extra regressors ``E`` (shape ``N x p``), each with one static coefficient
            ``c``, used as their own instruments (so they must be nearly noise-free).

    Returns:
        :class:`IV4Result` (``A``, ``B``, ``noise_variance`` of the whitened residual,
        ``iterations``, ``converged``, prefilter ``L``).
    """
    u_a, y_a, na, nb, nk = _check_data(u, y, na, nb, nk)
    E = _check_exog(exog, u_a.size)
    max_iter = _as_order(max_iter, "max_iter", 1)
    if not isinstance(tol, (int, float)) or isinstance(tol, bool) or not tol > 0:
        raise ValueError(f"tol: expected a positive number, received {tol!r}")
    ar = na + nb if ar_order is None else _as_order(ar_order, "ar_order", 0)
    if u_a.size < 2 * (max(na, nk + nb - 1) + ar + na + nb) + 10:
        raise ValueError(f"u, y: expected more samples than {u_a.size} for ar_order={ar}")
    start = max(na, nk + nb - 1)

    # stage 1: least squares
    first = arx(u_a, y_a, na, nb, nk, exog=E)
    # stage 2: IV with instruments simulated from the LS model (no prefilter)
    x = _instrument(u_a, E, first.A, first.B, first.exog_coef)
    Phi = np.hstack([_regressors(y_a, u_a, na, nb, nk, start), E[start:]])
    Z = np.hstack([_regressors(x, u_a, na, nb, nk, start), E[start:]])
    theta = _solve(Z, Phi, y_a[start:])

    converged = False
    L = np.ones(1)
    var = float("nan")
    it = 0
    for it in range(1, max_iter + 1):
        theta_new, L, var = _iv4_pass(u_a, y_a, E, theta, na, nb, nk, ar)
        step = float(np.linalg.norm(theta_new - theta))
        size = float(np.linalg.norm(theta))
        theta = theta_new
        if step <= tol * (1.0 + size):
            converged = True
            break
    A, B, c = _polys(theta, na, nb, nk)
    return IV4Result(
        A=A, B=B, nk=nk, noise_variance=var, exog_coef=c, iterations=it, converged=converged, L=L
    )


# ----------------------------------------------------------------------------- two-mass

OUTPUTS = ("speed", "speed_difference", "mean_speed_difference", "angle")
#: Integrators ``1/(1 - q^-1)`` each output's model leaves out (put back exactly before the conversion).
_INTEGRATORS = {"speed": 0, "speed_difference": 1, "mean_speed_difference": 2, "angle": 2}
#: A pole counts as real when its imaginary part is below this share of its size (at least 1 rad/s).
_REAL_POLE_TOL = 1e-9
#: A discrete pole counts as on the negative real axis when its imaginary part is below this.
_NEGATIVE_AXIS_TOL = 1e-12


@dataclass(frozen=True)
class TwoMassEstimate:
    """The two-mass parameters of a discrete model (:func:`two_mass_from_discrete`); NaN values,
    ``valid=False`` and a ``reason`` where the model has no resonance pair or is non-physical.
    ``J_M``, ``J_L``, ``C_F``, ``D_F`` are :func:`sim.two_mass_derived` of ``J_sigma``, ``V_J``,
    ``f_e``, ``d``."""

    J_sigma: float  # [kg m^2] total inertia (inverse residue at the integrator)
    V_J: float  # [-] inertia ratio J_L / J_M
    f_e: float  # [Hz] damped resonance frequency
    d: float  # [-] damping ratio of the resonance pair
    w_0: float  # [rad/s] undamped resonance (the pole's size)
    w_A: float  # [rad/s] anti-resonance (from the numerator)
    J_M: float  # [kg m^2]
    J_L: float  # [kg m^2]
    C_F: float  # [Nm/rad]
    D_F: float  # [Nm s/rad]
    integrator_pole: float  # the speed integrator's pole in z (1 for a put-back integrator)
    valid: bool
    reason: str

    @property
    def f_0(self) -> float:
        """Undamped resonance frequency [Hz]."""
        return self.w_0 / (2 * np.pi)

    @property
    def f_A(self) -> float:
        """Anti-resonance frequency [Hz]."""
        return self.w_A / (2 * np.pi)

    @classmethod
    def invalid(cls, reason: str) -> TwoMassEstimate:
        """No estimate (NaN values), for ``reason``."""
        nan = float("nan")
        return cls(nan, nan, nan, nan, nan, nan, nan, nan, nan, nan, nan, valid=False, reason=reason)


@dataclass(frozen=True)
class IV4TwoMass:
    """:func:`identify_iv4`'s answer: the two-mass estimate and the IV4 model ``Delta w = B/A u``
    it came from (sample time ``T_model`` [s])."""

    estimate: TwoMassEstimate
    A: FloatArray
    B: FloatArray
    T_model: float
    iterations: int
    converged: bool
    noise_variance: float


def _zoh_numerator(den: NDArray[np.float64], j: int, T_s: float) -> FloatArray:
    """Discrete numerator (in ``q^-1``, length ``n + 1``, leading 0) of the ZOH sampling of
    ``s^j / den(s)``; ``den`` monic of degree ``n > j``, real coefficients (descending powers)."""
    n = den.size - 1
    Ac = np.zeros((n, n))
    Ac[0, :] = -den[1:]
    Ac[1:, :-1] = np.eye(n - 1)
    M = np.zeros((n + 1, n + 1))
    M[:n, :n] = Ac
    M[0, n] = 1.0
    E = expm(M * T_s)
    Ad, Bd = E[:n, :n], E[:n, n]
    # Markov parameters h_k = C Ad^(k-1) Bd, then B = A_d * h (truncated): no cancellation
    h = np.zeros(n + 1)
    x = Bd.copy()
    for k in range(1, n + 1):
        h[k] = x[n - 1 - j]  # C picks the coefficient of s^j (controllable canonical form)
        x = Ad @ x
    A_d = np.real(np.poly(np.linalg.eigvals(Ad)))
    return np.convolve(A_d, h)[: n + 1]


def _is_time(value: Any, positive: bool) -> bool:
    """``value`` is a Python number (no bool) ``> 0`` (``positive``) or ``>= 0``."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and (value > 0 if positive else value >= 0)


def _checked_model(A: ArrayLike, B: ArrayLike, T_s: float, output: str, T_Ei: float) -> tuple[FloatArray, FloatArray]:
    """``A`` (normalized to a leading 1) and ``B`` as arrays, checked against ``output``'s model."""
    A_a, B_a = as_signal("A", A), as_signal("B", B)
    if not _is_time(T_s, positive=True):
        raise ValueError(f"T_s: expected a positive sample time in s, received {T_s!r}")
    if output not in OUTPUTS:
        raise ValueError(f"output: expected one of {OUTPUTS}, received {output!r}")
    if A_a.size < 1 or A_a[0] == 0.0:
        raise ValueError(f"A: expected a leading coefficient 1, received {A_a[:1]}")
    if not _is_time(T_Ei, positive=False):
        raise ValueError(f"T_Ei: expected a time constant >= 0 in s, received {T_Ei!r}")
    A_a = A_a / A_a[0]
    order_expected = 3 if output == "speed" else 2
    if A_a.size - 1 != order_expected:
        raise ValueError(f"A: expected order {order_expected} for output={output!r}, received order {A_a.size - 1}")
    if B_a.size < 2 or B_a[0] != 0.0:
        raise ValueError(f"B: expected a delay nk >= 1 (B[0] == 0) and length >= 2, received {B_a.tolist()}")
    if not np.any(B_a != 0.0):
        raise ValueError("B: expected a non-zero numerator, received all zeros")
    return A_a, B_a


def _full_model(A: FloatArray, B: FloatArray, T_s: float, output: str, T_Ei: float) -> tuple[FloatArray, FloatArray]:
    """The model from the torque (reference, for ``T_Ei > 0``) to the speed (or angle) with the
    left-out integrators and the current-loop pole put back into ``A``."""
    for _ in range(_INTEGRATORS[output]):
        A = np.convolve(A, [1.0, -1.0])
    if T_Ei > 0:
        A = np.convolve(A, [1.0, -np.exp(-T_s / T_Ei)])
    if output == "mean_speed_difference":
        B = B * T_s
    if B.size > A.size:
        raise ValueError(f"B: expected at most {A.size} coefficients for output={output!r}, T_Ei={T_Ei}, "
                         f"received {B.size}")
    return A, B


def _continuous_poles(poles: NDArray[np.complex128], T_s: float, n_int: int, T_Ei: float) -> tuple[NDArray[np.complex128], int]:
    """``s = log(z)/T_s`` of the discrete ``poles``, the put-back integrators and the current-loop
    pole set exactly; and the index of the current-loop pole (-1: none)."""
    s_poles = np.log(poles.astype(complex)) / T_s
    if n_int > 0:
        s_poles[np.argsort(np.abs(poles - 1.0))[:n_int]] = 0.0  # the put-back integrators are exact
    i_cur = -1
    if T_Ei > 0:
        i_cur = int(np.argmin(np.abs(s_poles + 1.0 / T_Ei)))
        s_poles[i_cur] = -1.0 / T_Ei  # the known current-loop pole, exact
    return s_poles, i_cur


def _numerator(s_poles: NDArray[np.complex128], B: FloatArray, T_s: float, T_Ei: float) -> FloatArray:
    """The continuous speed numerator ``[n_2, n_1, n_0]`` whose ZOH sampling over the poles
    ``s_poles`` fits ``B`` best (least squares; exact when consistent)."""
    n = s_poles.size
    den = np.real(np.poly(s_poles))
    basis = np.stack([_zoh_numerator(den, j, T_s) for j in range(3)], axis=1)[1:]
    target = np.concatenate([B, np.zeros(n + 1 - B.size)])[1:]
    scale = np.linalg.norm(basis, axis=0)
    coef, *_ = np.linalg.lstsq(basis / scale, target, rcond=None)
    n0, n1, n2 = coef / scale
    if T_Ei > 0:  # G(s) / (1 + s T_Ei) = (N / T_Ei) / (... (s + 1/T_Ei))
        n0, n1, n2 = T_Ei * n0, T_Ei * n1, T_Ei * n2
    return np.array([n2, n1, n0])


def _total_inertia(N_cont: FloatArray, s_poles: NDArray[np.complex128], i_cur: int, n_int: int, a_int: complex) -> float:
    """``J_sigma``: the inverse residue of the speed model ``N_cont / prod(s - p)`` at the
    integrator pole ``a_int`` (NaN where the residue has no real part)."""
    speed_poles = np.delete(s_poles, i_cur) if i_cur >= 0 else s_poles
    if n_int == 2:  # the angle model has one more pole at 0
        speed_poles = np.delete(speed_poles, int(np.argmin(np.abs(speed_poles))))
    others = np.delete(speed_poles, int(np.argmin(np.abs(speed_poles - a_int))))
    res = np.polyval(N_cont, a_int) / np.prod(a_int - others)
    return float(1.0 / np.real(res)) if np.real(res) != 0 else float("nan")


def _estimate(J_sigma: float, s_p: complex, N_cont: FloatArray, a_int: complex, T_s: float) -> TwoMassEstimate:
    """The estimate of the total inertia, the resonance pole ``s_p`` and the numerator ``N_cont``
    (``w_A^2 = n_0/n_2``), the rest derived by :func:`sim.two_mass_derived`."""
    n2, _, n0 = N_cont
    w_0 = float(abs(s_p))
    d = float(-s_p.real / w_0)
    f_e = float(s_p.imag / (2 * np.pi))
    w_A2 = float(n0 / n2) if n2 != 0 else float("nan")
    w_A = float(np.sqrt(w_A2)) if w_A2 > 0 else float("nan")
    V_J = (w_0 / w_A) ** 2 - 1.0 if w_A2 > 0 else float("nan")
    with np.errstate(divide="ignore", invalid="ignore"):  # NaN/inf for a non-physical model, not an error
        derived = two_mass_derived(np.float64(J_sigma), np.float64(V_J), np.float64(f_e), np.float64(d))
    valid = bool(J_sigma > 0 and V_J > 0 and 0 < d < 1)
    return TwoMassEstimate(
        J_sigma=J_sigma, V_J=float(V_J), f_e=f_e, d=d, w_0=w_0, w_A=w_A, J_M=float(derived.J_M),
        J_L=float(derived.J_L), C_F=float(derived.C_F), D_F=float(derived.D_F),
        integrator_pole=float(np.real(np.exp(a_int * T_s))), valid=valid,
        reason="" if valid else "non-physical values (expected J_sigma > 0, V_J > 0, 0 < d < 1)")


def two_mass_from_discrete(
    A: ArrayLike, B: ArrayLike, T_s: float, *, output: str = "speed", T_Ei: float = 0.0
) -> TwoMassEstimate:
    """Physical two-mass parameters from a discrete model from motor torque to motor speed.

    Continuous model (no backlash, no friction; ``w_0^2 = C_F J_sigma/(J_M J_L)``, ``w_A^2 = C_F/J_L``)::

        w_M/M_M = (J_L s^2 + D_F s + C_F) / (s (J_M J_L s^2 + D_F J_sigma s + C_F J_sigma))
                = (n_2 s^2 + n_1 s + n_0) / (s (s^2 + 2 d w_0 s + w_0^2))

    with ``n_2 = 1/J_M``, ``n_0 = w_0^2 / J_sigma``, ``w_A^2 = n_0/n_2``, ``V_J = (w_0/w_A)^2 - 1``.

    Conversion (exact for zero-order-hold sampled data):

    1. the discrete poles map exactly, ``s = log(z)/T_s``: the complex pair gives ``w_0 = |s|``,
       ``d = -Re(s)/|s|``, ``f_e = Im(s)/(2 pi)``; the real pole nearest ``z = 1`` is the integrator;
    2. the numerator: ZOH sampling is linear in the continuous numerator for fixed poles, so the
       discrete numerator ``B`` is fitted (least squares; exact when consistent) as
       ``sum_j n_j ZOH(s^j / D(s))``, ``j = 0, 1, 2`` - the physical numerator degree;
    3. ``J_sigma`` = inverse residue of ``G(s)`` at the integrator pole ``a``
       (``= w_0^2/n_0`` for ``a = 0``), ``w_A^2 = n_0/n_2``; ``J_M``, ``J_L``, ``C_F``, ``D_F``
       from ``J_sigma``, ``V_J``, ``f_e``, ``d`` by :func:`sim.two_mass_derived`.

    Args:
        A: ``[1, a_1, ..., a_na]`` denominator in ``q^-1``.
        B: ``[0]*nk + [b_0, ...]`` numerator in ``q^-1`` (``nk >= 1``).
        T_s: sample time [s] of the model.
        output: what the model's output is:
            ``"speed"``: speed samples ``w_M(k)``; ``A`` contains the integrator (order 3);
            ``"speed_difference"``: ``w_M(k) - w_M(k-1)``; ``A`` is the resonance (order 2),
            the integrator ``1/(1 - q^-1)`` is put back exactly;
            ``"mean_speed_difference"``: difference of the sample-interval mean speed
            ``(phi_M(k) - phi_M(k-1))/T_s`` (an encoder speed); the model is then the motor
            angle's, ``phi_M = T_s B / ((1 - q^-1)^2 A) u`` (double integrator put back);
            ``"angle"``: the motor angle, ``phi_M = B / ((1 - q^-1)^2 A) u``.
        T_Ei: current-loop time constant [s]; ``> 0`` means the model's input is the held torque
            reference ``M_ref`` and the known current-loop pole ``z = exp(-T_s/T_Ei)`` is put
            back like the integrators (``A`` then still holds only the resonance). ``0``: the
            input is the (held) air-gap torque itself.

    Returns:
        :class:`TwoMassEstimate` (``valid=False``, NaN values and a reason where the model has no
        resonance pair or is non-physical).
    """
    A_a, B_a = _checked_model(A, B, T_s, output, T_Ei)
    A_full, B_full = _full_model(A_a, B_a, T_s, output, T_Ei)
    n_int = _INTEGRATORS[output]
    poles = np.roots(A_full)
    if np.any(np.abs(poles) == 0.0) or np.any((np.abs(poles.imag) < _NEGATIVE_AXIS_TOL) & (poles.real < 0)):
        return TwoMassEstimate.invalid("a pole at z = 0 or on the negative real axis (no continuous equivalent)")
    s_poles, i_cur = _continuous_poles(poles, T_s, n_int, T_Ei)
    is_real = np.abs(s_poles.imag) < _REAL_POLE_TOL * np.maximum(1.0, np.abs(s_poles))
    upper = np.where((s_poles.imag > 0) & ~is_real)[0]
    if upper.size == 0:
        return TwoMassEstimate.invalid("no complex pole pair (no resonance in the model)")
    s_p = s_poles[upper[0]]
    drop = [upper[0], int(np.argmin(np.abs(s_poles - np.conj(s_p))))] + ([i_cur] if i_cur >= 0 else [])
    rest = np.delete(s_poles, drop)
    a_int = complex(rest[np.argmin(np.abs(rest))])  # the (speed) integrator pole; 0 for differenced models
    N_cont = _numerator(s_poles, B_full, T_s, T_Ei)
    J_sigma = _total_inertia(N_cont, s_poles, i_cur, n_int, a_int)
    return _estimate(J_sigma, s_p, N_cont, a_int, T_s)


def mean_torque(torque: ArrayLike, T_s: float, T_Ei: float, *, is_reference: bool = False) -> FloatArray:
    """The mean air-gap torque over each sample interval ``[k T_s, (k+1) T_s]``, shape ``N - 1``.

    The current loop ``T_Ei dM_M/dt = M_ref - M_M`` with a held reference makes ``M_M`` an
    exponential within each interval, ``a = exp(-T_s/T_Ei)``:

    - measured torque samples ``M_M(k)``: ``M_ref(k) = (M_M(k+1) - a M_M(k)) / (1 - a)``, and the
      interval mean is ``M_ref(k) + (M_M(k) - M_ref(k)) (T_Ei/T_s) (1 - a)`` (exact);
      for ``T_Ei = 0`` it is ``M_M(k+1)`` (the torque reached at the end of the interval);
    - a reference (``is_reference=True``, ``torque[k]`` held over the interval): ``M_M`` is
      simulated from ``M_M(0) = 0`` through the same loop.

    Measurement noise is amplified by about ``sqrt(1 + a^2)/(1 - a)`` (2.3 for the reference drive).
    """
    M = as_signal("torque", torque)
    if T_Ei <= 0:
        return M[:-1].copy() if is_reference else M[1:].copy()
    a = float(np.exp(-T_s / T_Ei))
    if is_reference:
        ref = M[:-1]
        M_M = np.concatenate([[0.0], lfilter([1.0 - a], [1.0, -a], ref)])[:-1]  # M_M(k)
    else:
        ref = (M[1:] - a * M[:-1]) / (1.0 - a)
        M_M = M[:-1]
    return ref + (M_M - ref) * (T_Ei / T_s) * (1.0 - a)


def identify_iv4(
    torque: ArrayLike,
    speed: ArrayLike,
    T_s: float,
    *,
    T_Ei: float = 0.0,
    torque_is_reference: bool = False,
    speed_is_mean: bool = True,
    friction: bool = True,
    max_iter: int = 10,
    tol: float = 1e-7,
) -> IV4TwoMass:
    """Identify ``J_sigma``, ``V_J``, ``f_e`` of a linear two-mass system with iterated IV4.

    The record must start at rest (speed and torque 0, as the SPEC test signal does).
    Preprocessing (``docs/iv4.md`` says why):

    - input: the mean air-gap torque over each sample interval (:func:`mean_torque`, exact
      for the known current loop ``T_Ei``), treated as held (zero-order hold) by the mechanics;
      for an encoder speed (``speed_is_mean=True``, the mean over ``[k-1, k]``) averaged once
      more, ``(u(k) + u(k-1))/2`` (trapezoid), so that the model keeps the speed's order;
    - the known rigid-body integrator is moved to the input: ``x = T cumsum(u)`` (the angular
      momentum-like "integrated torque" [Nm s]); output: the measured speed itself, so the speed
      quantisation stays white-ish noise on the output (differencing the speed would turn it
      into blue noise and lower the SNR of the elastic part);
    - model ``A(q) w = B(q) x`` with ``na = 2`` (the resonance), ``nb = 3``, ``nk = 1``;
      put back as ``Delta w = T B / A u`` and converted by :func:`two_mass_from_discrete`
      (``output="speed_difference"``);
    - load friction (``friction=True``): Coulomb and viscous friction and a torque offset act
      through the same integrator; three integrated regressors absorb them (see ``friction``);
    - no decimation: tried (block means, factor 4), it cost 5-30 % in ``V_J`` because block
      means of a step-like torque are not held at the slow rate; the QR-based IV solve copes
      with the poles near ``z = 1`` at full rate.

    Args:
        torque: ``M_M`` [Nm] (or ``K_M * current``) sampled with the speed, or the torque reference
            (``torque_is_reference=True``, ``torque[k]`` acts over ``[k T_s, (k+1) T_s]``); shape ``N``.
        speed: measured motor speed ``w_M`` [rad/s], shape ``N``.
        T_s: sample time [s].
        T_Ei: current-loop time constant [s] (known for a drive; SPEC: 0.5 ms); 0 = ideal loop.
        torque_is_reference: ``torque`` is ``M_ref`` (held), not the measured air-gap torque.
        speed_is_mean: the speed is an encoder speed ``(phi(k) - phi(k-1))/T_s`` (SPEC 1); else
            instantaneous speed samples.
        friction: add the load-friction and offset regressors (``exog`` of :func:`iv4`):
            ``T cumsum(sign w)`` (Coulomb), ``T cumsum(w)`` (viscous), ``T k`` (torque offset),
            each with one static coefficient, the motor speed standing in for the load speed.
        max_iter, tol: IV4 iteration control (see :func:`iv4`).

    Returns:
        :class:`IV4TwoMass`: the estimate of :func:`two_mass_from_discrete` and the ``Delta w``
        model (``A``, ``B``, ``T_model`` [s], ``iterations``, ``converged``, ``noise_variance``).
    """
    M = as_signal("torque", torque)
    w = as_signal("speed", speed)
    if M.shape != w.shape:
        raise ValueError(f"torque and speed: expected the same length, received {M.size} and {w.size}")
    for name, val, positive in (("T_s", T_s, True), ("T_Ei", T_Ei, False)):
        if not isinstance(val, (int, float)) or isinstance(val, bool) or not (val > 0 if positive else val >= 0):
            kind = "positive" if positive else "non-negative"
            raise ValueError(f"{name}: expected a {kind} time in s, received {val!r}")
    na, nb, nk = 2, 3, 1
    n_min = 40 * (na + nb) + 50
    T = T_s

    u_mean = mean_torque(M, T_s, T_Ei, is_reference=torque_is_reference)  # N - 1
    if speed_is_mean:
        u_mean = 0.5 * (u_mean + np.concatenate([[0.0], u_mean[:-1]]))
    if u_mean.size < n_min:
        raise ValueError(f"torque, speed: expected at least {n_min + 1} samples, received {M.size}")
    y = w[:-1]  # y(k) = w(k), driven by u(k-1), u(k-2), ... (u(k) acts over [k, k+1])
    x = T * np.cumsum(u_mean)  # integrator moved to the input
    exog = None
    if friction:
        # load friction, seen through the integrator: -M_FC sign(w) - mu_F w, integrated like x
        # (the motor speed stands in for the load speed); one static coefficient each
        w_int = w[1:] if speed_is_mean else w[:-1]  # speed over [k, k+1]
        cols = [T * np.cumsum(np.sign(w_int)), T * np.cumsum(w_int), T * np.arange(1, w_int.size + 1)]
        exog = np.stack([np.concatenate([[0.0], c[:-1]]) for c in cols], axis=1)  # lag 1, like x(k-1)
    model = iv4(x, y, na, nb, nk, max_iter=max_iter, tol=tol, exog=exog)
    B = model.B * T  # Delta w = (T B / A) u
    estimate = two_mass_from_discrete(model.A, B, T, output="speed_difference")
    return IV4TwoMass(estimate=estimate, A=model.A, B=B, T_model=T, iterations=model.iterations,
                      converged=model.converged, noise_variance=model.noise_variance)
