"""Drive configuration, two-mass parameters (batched float64 tensors), derived values, classes.

All quantities in SI units; symbols as in SPEC section 1. A :class:`TwoMassParams` holds seven
float64 tensors of one common ``batch_shape`` (any number of leading dimensions, ``()`` for one
system); every derived value has the same shape.
"""

from __future__ import annotations

import functools
import math
import numbers
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields
from typing import Any, NamedTuple

import torch

from sim._values import MAX_INT, shown

#: What each derived value is, with its formula (SPEC 1); the docstrings of the attributes.
DERIVED_DOCS: dict[str, str] = {
    "J_M": "Motor inertia [kg m^2]: ``J_sigma / (1 + V_J)``.",
    "J_L": "Load inertia [kg m^2]: ``J_sigma V_J / (1 + V_J)``.",
    "w_e": "Eigenfrequency [rad/s]: ``2 pi f_e``.",
    "w_0": "Natural frequency [rad/s]: ``w_e / sqrt(1 - d^2)``.",
    "C_F": "Stiffness [Nm/rad]: ``w_0^2 J_M J_L / J_sigma``.",
    "D_F": "Shaft damping [Nm s/rad]: ``2 d C_F / w_0``.",
}

STRUCTURE_CLASSES: tuple[str, ...] = ("stiff", "elastic", "elastic_backlash", "stiff_backlash")

PARAM_NAMES: tuple[str, ...] = ("J_sigma", "V_J", "f_e", "d", "backlash", "M_FC", "mu_F")
#: SPEC 1.1's real-axis parameters (optional, default 0): constant load torque ``M_L0`` [Nm] (any
#: sign), motor Coulomb friction ``M_FCM`` [Nm] and motor viscous friction ``mu_FM`` [Nm s/rad].
REAL_AXIS_NAMES: tuple[str, ...] = ("M_L0", "M_FCM", "mu_FM")
#: Every field of :class:`TwoMassParams`: :data:`PARAM_NAMES`, then :data:`REAL_AXIS_NAMES`.
ALL_PARAM_NAMES: tuple[str, ...] = PARAM_NAMES + REAL_AXIS_NAMES
DERIVED_NAMES: tuple[str, ...] = ("J_M", "J_L", "w_0", "w_e", "C_F", "D_F", "s")

# The thresholds of SPEC 1's class rule (see :func:`class_index`).
#: Normalized backlash ``s_N`` from which the backlash counts (``elastic_backlash`` or ``stiff_backlash``).
S_N_ELASTIC = 0.1
#: Normalized backlash ``s_N`` from which a system is ``stiff_backlash`` whatever its stiffness.
S_N_STIFF_BACKLASH = 1.0
#: ``w_e T_Ei`` from which the shaft is stiff (its eigenfrequency beyond the current loop's reach).
W_E_T_EI_STIFF = 1.0
#: Oscillation-to-resolution ratio ``r_osc`` from which the oscillation is visible in the encoder speed.
R_OSC_VISIBLE = 1.0
#: The thresholds of each quantity of the class rule (the arguments of :func:`class_index`).
CLASS_THRESHOLDS: dict[str, tuple[float, ...]] = {
    "s_N": (S_N_ELASTIC, S_N_STIFF_BACKLASH), "w_e_T_Ei": (W_E_T_EI_STIFF,), "r_osc": (R_OSC_VISIBLE,)}


def check_real(where: str, value: Any) -> int | float:
    """``value`` if it is a finite real number (Python, numpy or other ``numbers.Real``; not a bool),
    as a Python ``int`` or ``float`` (builtin values unchanged); else a one-line ``TypeError`` naming
    ``where`` (integers beyond a float's range too). The one check of the scalar settings of ``sim``
    (drive, test signal, limits) and of the numbers of a record's metadata."""
    if not isinstance(value, bool) and isinstance(value, numbers.Integral) and abs(int(value)) <= MAX_INT:
        return value if type(value) is int else int(value)
    if not isinstance(value, (bool, numbers.Integral)) and isinstance(value, numbers.Real):
        try:
            x = float(value)
        except OverflowError:  # a huge Fraction, say
            x = math.inf
        if math.isfinite(x):
            return value if type(value) is float else x
    raise TypeError(f"{where}: expected a finite number, received {shown(value)}")


