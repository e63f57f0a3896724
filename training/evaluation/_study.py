"""Evaluation of the SOM identification against IV4 on the paper's grid and a random set (SPEC 7).

Three jobs, in this order:

1. **Sets** (:class:`EvalSet`): the paper's grid (``f_e`` x ``backlash`` cells, ``per_cell``
   systems each; ``J_sigma``, ``V_J``, ``d``, ``M_FC``, ``mu_F`` drawn from the SPEC default
   population) and a random set from the default population.
2. **Runs** (:func:`run_set`): simulate every system once, run the SOM identifier and IV4 on the
   *same* record in a spawned process pool (one BLAS thread per worker), and keep one row per
   system: ``truth`` (true parameters, ``s_N``, ``r_osc``, ``w_e_T_Ei``, class), ``som`` and
   ``iv4`` (estimates, SI units). Per-method results are cached on disk, keyed by a hash of
   everything they depend on; a cache file of another config is refused, never mixed.
3. **Aggregation** (:func:`summarize`): recognition rates ``E_30``/``E_50`` per grid cell, per
   backlash, per true class and overall; per-parameter error statistics; the structure
   confusion matrix; the issue's acceptance checks. All figures come from ``training.evaluation._metrics``.

Conventions: a missing estimate is a miss. The SOM gives no ``f_e``/``V_J`` for the ``stiff``
class (``None``), a record it cannot analyse gets ``error``; IV4 results with ``valid=False``
count as missing. Relative errors are signed in the statistics and absolute in ``E_x``.
"""

from __future__ import annotations

import ast
import hashlib
import importlib.util
import json
import math
import os
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Executor, Future, wait
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sim import DriveConfig, PopulationRanges, TestSignalConfig, TwoMassParams, iter_records, sample_population
from sim.params import STRUCTURE_CLASSES
from training.evaluation import _metrics as metrics
from training.errors import UserError

#: The paper's grid (section 4, Fig. 10): eigenfrequencies [Hz] and total backlash widths [degree].
GRID_F_E: tuple[float, ...] = (10.0, 20.0, 30.0, 50.0, 80.0, 120.0)
GRID_BACKLASH_DEG: tuple[float, ...] = (0.0, 0.2, 0.5)

#: ``som``: our identifier (maps + model-based refinement); ``maps``: the maps' answer alone (the
#: paper's method); ``iv4``: the instrumental-variable baseline.
METHODS: tuple[str, ...] = ("som", "maps", "iv4")
#: Recognition tolerances reported [%].
TOLERANCES: tuple[int, ...] = (30, 50)
#: Parameters with relative error statistics (``backlash`` only over systems with backlash).
RELATIVE_PARAMS: tuple[str, ...] = ("J_sigma", "V_J", "f_e", "d", "backlash")
#: Parameters with absolute error statistics (true value may be 0): ``M_FC`` [Nm], ``mu_F`` [Nm s/rad].
ABSOLUTE_PARAMS: tuple[str, ...] = ("M_FC", "mu_F")
#: Estimates each method delivers (the rest are reported as not available).
METHOD_PARAMS: dict[str, tuple[str, ...]] = {
    "som": ("J_sigma", "V_J", "f_e", "d", "backlash", "M_FC", "mu_F"),
    "maps": ("J_sigma", "V_J", "f_e", "d", "backlash", "M_FC", "mu_F"),
    "iv4": ("J_sigma", "V_J", "f_e", "d"),
}
#: Predicted-class labels of the confusion matrix: the four classes plus a failed analysis.
PREDICTED_LABELS: tuple[str, ...] = STRUCTURE_CLASSES + ("failed",)

#: Bump when the per-system result format or the way a method is run changes (invalidates caches).
CACHE_VERSION = "twomass-eval-v1"

TRUTH_KEYS: tuple[str, ...] = ("J_sigma", "V_J", "f_e", "d", "backlash", "M_FC", "mu_F", "C_F", "s_N", "r_osc",
                               "w_e_T_Ei", "structure")


# ----------------------------------------------------------------------------- sets


