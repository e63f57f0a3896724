"""Seeded population samplers: the SPEC section 1 default ranges on one drive (all overridable), and
SPEC 3.1's envelope of drives and test runs (:func:`sample_envelope`); either with SPEC 1.1's
real-axis parts (:class:`RealAxisRanges`: constant load torque, motor friction) on request."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from sim._signal import TestSignalConfig, inertia_of_time_scale
from sim.params import DriveConfig, TwoMassParams


def _check_ranges(ranges: object, log_uniform: tuple[str, ...]) -> None:
    """Every ``(low, high)`` field of the dataclass ``ranges`` with ``0 <= low <= high`` (``low > 0``
    where log-uniform), each ``*_share`` in 0..1, ``cell`` an int >= 1; else ``ValueError``."""
    cls = type(ranges).__name__
    for f in fields(ranges):  # type: ignore[arg-type]
        v, where = getattr(ranges, f.name), f"{cls}.{f.name}"
        if f.name.endswith("_share"):
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{where}: expected 0..1, received {v}")
        elif f.name == "cell":
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{where}: expected an int >= 1, received {v!r}")
        elif len(v) != 2 or not 0 <= v[0] <= v[1]:
            raise ValueError(f"{where}: expected (low, high) with 0 <= low <= high, received {v}")
        elif f.name in log_uniform and v[0] <= 0:
            raise ValueError(f"{where}: log-uniform range needs low > 0, received {v}")


@dataclass(frozen=True)
class PopulationRanges:
    """Sampling ranges. ``*_log`` ranges are log-uniform; backlash in degrees (total width)."""

    J_sigma: tuple[float, float] = (0.01, 0.2)  # log-uniform [kg m^2]
    V_J: tuple[float, float] = (0.2, 5.0)  # log-uniform
    f_e: tuple[float, float] = (5.0, 500.0)  # log-uniform [Hz]
    d: tuple[float, float] = (0.005, 0.1)  # uniform
    backlash_deg: tuple[float, float] = (0.02, 1.0)  # log-uniform [degree], total width 2s
    backlash_zero_share: float = 0.3  # share of systems without backlash
    M_FC: tuple[float, float] = (0.0, 0.5)  # uniform [Nm]
    mu_F: tuple[float, float] = (0.0, 0.005)  # uniform [Nm s/rad]

    def __post_init__(self) -> None:
        _check_ranges(self, log_uniform=("J_sigma", "V_J", "f_e", "backlash_deg"))


@dataclass(frozen=True)
class RealAxisRanges:
    """SPEC 1.1's real-axis population, drawn on top of a population (each part independently), in
    units of the test's ``M*`` [Nm] and ``w_max`` [rad/s], so that it scales with the drive: a share
    ``M_L0_share`` of the systems has a constant load torque ``M_L0`` uniform in ``+-M_L0[1] M*``
    (``|M_L0|`` uniform in ``M_L0`` over ``M*``, either sign with equal odds); a share
    ``M_FCM_share`` has motor Coulomb friction ``M_FCM`` uniform in ``M_FCM`` over ``M*``; every
    system has motor viscous friction ``mu_FM`` with ``mu_FM w_max / M*`` uniform in ``mu_FM`` (on
    the reference drive and test, ``M* = 10 Nm``, ``w_max = 100 rad/s``: 0 .. 0.002 Nm s/rad, as
    SPEC 1.1 says; it scales with the drive as :class:`EnvelopeRanges`'s ``mu_F`` does)."""

    M_L0: tuple[float, float] = (0.0, 0.15)  # |M_L0| over M*, uniform
    M_L0_share: float = 0.5  # share of systems with a load torque
    M_FCM: tuple[float, float] = (0.0, 0.03)  # over M*, uniform
    M_FCM_share: float = 0.5  # share of systems with motor Coulomb friction
    mu_FM: tuple[float, float] = (0.0, 0.02)  # mu_FM w_max over M*, uniform

    def __post_init__(self) -> None:
        _check_ranges(self, log_uniform=())


def _real_axis(u: torch.Tensor, r: RealAxisRanges, M_star: torch.Tensor | float,
               w_max: torch.Tensor | float) -> dict[str, torch.Tensor]:
    """``M_L0``, ``M_FCM``, ``mu_FM`` (``n`` each) from the uniforms ``u`` (``6 x n``) and each system's
    test ``M_star`` [Nm] and ``w_max`` [rad/s] (numbers or ``n`` tensors)."""
    lin = lambda x, rng: rng[0] + x * (rng[1] - rng[0])  # noqa: E731
    zero = torch.zeros_like(u[0])
    sign = torch.where(u[1] < 0.5, -1.0, 1.0).to(torch.float64)
    M_L0 = torch.where(u[2] < r.M_L0_share, sign * lin(u[0], r.M_L0) * M_star, zero)
    M_FCM = torch.where(u[4] < r.M_FCM_share, lin(u[3], r.M_FCM) * M_star, zero)
    return {"M_L0": M_L0, "M_FCM": M_FCM, "mu_FM": lin(u[5], r.mu_FM) * M_star / w_max}


#: The reference test's ``M*`` [Nm] and ``w_max`` [rad/s] (SPEC 2's defaults), on which
#: :func:`sample_population` scales :class:`RealAxisRanges`.
_REFERENCE_TEST = TestSignalConfig()


def _real_axis_ranges(real_axis: RealAxisRanges | bool | None) -> RealAxisRanges | None:
    """``real_axis`` as ranges: ``True`` the defaults, None or ``False`` none; else a ``TypeError``."""
    if real_axis is None or real_axis is False:
        return None
    if real_axis is True:
        return RealAxisRanges()
    if not isinstance(real_axis, RealAxisRanges):
        raise TypeError(f"real_axis: expected RealAxisRanges, a bool or None, received {type(real_axis).__name__}")
    return real_axis


def _log_uniform(u: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
    return torch.exp(math.log(lo) + u * (math.log(hi) - math.log(lo)))


def sample_population(n: int, seed: int, ranges: PopulationRanges | None = None,
                      real_axis: RealAxisRanges | bool | None = None) -> TwoMassParams:
    """``n`` systems (batch shape ``(n,)``) drawn with a private generator seeded by ``seed``.

    ``real_axis``: SPEC 1.1's real-axis population on top (``True``: :class:`RealAxisRanges`'
    defaults; their shares of ``M*`` on the reference test, ``M* = 10 Nm``, ``w_max = 100 rad/s``),
    drawn after the default population's draws: the same seed gives the same seven parameters
    with or without it. None or ``False``: none (``M_L0 = M_FCM = mu_FM = 0``)."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"sample_population: expected n >= 1 (int), received {n!r}")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise TypeError(f"sample_population: expected an int seed, received {seed!r}")
    r = ranges or PopulationRanges()
    ra = _real_axis_ranges(real_axis)
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(9, n, generator=g, dtype=torch.float64)
    extra = {} if ra is None else _real_axis(torch.rand(6, n, generator=g, dtype=torch.float64), ra,
                                             _REFERENCE_TEST.M_star, _REFERENCE_TEST.w_max)
    backlash = torch.deg2rad(_log_uniform(u[4], *r.backlash_deg))
    backlash = torch.where(u[5] < r.backlash_zero_share, torch.zeros_like(backlash), backlash)
    return TwoMassParams(
        J_sigma=_log_uniform(u[0], *r.J_sigma),
        V_J=_log_uniform(u[1], *r.V_J),
        f_e=_log_uniform(u[2], *r.f_e),
        d=r.d[0] + u[3] * (r.d[1] - r.d[0]),
        backlash=backlash,
        M_FC=r.M_FC[0] + u[6] * (r.M_FC[1] - r.M_FC[0]),
        mu_F=r.mu_F[0] + u[7] * (r.mu_F[1] - r.mu_F[0]),
        **extra,
    )


@dataclass(frozen=True)
class EnvelopeRanges:
    """Sampling ranges over SPEC 3.1's drive envelope: drives, test runs and mechanics together.

    Systems come in *cells* of :attr:`cell` systems that share one drive and one test run (the
    simulator runs one drive per batch); each cell draws its drive and test, each system its
    mechanics. Log-uniform: ``T_s``, ``T_Ei``, ``M_N``, ``M_star_over_M_max``, ``w_max``,
    ``time_scale``, ``current_noise``, ``V_J``, ``f_e``, ``backlash_deg``; uniform: the rest;
    ``encoder_bits`` uniform integers (counts ``2**bits``). The test's ``M*`` is a share of the
    drive's ``M_max`` (the commissioning chain adapts it, section 8), ``w_max`` is free; the inertia
    follows from the test's time scale ``J_sigma w_max / M*``, friction from ``M*`` and ``w_max``
    (``M_FC`` and ``mu_F w_max`` as shares of ``M*``), the measured current's noise std as a share
    of ``M*/K_M``. Backlash is a physical angle (a gearbox's play does not scale with its motor).

    A share :attr:`reference_share` of the cells runs SPEC 1's reference drive and test instead
    (``DriveConfig()``, ``TestSignalConfig()``: the paper's world stays densely covered), with the
    time scales :attr:`reference_time_scale` (SPEC 1's ``J_sigma`` range at that test).
    """

    T_s: tuple[float, float] = (62.5e-6, 1e-3)  # [s]
    encoder_bits: tuple[int, int] = (12, 24)
    T_Ei: tuple[float, float] = (1e-4, 2e-3)  # [s]
    M_N: tuple[float, float] = (0.1, 1000.0)  # [Nm]
    M_max_over_M_N: tuple[float, float] = (1.5, 4.0)
    M_star_over_M_max: tuple[float, float] = (0.1, 1.0)
    w_max: tuple[float, float] = (5.0, 1000.0)  # [rad/s]
    time_scale: tuple[float, float] = (0.02, 5.0)  # J_sigma w_max / M* [s]
    current_noise: tuple[float, float] = (5e-4, 0.05)  # std over M*/K_M
    V_J: tuple[float, float] = (0.2, 5.0)
    f_e: tuple[float, float] = (5.0, 500.0)  # [Hz]
    d: tuple[float, float] = (0.005, 0.1)
    backlash_deg: tuple[float, float] = (0.01, 1.5)  # total width 2s [degree]
    backlash_zero_share: float = 0.3
    M_FC: tuple[float, float] = (0.0, 0.05)  # over M*
    mu_F: tuple[float, float] = (0.0, 0.05)  # mu_F w_max over M*
    cell: int = 8  # systems per drive and test run
    reference_share: float = 0.25  # share of cells on SPEC 1's reference drive and test
    reference_time_scale: tuple[float, float] = (0.1, 2.0)  # [s] their J_sigma w_max / M*

    def __post_init__(self) -> None:
        _check_ranges(self, log_uniform=tuple(f.name for f in fields(self) if f.name not in
                                              ("d", "M_FC", "mu_F", "encoder_bits", "backlash_zero_share", "cell",
                                               "reference_share")))


@dataclass(frozen=True)
class EnvelopeSample:
    """``params`` (batch ``(n,)``), and per system the index into ``cases`` of its drive and test
    run (``cell``, ``(n,)`` ints): ``cases[k] = (DriveConfig, TestSignalConfig)``."""

    params: TwoMassParams
    cell: torch.Tensor
    cases: tuple[tuple[DriveConfig, TestSignalConfig], ...]


def sample_envelope(n: int, seed: int, ranges: EnvelopeRanges | None = None,
                    real_axis: RealAxisRanges | bool | None = None) -> EnvelopeSample:
    """``n`` systems on drives and test runs drawn over SPEC 3.1's envelope (:class:`EnvelopeRanges`),
    with a private generator seeded by ``seed`` (a stream of its own: :func:`sample_population`'s
    draws for the same seed are unchanged). ``real_axis``: SPEC 1.1's parts on top, scaled with
    each system's test (see :func:`sample_population`; drawn after the rest: the same seed gives
    the same drives and mechanics with or without them)."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"sample_envelope: expected n >= 1 (int), received {n!r}")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise TypeError(f"sample_envelope: expected an int seed, received {seed!r}")
    r = ranges or EnvelopeRanges()
    ra = _real_axis_ranges(real_axis)
    g = torch.Generator().manual_seed(seed)
    n_cells = -(-n // r.cell)
    c = torch.rand(9, n_cells, generator=g, dtype=torch.float64)
    u = torch.rand(9, n, generator=g, dtype=torch.float64)
    lin = lambda x, rng: rng[0] + x * (rng[1] - rng[0])  # noqa: E731
    cases = []
    reference = (c[8] < r.reference_share).tolist()
    for k in range(n_cells):
        if reference[k]:
            cases.append((DriveConfig(), TestSignalConfig()))
            continue
        M_N = float(_log_uniform(c[0, k], *r.M_N))
        M_max = M_N * float(lin(c[1, k], r.M_max_over_M_N))
        M_star = M_max * float(_log_uniform(c[2, k], *r.M_star_over_M_max))
        bits = int(math.floor(lin(float(c[3, k]), (r.encoder_bits[0], r.encoder_bits[1] + 1))))
        drive = DriveConfig(M_max=M_max, M_N=M_N, K_M=1.0, T_Ei=float(_log_uniform(c[4, k], *r.T_Ei)),
                            T_s=float(_log_uniform(c[5, k], *r.T_s)), encoder_counts=2 ** min(bits, r.encoder_bits[1]),
                            current_noise_std=M_star * float(_log_uniform(c[6, k], *r.current_noise)))
        cases.append((drive, TestSignalConfig(M_star=M_star, w_max=float(_log_uniform(c[7, k], *r.w_max)))))
    cell = torch.arange(n) // r.cell
    M_star = torch.tensor([s.M_star for _, s in cases], dtype=torch.float64)[cell]
    w_max = torch.tensor([s.w_max for _, s in cases], dtype=torch.float64)[cell]
    backlash = torch.deg2rad(_log_uniform(u[4], *r.backlash_deg))
    backlash = torch.where(u[5] < r.backlash_zero_share, torch.zeros_like(backlash), backlash)
    on_reference = torch.tensor(reference, dtype=torch.bool)[cell]
    tau = torch.where(on_reference, _log_uniform(u[0], *r.reference_time_scale), _log_uniform(u[0], *r.time_scale))
    params = TwoMassParams(
        J_sigma=inertia_of_time_scale(tau, M_star, w_max),
        V_J=_log_uniform(u[1], *r.V_J),
        f_e=_log_uniform(u[2], *r.f_e),
        d=lin(u[3], r.d),
        backlash=backlash,
        M_FC=lin(u[6], r.M_FC) * M_star,
        mu_F=lin(u[7], r.mu_F) * M_star / w_max,
        **({} if ra is None else _real_axis(torch.rand(6, n, generator=g, dtype=torch.float64), ra, M_star, w_max)),
    )
    return EnvelopeSample(params, cell, tuple(cases))