def check_int(where: str, value: Any, low: int | None = None) -> int:
    """``value`` as a Python ``int`` if it is an integer (numpy ints too; not a bool) ``>= low``;
    else a one-line ``ValueError`` naming ``where``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or (low is not None and value < low):
        raise ValueError(f"{where}: expected an int{'' if low is None else f' >= {low}'}, received {value!r}")
    return int(value)


@dataclass(frozen=True)
class DriveConfig:
    """The known drive: torque limits, current loop, sampling, encoder, current noise.

    Each field takes any finite real number (numpy scalars are stored as Python numbers); bools,
    strings and non-finite values raise ``TypeError``, out-of-range values ``ValueError``."""

    M_max: float = 20.0  # torque limit [Nm]
    M_N: float = 10.0  # rated torque [Nm]
    K_M: float = 1.0  # torque constant [Nm/A]
    T_Ei: float = 5e-4  # current-loop time constant [s]
    T_s: float = 2.5e-4  # sample time [s]
    encoder_counts: int = 2**20  # counts per revolution
    current_noise_std: float = 0.01  # white noise on the measured current [A]

    def __post_init__(self) -> None:
        for f in fields(self):
            v = check_real(f"DriveConfig.{f.name}", getattr(self, f.name))
            object.__setattr__(self, f.name, v)
            if f.name == "current_noise_std":
                if v < 0:
                    raise ValueError(f"DriveConfig.current_noise_std: expected >= 0, received {v}")
            elif v <= 0:
                raise ValueError(f"DriveConfig.{f.name}: expected > 0, received {v}")
        if int(self.encoder_counts) != self.encoder_counts:
            raise ValueError(f"DriveConfig.encoder_counts: expected an integer, received {self.encoder_counts}")

    def current_noise(self, M_star: float) -> float:
        """The measured current's noise std as torque over a test's ``M_star`` [Nm] (SPEC 3.1's share)."""
        return self.current_noise_std * self.K_M / M_star

    @property
    def q_phi(self) -> float:
        """Angle quantum [rad]: one encoder count."""
        return 2.0 * math.pi / self.encoder_counts

    @property
    def counts_per_rad(self) -> float:
        """Encoder counts per radian of motor angle."""
        return self.encoder_counts / (2.0 * math.pi)

    @property
    def q_w(self) -> float:
        """Speed quantum [rad/s]: one count per sample time (:func:`speed_quantum`)."""
        return speed_quantum(self.encoder_counts, self.T_s)

    def to_dict(self) -> dict[str, float]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def speed_quantum(encoder_counts: float, T_s: float) -> float:
    """The encoder speed's quantum ``q_w = 2 pi / (encoder_counts T_s)`` [rad/s]: one count per sample."""
    return 2.0 * math.pi / (encoder_counts * T_s)


def one_mass_stand_in(T_s: float) -> dict[str, float]:
    """``V_J``, ``f_e`` [Hz] and ``d`` that make the two-mass model act as one mass at sample time
    ``T_s`` [s]: 1 % of the inertia on a shaft at the highest frequency the sampling resolves
    (``0.25 / T_s``, at most 1 kHz), well damped. For replaying a ``stiff`` answer (no ``f_e``, ``V_J``)."""
    return {"V_J": 0.01, "f_e": min(1000.0, 0.25 / T_s), "d": 0.1}


def _is_bool(value: Any) -> bool:
    """A bool, or a tensor, array or flat list of bools (``True`` would pass as 1.0)."""
    if isinstance(value, (list, tuple)):
        return any(isinstance(v, bool) for v in value)
    return isinstance(value, bool) or str(getattr(value, "dtype", "")) in ("bool", "torch.bool")


def _as_tensor(name: str, value: Any, check_finite: bool = True) -> torch.Tensor:
    if _is_bool(value):
        raise TypeError(f"TwoMassParams.{name}: expected a number or tensor, received a bool {value!r}")
    if isinstance(value, torch.Tensor):
        t = value.detach().to(torch.float64)
    else:
        try:  # a Python number, a sequence, an array
            t = torch.as_tensor(float(value) if isinstance(value, (int, float)) else value, dtype=torch.float64)
        except OverflowError:  # an integer beyond a float's range
            raise TypeError(f"TwoMassParams.{name}: expected numbers a float can hold, received "
                            f"{shown(value)}") from None
        except (TypeError, ValueError, RuntimeError) as err:
            raise TypeError(f"TwoMassParams.{name}: expected a number or tensor, received "
                            f"{type(value).__name__}") from err
    if check_finite and not bool(torch.isfinite(t).all()):
        raise ValueError(f"TwoMassParams.{name}: expected finite values, received {t}")
    return t


#: The keys of :meth:`TwoMassParams.from_dicts`: the physical set, the population set, the keys
#: both take (default 0) and all of them.
_PHYSICAL_KEYS = frozenset({"J_M", "J_L", "C_F", "D_F"})
_POPULATION_KEYS = frozenset({"J_sigma", "V_J", "f_e", "d"})
_SHARED_KEYS = ("backlash", "M_FC", "mu_F") + REAL_AXIS_NAMES
_DICT_KEYS = frozenset(ALL_PARAM_NAMES) | _PHYSICAL_KEYS

#: The valid range of each parameter, as the error states it (checked by :func:`_out_of_range`).
_RANGE_TEXT = {"J_sigma": "> 0", "V_J": "> 0", "f_e": "> 0", "d": "0 <= d < 1", "backlash": ">= 0", "M_FC": ">= 0",
               "mu_F": ">= 0", "M_L0": "any finite value", "M_FCM": ">= 0", "mu_FM": ">= 0"}


def _out_of_range(v: torch.Tensor) -> int | None:
    """Index into :data:`ALL_PARAM_NAMES` of the first parameter with a value outside its range, or
    None; ``v``: ``10 x n``, the rows in :data:`ALL_PARAM_NAMES` order (all finite; ``M_L0`` any)."""
    positive, d, nonneg, motor = v[:3], v[3], v[4:7], v[8:]
    ok = torch.cat([(positive > 0).all(1), ((d >= 0) & (d < 1)).all()[None], (nonneg >= 0).all(1),
                    torch.ones(1, dtype=torch.bool), (motor >= 0).all(1)])
    if bool(ok.all()):
        return None
    return int((~ok).nonzero()[0])


def _broadcast_shape(shapes: list[torch.Size]) -> torch.Size | None:
    """The broadcast of ``shapes`` (numpy rules), or None. Plain Python: ``torch.broadcast_shapes``
    imports torch.fx's symbolic shapes and sympy on first use (0.5 s) and costs ~0.3 ms a call."""
    ndim = max((len(s) for s in shapes), default=0)
    out = []
    for dims in zip(*[(1,) * (ndim - len(s)) + tuple(s) for s in shapes]):
        sizes = {d for d in dims if d != 1}
        if len(sizes) > 1:
            return None
        out.append(sizes.pop() if sizes else 1)
    return torch.Size(out)


class _Derived:
    """A derived value as a read-only attribute: the field of ``obj.derived`` of the same name,
    documented by :data:`DERIVED_DOCS`."""

    def __init__(self, name: str):
        self.name, self.__doc__ = name, DERIVED_DOCS[name]

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        return self if obj is None else getattr(obj.derived, self.name)


@dataclass(frozen=True)
class TwoMassParams:
    """Two-mass mechanic, population parameterization; tensors of shape ``*batch``.

    Each field takes a number, a tensor or an array-like (not bools) and is stored as a float64
    tensor of its own (a copy: editing the caller's tensor afterwards changes nothing here; do not
    edit these tensors in place either, the validation and the cached derived values rely on them).
    ``J_sigma`` total inertia [kg m^2], ``V_J = J_L/J_M``, ``f_e`` eigenfrequency [Hz],
    ``d`` relative damping, ``backlash`` total width ``2s`` [rad], ``M_FC`` load Coulomb friction
    [Nm], ``mu_F`` load viscous friction [Nm s/rad]; SPEC 1.1's real-axis parts, optional (default
    0: the model of SPEC 1): ``M_L0`` constant load torque on the load [Nm] (any sign), ``M_FCM``
    motor Coulomb friction [Nm], ``mu_FM`` motor viscous friction [Nm s/rad].
    """

    J_sigma: torch.Tensor
    V_J: torch.Tensor
    f_e: torch.Tensor
    d: torch.Tensor
    backlash: torch.Tensor
    M_FC: torch.Tensor
    mu_F: torch.Tensor
    M_L0: torch.Tensor = 0.0  # type: ignore[assignment]  (stored as a tensor)
    M_FCM: torch.Tensor = 0.0  # type: ignore[assignment]
    mu_FM: torch.Tensor = 0.0  # type: ignore[assignment]

    def __post_init__(self) -> None:
        ts = {n: _as_tensor(n, getattr(self, n), check_finite=False) for n in ALL_PARAM_NAMES}
        shape = _broadcast_shape([t.shape for t in ts.values()])
        if shape is None:
            raise ValueError(f"TwoMassParams: parameter shapes do not broadcast: "
                             f"{ {n: tuple(t.shape) for n, t in ts.items()} }")
        for n, t in ts.items():  # a copy of its own: the caller's tensor (or array) may change later
            object.__setattr__(self, n, torch.empty(shape, dtype=torch.float64, device=t.device).copy_(t))
        # one pass over all values (a model fit builds many small candidate batches)
        values = torch.stack([getattr(self, n).reshape(-1) for n in ALL_PARAM_NAMES])  # 10 x n
        finite = torch.isfinite(values).all(1)
        if not bool(finite.all()):
            n = ALL_PARAM_NAMES[int((~finite).nonzero()[0])]
            raise ValueError(f"TwoMassParams.{n}: expected finite values, received {ts[n]}")
        bad = _out_of_range(values)
        if bad is not None:
            n, t = ALL_PARAM_NAMES[bad], ts[ALL_PARAM_NAMES[bad]]
            raise ValueError(f"TwoMassParams.{n}: expected {_RANGE_TEXT[n]}, received range "
                             f"[{float(t.min())}, {float(t.max())}]")

    # -- shape handling -------------------------------------------------------------------
    @property
    def batch_shape(self) -> torch.Size:
        return self.J_sigma.shape

    def __len__(self) -> int:
        if self.J_sigma.dim() == 0:
            raise TypeError("len() of a single-system TwoMassParams")
        return self.J_sigma.shape[0]

    def __getitem__(self, index: Any) -> "TwoMassParams":
        return TwoMassParams(**{n: getattr(self, n)[index] for n in ALL_PARAM_NAMES})

    def reshape(self, *shape: int) -> "TwoMassParams":
        return TwoMassParams(**{n: getattr(self, n).reshape(*shape) for n in ALL_PARAM_NAMES})

    @property
    def real_axis(self) -> bool:
        """Whether any system has a SPEC 1.1 part (``M_L0``, ``M_FCM`` or ``mu_FM`` not 0)."""
        return bool(((self.M_L0 != 0) | (self.M_FCM != 0) | (self.mu_FM != 0)).any())

    @property
    def M_hold(self) -> torch.Tensor:
        """The torque [Nm] that holds each axis at rest before a test (SPEC 1.1): ``M_L0``, the
        ideal holding torque (the simulated drive knows it exactly), ``*batch``."""
        return self.M_L0

    # -- derived values (SPEC 1) ----------------------------------------------------------
    @functools.cached_property
    def derived(self) -> "TwoMassDerived":
        """All derived values of SPEC 1 (:func:`two_mass_derived`), ``*batch`` each."""
        return two_mass_derived(self.J_sigma, self.V_J, self.f_e, self.d)

    J_M = _Derived("J_M")
    J_L = _Derived("J_L")
    w_e = _Derived("w_e")
    w_0 = _Derived("w_0")
    C_F = _Derived("C_F")
    D_F = _Derived("D_F")

    @property
    def s(self) -> torch.Tensor:
        """Backlash half width [rad]."""
        return 0.5 * self.backlash

    def s_N(self, drive: DriveConfig) -> torch.Tensor:
        """Normalized backlash ``s C_F / M_N``."""
        return normalized_backlash(self.backlash, drive.M_N, self.C_F)

    def r_osc(self, drive: DriveConfig, M_star: float) -> torch.Tensor:
        """Oscillation-to-resolution ratio ``V_J M_star / (J_sigma w_0 q_w)``."""
        return self.V_J * M_star / (self.J_sigma * self.w_0 * drive.q_w)

    # -- construction / conversion ----------------------------------------------------------
    @classmethod
    def from_physical(cls, *, J_M: Any, J_L: Any, C_F: Any, D_F: Any = 0.0, backlash: Any = 0.0,
                      M_FC: Any = 0.0, mu_F: Any = 0.0, M_L0: Any = 0.0, M_FCM: Any = 0.0,
                      mu_FM: Any = 0.0) -> "TwoMassParams":
        """From ``J_M, J_L`` [kg m^2], ``C_F`` [Nm/rad], ``D_F`` [Nm s/rad] (and the rest as is)."""
        J_M, J_L, C_F, D_F = (_as_tensor(n, v) for n, v in
                              (("J_M", J_M), ("J_L", J_L), ("C_F", C_F), ("D_F", D_F)))
        if bool((J_M <= 0).any() | (J_L <= 0).any() | (C_F <= 0).any()):
            raise ValueError("TwoMassParams.from_physical: expected J_M, J_L, C_F > 0")
        J_sigma = J_M + J_L
        w_0 = torch.sqrt(C_F * J_sigma / (J_M * J_L))
        d = w_0 * D_F / (2.0 * C_F)
        w_e = w_0 * torch.sqrt(1.0 - d**2)
        return cls(J_sigma=J_sigma, V_J=J_L / J_M, f_e=w_e / (2.0 * math.pi), d=d,
                   backlash=backlash, M_FC=M_FC, mu_F=mu_F, M_L0=M_L0, M_FCM=M_FCM, mu_FM=mu_FM)

    def to_dicts(self) -> list[dict[str, float]]:
        """One dict of the parameters per system (flattened batch order): the seven of
        :data:`PARAM_NAMES`, and those of :data:`REAL_AXIS_NAMES` where this batch has any (:attr:`real_axis`)."""
        names = ALL_PARAM_NAMES if self.real_axis else PARAM_NAMES
        cols = {n: getattr(self, n).reshape(-1).tolist() for n in names}
        return [{n: cols[n][i] for n in names} for i in range(self.J_sigma.numel())]

    @classmethod
    def from_dicts(cls, items: Mapping[str, Any] | Iterable[Mapping[str, Any]]) -> "TwoMassParams":
        """From one dict (a single system) or a list of dicts (batch ``(n,)``).

        Each dict holds the seven parameters (``backlash``, ``M_FC``, ``mu_F``, ``d`` default to 0;
        optionally ``M_L0``, ``M_FCM``, ``mu_FM``, default 0) or the physical set ``J_M, J_L, C_F``
        (+ optional ``D_F``), not both (``ValueError``)."""
        single = isinstance(items, Mapping)
        rows = [items] if single else list(items)
        if not rows:
            raise ValueError("TwoMassParams.from_dicts: expected at least one system, received none")
        parts = []
        for i, row in enumerate(rows):
            if not isinstance(row, Mapping):
                raise TypeError(f"TwoMassParams.from_dicts: system {i}: expected a dict, received {type(row).__name__}")
            unknown = sorted(set(row) - _DICT_KEYS)
            if unknown:
                raise ValueError(f"TwoMassParams.from_dicts: system {i}: unknown keys {unknown}; "
                                 f"expected {list(ALL_PARAM_NAMES)} or J_M, J_L, C_F, D_F")
            physical = sorted(set(row) & _PHYSICAL_KEYS)
            population = sorted(set(row) & _POPULATION_KEYS)
            if physical and population:
                raise ValueError(f"TwoMassParams.from_dicts: system {i}: expected either J_sigma, V_J, f_e, d or "
                                 f"J_M, J_L, C_F, D_F, received both {population} and {physical}")
            rest = {k: row.get(k, 0.0) for k in _SHARED_KEYS}
            if physical:
                missing = [k for k in ("J_M", "J_L", "C_F") if k not in row]
                if missing:
                    raise ValueError(f"TwoMassParams.from_dicts: system {i}: missing keys {missing}")
                parts.append(cls.from_physical(J_M=row["J_M"], J_L=row["J_L"], C_F=row["C_F"],
                                               D_F=row.get("D_F", 0.0), **rest))
            else:
                missing = [k for k in ("J_sigma", "V_J", "f_e") if k not in row]
                if missing:
                    raise ValueError(f"TwoMassParams.from_dicts: system {i}: missing keys {missing}")
                parts.append(cls(J_sigma=row["J_sigma"], V_J=row["V_J"], f_e=row["f_e"],
                                 d=row.get("d", 0.0), **rest))
        if single:
            return parts[0]
        return cls(**{n: torch.stack([getattr(p, n) for p in parts]) for n in ALL_PARAM_NAMES})

    def truth(self, drive: DriveConfig, M_star: float) -> list[dict[str, Any]]:
        """Per system: the parameters (those of :data:`REAL_AXIS_NAMES` too), the derived values and
        the structure class name."""
        cls_idx = structure_class(self, drive, M_star).reshape(-1).tolist()
        dv = self.derived  # once: each derived attribute would compute all of them
        cols = {n: getattr(dv if n in TwoMassDerived._fields else self, n).reshape(-1).tolist()
                for n in ALL_PARAM_NAMES + DERIVED_NAMES}
        cols["s_N"] = self.s_N(drive).reshape(-1).tolist()
        cols["r_osc"] = self.r_osc(drive, M_star).reshape(-1).tolist()
        out = []
        for i, c in enumerate(cls_idx):
            row: dict[str, Any] = {n: v[i] for n, v in cols.items()}
            row["structure"] = STRUCTURE_CLASSES[c]
            out.append(row)
        return out


def structure_class(params: TwoMassParams, drive: DriveConfig, M_star: float) -> torch.Tensor:
    """Ground-truth class index into :data:`STRUCTURE_CLASSES` (LongTensor ``*batch``), SPEC 1."""
    return class_index(params.s_N(drive), params.w_e * drive.T_Ei, params.r_osc(drive, M_star))


class TwoMassDerived(NamedTuple):
    """The derived values of SPEC 1, of the type and shape of the inputs (see :data:`DERIVED_DOCS`)."""

    J_M: Any
    J_L: Any
    w_e: Any
    w_0: Any
    C_F: Any
    D_F: Any


def two_mass_derived(J_sigma: Any, V_J: Any, f_e: Any, d: Any) -> TwoMassDerived:
    """``J_M, J_L, w_e, w_0, C_F, D_F`` from ``J_sigma, V_J, f_e, d`` (SPEC 1): the one definition,
    for Python floats, numpy arrays and torch tensors alike (elementwise, broadcasting)."""
    J_M = J_sigma / (1.0 + V_J)
    J_L = J_sigma * V_J / (1.0 + V_J)
    w_e = 2.0 * math.pi * f_e
    w_0 = w_e / (1.0 - d * d) ** 0.5
    C_F = w_0 * w_0 * J_M * J_L / J_sigma
    return TwoMassDerived(J_M, J_L, w_e, w_0, C_F, 2.0 * d * C_F / w_0)


def gap_width(s_N: Any, M_N: Any, C_F: Any) -> Any:
    """The backlash ``2s`` [rad] of the normalized backlash ``s_N = s C_F / M_N`` (floats, arrays or tensors)."""
    return 2.0 * s_N * M_N / C_F


def normalized_backlash(backlash: Any, M_N: Any, C_F: Any) -> Any:
    """The normalized backlash ``s_N = s C_F / M_N`` of the width ``backlash = 2s`` [rad] (floats,
    arrays or tensors)."""
    return 0.5 * backlash * C_F / M_N


def class_index(s_N: Any, w_e_T_Ei: Any, r_osc: Any) -> torch.Tensor:
    """SPEC 1's class rule on the normalized backlash ``s_N``, ``w_e T_Ei`` and ``r_osc``: an index
    into :data:`STRUCTURE_CLASSES` (LongTensor of the broadcast shape; floats give a 0-d tensor)."""
    s_N, w_e_T_Ei, r_osc = (torch.as_tensor(x, dtype=torch.float64) for x in (s_N, w_e_T_Ei, r_osc))
    soft = w_e_T_Ei < W_E_T_EI_STIFF
    visible = r_osc >= R_OSC_VISIBLE
    backlash = s_N >= S_N_ELASTIC
    cls = torch.zeros(_broadcast_shape([s_N.shape, soft.shape, visible.shape]) or (), dtype=torch.long)
    cls = torch.where((s_N < S_N_ELASTIC) & soft & visible, 1, cls)
    cls = torch.where(soft & backlash & (s_N < S_N_STIFF_BACKLASH), 2, cls)
    return torch.where((s_N >= S_N_STIFF_BACKLASH) | (~soft & backlash), 3, cls)