@dataclass(frozen=True)
class EvalSet:
    """Definition of one evaluation set; equal definitions give equal systems and records.

    ``kind``: ``"grid"`` (``per_cell`` systems per ``f_e`` [Hz] x ``backlash_deg`` [degree]
    cell, cells in ``f_e``-major order) or ``"population"`` (``n`` systems of ``ranges``).
    ``seed`` seeds the population draw; the current noise of record ``i`` uses
    ``noise_seed + i`` (``sim.iter_records``).
    """

    name: str
    kind: str
    seed: int
    n: int = 0
    per_cell: int = 0
    f_e: tuple[float, ...] = ()
    backlash_deg: tuple[float, ...] = ()
    ranges: PopulationRanges = field(default_factory=PopulationRanges)

    def __post_init__(self) -> None:
        if self.kind not in ("grid", "population"):
            raise ValueError(f"EvalSet.kind: expected 'grid' or 'population', received {self.kind!r}")
        if self.kind == "grid":
            if self.per_cell < 1 or not self.f_e or not self.backlash_deg:
                raise ValueError(f"EvalSet {self.name}: expected per_cell >= 1 and non-empty f_e, backlash_deg; "
                                 f"received {self.per_cell}, {self.f_e}, {self.backlash_deg}")
            if min(self.f_e) <= 0 or min(self.backlash_deg) < 0:
                raise ValueError(f"EvalSet {self.name}: expected f_e > 0 Hz and backlash >= 0 degree, "
                                 f"received {self.f_e}, {self.backlash_deg}")
        elif self.n < 1:
            raise ValueError(f"EvalSet {self.name}: expected n >= 1, received {self.n}")

    @property
    def size(self) -> int:
        """Number of systems."""
        return self.per_cell * len(self.f_e) * len(self.backlash_deg) if self.kind == "grid" else self.n

    @property
    def noise_seed(self) -> int:
        return self.seed * 1_000_003 + 17

    def cells(self) -> list[tuple[float, float]]:
        """Grid cells ``(f_e [Hz], backlash [degree])`` in ``f_e``-major order; ``[]`` for a population."""
        return [(f, b) for f in self.f_e for b in self.backlash_deg] if self.kind == "grid" else []

    def params(self) -> TwoMassParams:
        """The systems, batch shape ``(size,)``; for a grid, systems ``k*per_cell .. (k+1)*per_cell - 1``
        form cell ``k``, with ``f_e`` and ``backlash`` fixed and the rest drawn from ``ranges``."""
        p = sample_population(self.size, self.seed, self.ranges)
        if self.kind == "population":
            return p
        cells = self.cells()
        f_e = torch.tensor([c[0] for c in cells for _ in range(self.per_cell)], dtype=torch.float64)
        bl = torch.deg2rad(torch.tensor([c[1] for c in cells for _ in range(self.per_cell)], dtype=torch.float64))
        return TwoMassParams(J_sigma=p.J_sigma, V_J=p.V_J, f_e=f_e, d=p.d, backlash=bl, M_FC=p.M_FC, mu_F=p.mu_F)

    def cell_of(self, i: int) -> tuple[float, float] | None:
        return self.cells()[i // self.per_cell] if self.kind == "grid" else None

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["f_e"], d["backlash_deg"] = list(self.f_e), list(self.backlash_deg)
        d["ranges"] = {k: list(v) if isinstance(v, tuple) else v for k, v in d["ranges"].items()}
        return d


def grid_set(per_cell: int = 20, seed: int = 5, *, f_e: Sequence[float] = GRID_F_E,
             backlash_deg: Sequence[float] = GRID_BACKLASH_DEG, ranges: PopulationRanges | None = None) -> EvalSet:
    """The paper's grid: ``len(f_e) * len(backlash_deg)`` cells of ``per_cell`` systems."""
    return EvalSet(name="grid", kind="grid", seed=seed, per_cell=per_cell, f_e=tuple(float(f) for f in f_e),
                   backlash_deg=tuple(float(b) for b in backlash_deg), ranges=ranges or PopulationRanges())


def population_set(n: int = 1000, seed: int = 6, ranges: PopulationRanges | None = None) -> EvalSet:
    """``n`` systems drawn from the (default) population."""
    return EvalSet(name="population", kind="population", seed=seed, n=n, ranges=ranges or PopulationRanges())


# ----------------------------------------------------------------------------- per record


_IDENTIFIERS: dict[tuple[str, bool], Any] = {}


def _identifier(checkpoints: str, refine: bool = True) -> Any:
    """The loaded maps of ``checkpoints`` (with or without the refinement), once per process."""
    if (checkpoints, refine) not in _IDENTIFIERS:
        from training.identification._identifier import Identifier
        from training.identification._refine import RefineConfig

        _IDENTIFIERS[checkpoints, refine] = Identifier.load(checkpoints, refine=RefineConfig() if refine else None)
    return _IDENTIFIERS[checkpoints, refine]


def _num(x: Any) -> float | None:
    """A finite float, else ``None`` (JSON-able)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0] if text else ''}".rstrip(": ")


def som_result(record: Any, checkpoints: str, refine: bool = True) -> dict[str, Any]:
    """SOM identification of one record (``refine=False``: the maps' answer alone), reduced to
    what the evaluation needs (JSON-able).

    Keys: ``structure`` (class name or ``None``), ``J_sigma``, ``V_J``, ``f_e`` [Hz], ``d``,
    ``backlash`` [rad], ``M_FC`` [Nm], ``mu_F`` [Nm s/rad] (``None`` where not identified),
    ``osc_quanta``, ``outside_training``, ``n_warnings`` and ``error`` (one line or ``None``).
    Any exception of the analysis is caught and reported as ``error`` (it is a miss).
    """
    out: dict[str, Any] = dict.fromkeys(METHOD_PARAMS["som"])
    out.update(structure=None, osc_quanta=None, outside_training=None, n_warnings=0, error=None)
    try:
        res = _identifier(checkpoints, refine).identify_records([record])[0]
    except Exception as err:  # noqa: BLE001 - one bad record must not end a long run; it is reported
        out["error"] = _one_line(err)
        return out
    if "error" in res:
        out["error"] = str(res["error"])
        return out
    out["structure"] = res["structure"]
    out.update({k: _num(res["parameters"].get(k)) for k in METHOD_PARAMS["som"]})
    q = res.get("quality", {})
    out.update(osc_quanta=_num(q.get("osc_quanta")), outside_training=bool(q.get("outside_training", False)),
               n_warnings=len(res.get("warnings", [])))
    return out


def iv4_result(record: Any) -> dict[str, Any]:
    """IV4 (``training.evaluation._iv4.identify_iv4`` with its defaults) on one record (JSON-able).

    Keys: ``J_sigma``, ``V_J``, ``f_e`` [Hz], ``d`` (``None`` where NaN), ``valid``, ``reason``,
    ``converged``, ``iterations``. Input: ``K_M * current`` (or ``torque``) and the measured speed.
    """
    from training.evaluation._iv4 import identify_iv4

    out: dict[str, Any] = dict.fromkeys(METHOD_PARAMS["iv4"])
    out.update(valid=False, reason="", converged=False, iterations=0)
    try:
        torque = record.torque if getattr(record, "torque", None) is not None else \
            np.asarray(record.current, dtype=np.float64) * float(record.meta["K_M"])
        res = identify_iv4(torque, record.speed, float(record.meta["T_s"]), T_Ei=float(record.meta["T_Ei"]))
    except Exception as err:  # noqa: BLE001 - reported as an invalid result (a miss)
        out["reason"] = _one_line(err)
        return out
    out.update({k: _num(res.get(k)) for k in METHOD_PARAMS["iv4"]})
    out.update(valid=bool(res.get("valid", False)), reason=str(res.get("reason", "")),
               converged=bool(res.get("converged", False)), iterations=int(res.get("iterations", 0)))
    return out


def _process(record: Any, checkpoints: str, methods: tuple[str, ...]) -> tuple[int, dict[str, dict[str, Any]]]:
    """Worker job: ``(system index, {method: result})`` for one record."""
    index = int(record.name[3:])
    out: dict[str, dict[str, Any]] = {}
    if "som" in methods:
        out["som"] = som_result(record, checkpoints)
    if "maps" in methods:
        out["maps"] = som_result(record, checkpoints, refine=False)
    if "iv4" in methods:
        out["iv4"] = iv4_result(record)
    return index, out


def _imap_bounded(pool: Executor, fn: Callable[[Any], Any], items: Iterable[Any], limit: int) -> Iterator[Any]:
    """``fn`` over ``items`` in ``pool``, results in completion order, at most ``limit`` in flight
    (the records are simulated lazily, so memory stays bounded)."""
    pending: set[Future[Any]] = set()
    for item in items:
        pending.add(pool.submit(fn, item))
        if len(pending) >= limit:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for f in done:
                yield f.result()
    while pending:
        done, pending = wait(pending, return_when=FIRST_COMPLETED)
        for f in done:
            yield f.result()


# ----------------------------------------------------------------------------- cache


def checkpoints_digest(checkpoints: str | os.PathLike[str]) -> str:
    """SHA-256 of the maps' ``manifest.json`` (which holds each map file's SHA-256)."""
    path = Path(checkpoints) / "manifest.json"
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except FileNotFoundError:
        raise UserError(f"{path}: not found; expected a checkpoint folder with a manifest") from None


#: Top-level packages whose source enters :func:`source_digest`.
_OWN_PACKAGES = ("sim", "training", "som_torch")
#: Modules a method's results depend on (their import closure within :data:`_OWN_PACKAGES` is hashed).
METHOD_ROOTS: dict[str, tuple[str, ...]] = {"som": ("sim", "training.identification._identifier"), "maps": ("sim", "training.identification._identifier"),
                                             "iv4": ("sim", "training.evaluation._iv4")}


def _module_file(name: str) -> Path | None:
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, AttributeError, ValueError):  # e.g. a function imported from a module
        return None
    return Path(spec.origin) if spec is not None and spec.origin and spec.origin.endswith(".py") else None


def source_digest(roots: Sequence[str]) -> str:
    """SHA-256 over the source files of ``roots`` and of everything they import from this project
    (static walk of ``import`` statements; plus each package's ``*.c`` sources), so that a code change in the simulator, the analysis or
    a method invalidates cached results even when no version constant was bumped."""
    seen: dict[str, Path] = {}
    todo = list(roots)
    while todo:
        name = todo.pop()
        if name in seen or name.split(".")[0] not in _OWN_PACKAGES:
            continue
        path = _module_file(name)
        if path is None:
            continue
        seen[name] = path
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                todo += [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")
                    base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
                todo.append(base)
                todo += [f"{base}.{a.name}" for a in node.names]  # submodules; non-modules are skipped
    files = {name: path for name, path in seen.items()}
    for name, path in seen.items():
        if path.name == "__init__.py":  # native sources of a package (the simulator's C kernel)
            files.update({f"{name}/{c.name}": c for c in path.parent.glob("*.c")})
    h = hashlib.sha256()
    for name in sorted(files):
        h.update(name.encode() + b"\0" + files[name].read_bytes())
    return h.hexdigest()


def method_config(method: str, eval_set: EvalSet, drive: DriveConfig, signal: TestSignalConfig,
                  checkpoints: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """Everything the per-system results of ``method`` on ``eval_set`` depend on (JSON-able)."""
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, received {method!r}")
    cfg: dict[str, Any] = {"cache_version": CACHE_VERSION, "method": method, "set": eval_set.to_dict(),
                           "drive": asdict(drive), "signal": asdict(signal),
                           "source_sha256": source_digest(METHOD_ROOTS[method])}
    if method in ("som", "maps"):
        from training.identification._analysis import FEATURE_VERSION

        if checkpoints is None:
            raise ValueError(f"method_config: expected a checkpoint folder for method {method!r}, received None")
        cfg.update(feature_version=FEATURE_VERSION, checkpoints_manifest_sha256=checkpoints_digest(checkpoints))
    else:
        cfg.update(iv4="identify_iv4 defaults (speed_is_mean, friction, max_iter=10), T_Ei from the record")
    return cfg


def _cache_path(cache_dir: Path, cfg: Mapping[str, Any]) -> Path:
    key = hashlib.sha256(json.dumps(cfg, sort_keys=True).encode()).hexdigest()[:20]
    return cache_dir / f"{cfg['set']['name']}_{cfg['method']}_{key}.json"


def load_cached(cache_dir: Path, cfg: Mapping[str, Any], n: int) -> tuple[list[dict[str, Any]], dict[str, Any]] | None:
    """``(results, meta)``: the cached per-system results of ``cfg`` (``n`` of them) and how they
    were computed (``compute_s``, ``workers``, ``loadavg``; see :func:`save_cached`), or ``None``.

    Raises:
        UserError: the file under this key holds another config or another number of systems.
    """
    path = _cache_path(cache_dir, cfg)
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise UserError(f"{path}: unreadable cache file ({err}); remove it") from None
    if data.get("config") != json.loads(json.dumps(cfg)) or len(data.get("results", [])) != n:
        raise UserError(f"{path}: cache of another config or size (expected {n} results); remove it or use another --cache")
    return list(data["results"]), dict(data.get("meta", {}))


def save_cached(cache_dir: Path, cfg: Mapping[str, Any], results: Sequence[Mapping[str, Any]],
                meta: Mapping[str, Any] | None = None) -> Path:
    """Write the results of ``cfg`` and ``meta`` (JSON-able notes, e.g. the compute time) atomically
    (temporary file, then rename)."""
    cache_dir.mkdir(parents=True, exist_ok=True)
    path = _cache_path(cache_dir, cfg)
    fd, tmp = tempfile.mkstemp(dir=cache_dir, suffix=".tmp.json")
    try:
        with os.fdopen(fd, "w") as fh:
            json.dump({"config": cfg, "meta": dict(meta or {}), "results": list(results)}, fh)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


# ----------------------------------------------------------------------------- runs


def truth_rows(eval_set: EvalSet, drive: DriveConfig, signal: TestSignalConfig) -> list[dict[str, Any]]:
    """Per system: ``set``, ``index``, ``cell_f_e``/``cell_backlash_deg`` (grid) and ``truth``
    (:data:`TRUTH_KEYS`; ``backlash`` [rad], ``structure`` a class name)."""
    truths = eval_set.params().truth(drive, signal.M_star)
    rows = []
    for i, t in enumerate(truths):
        cell = eval_set.cell_of(i)
        t = dict(t, w_e_T_Ei=t["w_e"] * drive.T_Ei)
        rows.append({"set": eval_set.name, "index": i, "cell_f_e": cell[0] if cell else None,
                     "cell_backlash_deg": cell[1] if cell else None,
                     "truth": {k: t[k] for k in TRUTH_KEYS}})
    return rows


def run_set(eval_set: EvalSet, *, methods: Sequence[str] = METHODS, drive: DriveConfig | None = None,
            signal: TestSignalConfig | None = None, checkpoints: str | os.PathLike[str] | None = None,
            cache_dir: str | os.PathLike[str] | None = None, workers: int = 2,
            progress: Callable[[int], None] | None = None) -> tuple[list[dict[str, Any]], dict[str, dict[str, Any]]]:
    """Simulate ``eval_set`` once and run every method of ``methods`` on the same records.

    Args:
        methods: subset of :data:`METHODS`.
        checkpoints: map folder for the SOM (default: the shipped ``checkpoints/``).
        cache_dir: folder for per-method result caches (``None``: no cache).
        workers: processes of the spawn pool (1 BLAS thread each); ``0`` runs in this process
            (slow unless ``OPENBLAS_NUM_THREADS=1`` was set before numpy was imported).
        progress: called with the number of systems finished since the last call.

    Returns:
        ``(rows, info)``: one row per system (see :func:`truth_rows`, plus one key per method)
        and, per method, ``cached`` (bool) and how its results were computed: ``compute_s``
        (wall time of simulation + all methods computed together), ``workers``, ``loadavg``
        (1-minute load average before and after; the machine may be shared).
    """
    from training.learning._dataset import _worker_pool
    from training.identification._identifier import DEFAULT_CHECKPOINTS

    if not methods or any(m not in METHODS for m in methods):
        raise ValueError(f"methods: expected a non-empty subset of {METHODS}, received {list(methods)}")
    methods = tuple(m for m in METHODS if m in methods)
    if workers < 0:
        raise ValueError(f"workers: expected >= 0, received {workers}")
    drive = drive or DriveConfig()
    signal = signal or TestSignalConfig()
    ckpt = str(Path(checkpoints) if checkpoints is not None else DEFAULT_CHECKPOINTS)
    n = eval_set.size
    cfgs = {m: method_config(m, eval_set, drive, signal, ckpt) for m in methods}
    if "som" in methods or "maps" in methods:
        _identifier(ckpt)  # fail fast (one line) on maps that do not fit this toolkit, cached or not
    cache = Path(cache_dir) if cache_dir is not None else None
    results: dict[str, list[Any]] = {}
    info: dict[str, dict[str, Any]] = {}
    for m in methods:
        hit = load_cached(cache, cfgs[m], n) if cache is not None else None
        if hit is not None:
            results[m] = hit[0]
            info[m] = {"cached": True, **hit[1]}
    todo = tuple(m for m in methods if m not in results)
    if todo:
        t0, load0 = time.perf_counter(), _loadavg()
        fresh: dict[str, list[Any]] = {m: [None] * n for m in todo}
        records = iter_records(eval_set.params(), drive, signal, seed=eval_set.noise_seed, group=64)
        job = partial(_process, checkpoints=ckpt, methods=todo)
        if workers == 0:
            for index, res in map(job, records):
                for m in todo:
                    fresh[m][index] = res[m]
                if progress:
                    progress(1)
        else:
            with _worker_pool(workers) as pool:
                for index, res in _imap_bounded(pool, job, records, 4 * workers):
                    for m in todo:
                        fresh[m][index] = res[m]
                    if progress:
                        progress(1)
        missing = [m for m in todo if any(r is None for r in fresh[m])]
        if missing:
            raise RuntimeError(f"run_set: expected {n} results per method, some missing for {missing}")
        meta = {"compute_s": time.perf_counter() - t0, "workers": workers, "methods_together": list(todo),
                "loadavg": [load0, _loadavg()], "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
        for m in todo:
            results[m] = fresh[m]
            info[m] = {"cached": False, **meta}
            if cache is not None:
                save_cached(cache, cfgs[m], fresh[m], meta)
    elif progress:
        progress(n)
    rows = truth_rows(eval_set, drive, signal)
    for m in methods:
        for row, res in zip(rows, results[m]):
            row[m] = res
    return rows, {m: info[m] for m in methods}


def _loadavg() -> float | None:
    try:
        return round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):
        return None


# ----------------------------------------------------------------------------- aggregation


def _column(rows: Sequence[Mapping[str, Any]], part: str, key: str) -> np.ndarray:
    """``rows[i][part][key]`` as float ``N`` (``None`` -> NaN)."""
    return np.array([np.nan if r[part].get(key) is None else float(r[part][key]) for r in rows], dtype=float)


def estimates(rows: Sequence[Mapping[str, Any]], method: str, key: str) -> np.ndarray:
    """Estimates of ``key`` by ``method`` (``N``); NaN where missing, for IV4 also where ``valid`` is False."""
    est = _column(rows, method, key)
    if method == "iv4":
        valid = np.array([bool(r["iv4"].get("valid")) for r in rows], dtype=bool)
        est[~valid] = np.nan
    return est


def relative_errors(rows: Sequence[Mapping[str, Any]], method: str,
                    params: Sequence[str] = metrics.RECOGNITION_PARAMS) -> dict[str, np.ndarray]:
    """Absolute relative errors ``|estimate - truth|/|truth|`` per parameter (``N``, NaN = missing;
    ``metrics.relative_error``)."""
    out = {}
    for p in params:
        truth = _column(rows, "truth", p)
        with np.errstate(divide="ignore", invalid="ignore"):
            out[p] = metrics.relative_error(estimates(rows, method, p), truth)
    return out


def recognition(rows: Sequence[Mapping[str, Any]], method: str, x_percent: float) -> float:
    """``E_x`` [%] of ``method`` over ``rows`` (``metrics.recognition_rate`` of the absolute relative
    errors; NaN for no rows)."""
    if not rows:
        return float("nan")
    return metrics.recognition_rate(relative_errors(rows, method), x_percent)


def _rates(rows: Sequence[Mapping[str, Any]], methods: Sequence[str]) -> dict[str, dict[str, float | None]]:
    return {m: {f"E_{x}": _num(recognition(rows, m, x)) for x in TOLERANCES} for m in methods}


def parameter_stats(rows: Sequence[Mapping[str, Any]], method: str) -> dict[str, dict[str, Any]]:
    """Per parameter: ``kind`` (relative/absolute), ``n`` (systems with an estimate), ``n_missing``,
    ``mean``, ``std`` (signed error), ``median_abs``, and for relative errors ``within_30``/``within_50``
    (% of the systems in scope within that error, missing counted outside); parameters ``method``
    does not estimate are omitted.
    ``backlash`` is scored only over systems with backlash whose estimate is a backlash class."""
    out: dict[str, dict[str, Any]] = {}
    for p in RELATIVE_PARAMS + ABSOLUTE_PARAMS:
        if p not in METHOD_PARAMS[method]:
            continue
        truth = _column(rows, "truth", p)
        est = estimates(rows, method, p)
        if p in RELATIVE_PARAMS:
            scope = truth > 0
            with np.errstate(divide="ignore", invalid="ignore"):
                err = (est - truth) / truth
        else:
            scope = np.ones_like(truth, dtype=bool)
            err = est - truth
        if p == "backlash":
            err = np.where(est > 0, err, np.nan)  # 0 = "no backlash class": counted as missing
        e = err[scope]
        ok = e[np.isfinite(e)]
        out[p] = {"kind": "relative" if p in RELATIVE_PARAMS else "absolute", "n": int(ok.size),
                  "n_missing": int(e.size - ok.size), "mean": _num(ok.mean()) if ok.size else None,
                  "std": _num(ok.std()) if ok.size else None,
                  "median_abs": _num(np.median(np.abs(ok))) if ok.size else None}
        if p in RELATIVE_PARAMS:  # share of the systems in scope within x % (missing = outside) [%]
            for x in TOLERANCES:
                out[p][f"within_{x}"] = _num(100.0 * np.mean(np.nan_to_num(np.abs(e), nan=np.inf) <= x / 100.0)) \
                    if e.size else None
    return out


def structure_confusion(rows: Sequence[Mapping[str, Any]]) -> np.ndarray:
    """SOM structure confusion (``4 x 5``): rows = true class of :data:`STRUCTURE_CLASSES`,
    columns = predicted class or ``failed`` (:data:`PREDICTED_LABELS`)."""
    truth = np.array([STRUCTURE_CLASSES.index(r["truth"]["structure"]) for r in rows], dtype=int)
    pred = np.array([PREDICTED_LABELS.index(r["som"]["structure"] or "failed") for r in rows], dtype=int)
    return metrics.confusion_matrix(truth, pred, len(PREDICTED_LABELS))[: len(STRUCTURE_CLASSES)]


def _failures(rows: Sequence[Mapping[str, Any]], methods: Sequence[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for m in ("som", "maps"):
        if m in methods:
            errs = [r[m]["error"] for r in rows if r[m].get("error")]
            out[m] = {"n_error": len(errs), "examples": sorted(set(errs))[:3],
                      "n_stiff_no_f_e": sum(1 for r in rows if r[m]["structure"] == "stiff")}
    if "iv4" in methods:
        bad = [r["iv4"]["reason"] for r in rows if not r["iv4"].get("valid")]
        out["iv4"] = {"n_invalid": len(bad), "examples": sorted(set(bad))[:3]}
    return out


def summarize_set(rows: Sequence[Mapping[str, Any]], methods: Sequence[str],
                  eval_set: EvalSet | None = None) -> dict[str, Any]:
    """All tables of one set (JSON-able). Cells and per-backlash means when ``eval_set`` is a grid."""
    methods = [m for m in METHODS if m in methods]
    r_osc = _column(rows, "truth", "r_osc")
    out: dict[str, Any] = {"n": len(rows), "r_osc_below_1": int(np.sum(r_osc < 1.0)),
                           "overall": _rates(rows, methods), "per_class": [], "parameters": {},
                           "failures": _failures(rows, methods)}
    for c in STRUCTURE_CLASSES:
        sub = [r for r in rows if r["truth"]["structure"] == c]
        out["per_class"].append({"class": c, "n": len(sub), **_rates(sub, methods)})
    for m in methods:
        out["parameters"][m] = parameter_stats(rows, m)
    if "som" in methods:
        out["confusion"] = {"true": list(STRUCTURE_CLASSES), "predicted": list(PREDICTED_LABELS),
                            "matrix": structure_confusion(rows).tolist()}
    if eval_set is not None and eval_set.kind == "grid":
        cells = []
        for f_e, bl in eval_set.cells():
            sub = [r for r in rows if r["cell_f_e"] == f_e and r["cell_backlash_deg"] == bl]
            s_N = _column(sub, "truth", "s_N")
            classes = {c: sum(1 for r in sub if r["truth"]["structure"] == c) for c in STRUCTURE_CLASSES}
            cells.append({"f_e": f_e, "backlash_deg": bl, "n": len(sub),
                          "s_N_median": _num(np.median(s_N)) if sub else None,
                          "s_N_above_1": _num(np.mean(s_N > 1.0)) if sub else None,
                          "r_osc_below_1": int(np.sum(_column(sub, "truth", "r_osc") < 1.0)),
                          "classes": classes, **_rates(sub, methods)})
        out["cells"] = cells
        out["backlash_means"] = [{"backlash_deg": bl, **_rates([r for r in rows if r["cell_backlash_deg"] == bl], methods)}
                                 for bl in eval_set.backlash_deg]
    return out


def acceptance_checks(grid: Mapping[str, Any], methods: Sequence[str]) -> list[dict[str, Any]]:
    """The issue's targets on the grid summary: SOM ``E_30 >= 95 %`` in every cell with backlash
    <= 0.2 degree and ``f_e`` <= 80 Hz; SOM ``E_30`` above IV4's in every cell where most
    systems have ``s_N > 1``. Each check: ``name``, ``passed`` (``None``: not applicable), ``detail``."""
    cells = grid.get("cells", [])
    checks = []
    if "som" in methods:
        scope = [c for c in cells if c["backlash_deg"] <= 0.2 and c["f_e"] <= 80.0]
        fail = [c for c in scope if (c["som"]["E_30"] or 0.0) < 95.0]
        checks.append({"name": "SOM E_30 >= 95 % where backlash <= 0.2 degree and f_e <= 80 Hz",
                       "passed": (not fail) if scope else None,
                       "detail": f"{len(scope) - len(fail)} of {len(scope)} cells pass" + (
                           "; failing: " + ", ".join(f"{c['f_e']:g} Hz/{c['backlash_deg']:g} deg "
                                                     f"({c['som']['E_30']:.0f} %)" for c in fail) if fail else "")})
    if "som" in methods and "iv4" in methods:
        scope = [c for c in cells if (c["s_N_above_1"] or 0.0) > 0.5]
        fail = [c for c in scope if not ((c["som"]["E_30"] or 0.0) > (c["iv4"]["E_30"] or 0.0))]
        checks.append({"name": "SOM E_30 > IV4 E_30 where most systems have s_N > 1",
                       "passed": (not fail) if scope else None,
                       "detail": f"{len(scope) - len(fail)} of {len(scope)} cells pass" + (
                           "; failing: " + ", ".join(f"{c['f_e']:g} Hz/{c['backlash_deg']:g} deg "
                                                     f"(SOM {c['som']['E_30']:.0f} vs IV4 {c['iv4']['E_30']:.0f} %)"
                                                     for c in fail) if fail else "")})
    return checks


def identification_checks(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Issue 4's targets on a random population set (SOM identifier, SPEC default population):
    structure accuracy >= 95 % over systems at least 20 % away from every class threshold;
    over ``elastic`` and ``elastic_backlash``: ``E_30 >= 95 %`` and ``E_50 >= 99 %``; ``J_sigma``
    within 5 % for >= 95 %; backlash width within 30 % for >= 90 % of systems with ``s_N >= 0.3``;
    Coulomb friction within 0.05 Nm for >= 90 %. Each check: ``name``, ``passed``, ``detail``."""
    if not rows:
        return []
    truth = {k: _column(rows, "truth", k) for k in ("w_e_T_Ei", "s_N", "r_osc", "backlash", "M_FC")}
    far = metrics.threshold_margin({k: truth[k] for k in ("w_e_T_Ei", "s_N", "r_osc")}) >= 0.2
    correct = np.array([r["som"]["structure"] == r["truth"]["structure"] for r in rows])
    elastic = np.array([r["truth"]["structure"] in ("elastic", "elastic_backlash") for r in rows])
    err = relative_errors(rows, "som")
    e30 = float(100 * metrics.recognized({k: v[elastic] for k, v in err.items()}, 30).mean()) if elastic.any() else float("nan")
    e50 = float(100 * metrics.recognized({k: v[elastic] for k, v in err.items()}, 50).mean()) if elastic.any() else float("nan")
    j5 = float(100 * np.mean(np.nan_to_num(err["J_sigma"], nan=np.inf) <= 0.05))
    wide = truth["s_N"] >= 0.3
    bl_err = metrics.relative_error(estimates(rows, "som", "backlash")[wide], truth["backlash"][wide])
    bl30 = float(100 * np.mean(np.nan_to_num(bl_err, nan=np.inf) <= 0.3)) if wide.any() else float("nan")
    fc = float(100 * np.mean(np.nan_to_num(np.abs(estimates(rows, "som", "M_FC") - truth["M_FC"]), nan=np.inf) <= 0.05))
    acc = float(100 * correct[far].mean()) if far.any() else float("nan")
    figures = [
        (f"structure accuracy >= 95 % (systems >= 20 % from every threshold, n={int(far.sum())})", acc, 95.0),
        (f"E_30 >= 95 % over elastic + elastic_backlash (n={int(elastic.sum())})", e30, 95.0),
        (f"E_50 >= 99 % over elastic + elastic_backlash (n={int(elastic.sum())})", e50, 99.0),
        (f"J_sigma within 5 % for >= 95 % (n={len(rows)})", j5, 95.0),
        (f"backlash within 30 % for >= 90 % of s_N >= 0.3 (n={int(wide.sum())})", bl30, 90.0),
        (f"M_FC within 0.05 Nm for >= 90 % (n={len(rows)})", fc, 90.0),
    ]
    return [{"name": name, "passed": bool(value >= target), "detail": f"measured {value:.1f} %"}
            for name, value, target in figures]


def summarize(rows_by_set: Mapping[str, Sequence[Mapping[str, Any]]], sets: Mapping[str, EvalSet],
              methods: Sequence[str]) -> dict[str, Any]:
    """Summaries of all sets plus the acceptance checks (on the set named ``grid``, if any)."""
    out: dict[str, Any] = {"methods": [m for m in METHODS if m in methods], "sets": {}}
    for name, rows in rows_by_set.items():
        out["sets"][name] = summarize_set(rows, methods, sets.get(name))
    out["checks"] = acceptance_checks(out["sets"]["grid"], methods) if "grid" in out["sets"] else []
    if "som" in methods and "population" in rows_by_set:
        out["checks"] += identification_checks(rows_by_set["population"])
    return out
