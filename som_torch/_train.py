"""Training: the paper's online rule (eq. 3, masked best match eq. 2) and batch SOM."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Union

import torch

from . import _native
from ._init import initialize, map_seeds
from ._options import NEIGHBOURHOODS, SCHEDULES, lookup
from ._som import SOM

Hook = Callable[[int, SOM, dict], None]
"""``hook(epoch, som, info)`` after each epoch; ``info``: ``step``, ``epochs``,
``learning_rate`` and ``sigma`` (float64 ``*batch``, the values used last)."""
Value = Union[float, torch.Tensor]
Range = Union[Value, tuple[Value, Value], list[Value]]


def _start_end(value: Range | None, default: tuple[float, float], batch: torch.Size, name: str,
               schedule: str | Callable) -> tuple[torch.Tensor, torch.Tensor]:
    """``value`` -> the schedule's start and end, two float64 ``B`` tensors.

    ``value``: ``start`` or ``(start, end)``, a tuple or a 2-element list (e.g. from JSON); each a
    number or a ``*batch`` tensor/array. Per-map values only as tensors or arrays: a bare list is
    always ``(start, end)``, never one value per map. The start must be finite and > 0; the end
    finite and >= 0 (a linear decay may end at 0), and > 0 for ``"exponential"`` (no geometric
    decay reaches 0); ``"asymptotic"`` and ``"constant"`` ignore the end but check it too."""
    if value is None:
        value = default
    if isinstance(value, (tuple, list)):
        if len(value) != 2:
            raise ValueError(f"{name}: expected start or (start, end), per-map values as a *batch tensor, received {value!r}")
        start, end = value
    else:
        start, end = value, default[1]
    out = []
    for v, what in ((start, "start"), (end, "end")):
        try:
            t = torch.as_tensor(v, dtype=torch.float64)
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(f"{name} {what}: expected a number or a *batch tensor, received {v!r}") from None
        try:
            out.append(t.expand(batch).reshape(-1))  # B
        except RuntimeError:
            raise ValueError(f"{name} {what}: expected a float or *batch = {tuple(batch)}, received shape {tuple(t.shape)}") from None
    first, last = out
    if not bool((torch.isfinite(first) & (first > 0)).all()):
        raise ValueError(f"{name}: expected a finite positive start value, received {start!r}")
    strict = schedule == "exponential"
    if not bool((torch.isfinite(last) & ((last > 0) if strict else (last >= 0))).all()):
        raise ValueError(f"{name}: expected a finite end value {'> 0' if strict else '>= 0'} "
                         f"(schedule {schedule!r}), received {end!r}")
    return first, last


def _threads(num_threads: int | None) -> int | None:
    """``num_threads`` checked: a positive int or None."""
    if num_threads is not None and (not isinstance(num_threads, int) or isinstance(num_threads, bool) or num_threads < 1):
        raise ValueError(f"num_threads: expected a positive int or None, received {num_threads!r}")
    return num_threads


def _table(schedule: Callable, start: torch.Tensor, end: torch.Tensor, steps: torch.Tensor, total: int) -> torch.Tensor:
    """Values of the schedule function (resolved by ``lookup``), float64 ``len(steps) x B``."""
    return schedule(start, end, steps.to(torch.float64)[:, None], total)


def _progress(enabled: bool, total: int, desc: str):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="step", leave=False)


def _orders(gens: list[torch.Generator], n: int, shuffle: bool) -> torch.Tensor:
    """Sample order of one epoch, long ``N x B``."""
    if not shuffle:
        return torch.arange(n)[:, None].expand(n, len(gens))
    return torch.stack([torch.randperm(n, generator=g) for g in gens], dim=1)


def train_online(
    som: SOM,
    data: torch.Tensor,
    *,
    epochs: int = 10,
    learning_rate: Range = (0.5, 0.01),
    sigma: Range | None = None,
    schedule: str = "asymptotic",
    neighbourhood: str = "gaussian",
    seed: int | Sequence[int] | torch.Tensor = 0,
    shuffle: bool = True,
    method: str = "fast",
    refresh_every: int = 256,
    num_threads: int | None = 1,
    progress: bool = False,
    hooks: Iterable[Hook] = (),
) -> SOM:
    """Train in place with the online rule, one sample per step, all maps of the batch at once.

    Step ``t`` (global, ``0 .. epochs*N - 1``), for each map: best match ``c`` over the active,
    non-NaN components (eq. 2); then every component of every unit moves,
    ``w_u += lr(t) * h(|r_u - r_c|^2, sigma(t)) * (x - w_u)`` (eq. 3; NaN components of ``x``
    stay put). Each epoch visits each sample once, in a random order per map drawn from a
    generator seeded with the map's seed (``shuffle=False``: in order).

    Args:
        som: weights ``*batch x U x C`` (initialize first; see :func:`fit`).
        data: raw ``N x C`` (shared) or ``*batch x N x C`` (per map); inactive columns carry
            the parameters; NaN = missing.
        learning_rate, sigma: ``start`` or ``(start, end)`` (a tuple or a 2-element list), each a
            float or a ``*batch`` tensor (per-map schedules; a list is never read per map).
            Start > 0; end >= 0 (> 0 for ``"exponential"``), see :func:`_start_end`.
            ``sigma`` (grid radius) defaults to ``(max(rows, cols)/2, 1)``.
        schedule: one of :data:`SCHEDULES` (default ``"asymptotic"``: MiniSom's default decay).
        neighbourhood: one of :data:`NEIGHBOURHOODS`.
        seed: int (maps get ``seed, seed+1, ...``) or ``*batch`` seeds.
        method: ``"fast"`` = ``"native"`` where the C kernel is available and the maps are on
            the CPU (see ``_native``: one call per epoch, weights' dtype), else ``"torch"`` (one
            batched tensor step per sample, weights' dtype and device (e.g. CUDA: ``som.to``),
            incremental norms refreshed every ``refresh_every`` steps);
            ``"reference"``: float64, one map and one sample at a time, plain formulas.
        num_threads: torch intra-op threads during the epochs (restored afterwards); the
            per-step tensors are small, so 1 is fastest on a shared CPU; ``None`` leaves it.
            The native kernel has its own threads, one map per thread
            (``SOM_TORCH_THREADS``, see :mod:`som_torch._config`).
        hooks: called after each epoch as ``hook(epoch, som, info)``.
    """
    if not isinstance(epochs, int) or epochs < 1:
        raise ValueError(f"epochs: expected a positive int, received {epochs!r}")
    nb = lookup(NEIGHBOURHOODS, neighbourhood, "neighbourhood")
    native_ok = (method in ("fast", "native") and isinstance(neighbourhood, str) and som.device.type == "cpu"
                 and _native.kernel(som.weights.dtype) is not None)  # builds the kernel on first use
    if method == "native" and not native_ok:
        raise ValueError("method 'native': no C compiler/kernel here (or a custom neighbourhood, or maps off the CPU); "
                         "use 'torch'")
    methods = {"fast": _online_native if native_ok else _online_fast, "native": _online_native,
               "torch": _online_fast, "reference": _online_reference}
    step_fn = lookup(methods, method, "method")
    num_threads = _threads(num_threads)
    x = som.normalize(data, min_samples=1)  # *batch x N x C
    B, C, U, N = som.batch_shape.numel(), som.n_components, som.n_units, x.shape[-2]
    schedule_fn = lookup(SCHEDULES, schedule, "schedule")
    lr0, lr1 = _start_end(learning_rate, (0.5, 0.01), som.batch_shape, "learning_rate", schedule)
    sg0, sg1 = _start_end(sigma, (max(som.grid.rows, som.grid.cols) / 2.0, 1.0), som.batch_shape, "sigma", schedule)
    total = epochs * N
    gens = [torch.Generator().manual_seed(s) for s in map_seeds(seed, som.batch_shape)]
    ctx = dict(x=x.reshape(B, N, C), active=som.active.reshape(B, C), nb=nb,  # B x N x C
               refresh=max(int(refresh_every), 1), kind=_native.KINDS.get(neighbourhood, -1) if native_ok else -1)
    bar = _progress(progress, total, "som online")
    weights = som.weights.reshape(B, U, C)  # B x U x C
    for epoch in range(epochs):
        steps = torch.arange(epoch * N, (epoch + 1) * N)
        lr = _table(schedule_fn, lr0, lr1, steps, total)  # N x B
        sg = _table(schedule_fn, sg0, sg1, steps, total)  # N x B
        order = _orders(gens, N, shuffle)  # N x B
        threads = torch.get_num_threads()
        try:
            if num_threads is not None:
                torch.set_num_threads(num_threads)
            weights = step_fn(weights, som.grid, order, lr, sg, **ctx)
        finally:
            torch.set_num_threads(threads)
        som.weights = weights.reshape(*som.batch_shape, U, C)  # *batch x U x C
        if bar is not None:
            bar.update(N)
        info = {"step": (epoch + 1) * N, "epochs": epochs,
                "learning_rate": lr[-1].reshape(som.batch_shape), "sigma": sg[-1].reshape(som.batch_shape)}
        for hook in hooks:
            hook(epoch, som, info)
    if bar is not None:
        bar.close()
    return som


def _online_native(w, grid, order, lr, sg, *, x, active, nb, refresh, kind):
    """One epoch in the native C kernel (see ``_native``; the gaussian from the grid's axes, the other
    neighbourhoods from its distance table). w: B x U x C; returns B x U x C."""
    B, U, C = w.shape
    dt = w.dtype
    fn = _native.kernel(dt)
    N = order.shape[0]
    L = _native.lanes(dt)
    NB = -(-U // L)
    # B x NB*L x C (a copy): padding units (weight 0) fill the last block
    wp = torch.nn.functional.pad(w, (0, 0, 0, NB * L - U))
    wt = wp.reshape(B, NB, L, C).transpose(2, 3).contiguous()  # B x NB x C x L
    xe = x[torch.arange(B)[None, :], order].to(dt)  # N x B x C
    valid = ~torch.isnan(xe)
    vv = valid.to(dt).contiguous() if bool((~valid).any()) else None  # N x B x C or none
    xe = torch.where(valid, xe, 0.0).contiguous()
    act = active.to(dt).contiguous()  # B x C
    y, xc = (a.to(dt).contiguous() for a in grid.axes)  # rows, 2 x cols
    d2 = None if kind == _native.KINDS["gaussian"] else grid.distances2.to(dt).contiguous()  # U x U
    lr, sg = lr.to(dt).contiguous(), sg.to(dt).contiguous()  # N x B each
    dist, h = torch.empty(B, NB, L, dtype=dt), torch.empty(B, NB, L, dtype=dt)  # per-map scratch
    bmus = torch.empty(N, B, dtype=torch.long)
    # L and NB = ceil(U / L) come from fn's own library: the layout always fits (fn returns 0)
    fn(B, U, C, N, NB, L, wt, xe, vv, act, grid.rows, grid.cols, y, xc, d2, lr, sg, kind, _native.threads(B),
       dist, h, bmus)
    return wt.transpose(2, 3).reshape(B, NB * L, C)[:, :U].contiguous()  # B x U x C


def _online_fast(w, grid, order, lr, sg, *, x, active, nb, refresh, kind=-1):
    """One epoch, all maps per tensor step. w: B x U x C; returns the trained B x U x C.

    Works on the transposed weights ``B x C x U`` (unit axis contiguous: the per-step matmul
    and update are several times faster), keeps the squared norms of the active parts
    incrementally and refreshes them exactly every ``refresh`` steps."""
    B, U, C = w.shape
    dt, dev = w.dtype, w.device
    wt = w.transpose(1, 2).contiguous()  # B x C x U
    d2grid = grid.distances2.to(dev, dt)  # U x U
    xe = x[torch.arange(B)[None, :], order].to(dt)  # N x B x C
    valid = ~torch.isnan(xe)
    has_nan = bool((~valid).any())
    xe = torch.where(valid, xe, 0.0)
    act = active.to(dt)  # B x C
    m = act * valid.to(dt)  # N x B x C: distance mask per sample
    xm = (xe * m).unsqueeze(-2)  # N x B x 1 x C
    xsq = (xe * xe * m).sum(-1, keepdim=True)  # N x B x 1
    m = m.unsqueeze(-2)  # N x B x 1 x C
    lr = lr.to(dev, dt).unsqueeze(-1)  # N x B x 1
    sg = sg.to(dev, dt).unsqueeze(-1)  # N x B x 1
    vcol = valid.to(dt).unsqueeze(-1)  # N x B x C x 1
    xcol = xe.unsqueeze(-1)  # N x B x C x 1
    act_row = act.unsqueeze(1)  # B x 1 x C
    gauss = (-0.5 / (sg * sg), lr.log()) if nb is NEIGHBOURHOODS["gaussian"] else None  # N x B x 1 each
    nrm = torch.bmm(act_row, wt * wt).squeeze(1)  # B x U
    for i in range(order.shape[0]):
        s = torch.bmm(xm[i], wt).squeeze(1)  # B x U
        if has_nan:
            nrm = torch.bmm(m[i], wt * wt).squeeze(1)  # B x U
        e = torch.add(nrm, s, alpha=-2.0)  # B x U: |w - x|^2 - |x|^2 (active components)
        bmu = e.argmin(1)  # B
        if gauss is not None:  # exp(-d2 / (2 sigma^2) + log lr): two ops
            h = torch.addcmul(gauss[1][i], d2grid.index_select(0, bmu), gauss[0][i]).exp_()  # B x U
        else:
            h = nb(d2grid.index_select(0, bmu), sg[i]).mul_(lr[i])  # B x U
        if has_nan:
            wt.lerp_(xcol[i], h.unsqueeze(1) * vcol[i])  # weight B x C x U
            continue
        wt.lerp_(xcol[i], h.unsqueeze(1))  # weight B x 1 x U
        if (i + 1) % refresh == 0:
            nrm = torch.bmm(act_row, wt * wt).squeeze(1)  # B x U
        else:  # |w + h (x - w)|^2 = |w|^2 + 2 h (w.x - |w|^2) + h^2 |x - w|^2 (active components)
            inner = torch.addcmul(s.sub_(nrm), h, e.add_(xsq[i]), value=0.5)  # B x U
            nrm = nrm.addcmul_(h, inner, value=2.0)
    return wt.transpose(1, 2).contiguous()  # B x U x C


def _online_reference(w, grid, order, lr, sg, *, x, active, nb, refresh, kind=-1):
    """One epoch, plain formulas in float64, one map and one sample at a time."""
    dtype = w.dtype
    w = w.to(torch.float64).clone()  # B x U x C
    B, d2grid = w.shape[0], grid.distances2
    for i in range(order.shape[0]):
        for b in range(B):
            v = x[b, order[i, b]]  # C
            ok = ~torch.isnan(v)
            m = active[b] & ok
            dist = torch.where(m, (v - w[b]) ** 2, 0.0).sum(-1)  # U (inactive and NaN columns skipped)
            c = int(torch.argmin(dist))
            h = nb(d2grid[c], sg[i, b]) * lr[i, b]  # U
            w[b] += h[:, None] * torch.where(ok, v - w[b], 0.0)
    return w.to(dtype)


def train_batch(
    som: SOM,
    data: torch.Tensor,
    *,
    epochs: int = 10,
    sigma: Range | None = None,
    schedule: str = "linear",
    neighbourhood: str = "gaussian",
    num_threads: int | None = None,
    progress: bool = False,
    hooks: Iterable[Hook] = (),
    reduce: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> SOM:
    """Train in place with the batch SOM: per epoch, every unit becomes the neighbourhood-weighted
    mean of the samples (per component, NaN skipped) given the best matches (active, non-NaN
    components) under the current weights. Units that no sample reaches keep their weights.
    ``sigma`` per epoch ``e`` follows ``schedule`` over ``e = 0 .. epochs-1`` (total ``epochs``).
    Best matches in the weights' dtype, the per-unit sums and the neighbourhood means in float64;
    deterministic (no seed); on the maps' device. ``data``: raw ``N x C`` or ``*batch x N x C``.
    ``num_threads``: torch threads during training (``None``: unchanged).

    ``reduce``: data-parallel training. ``data`` is this process's share of the samples and
    ``reduce(t)`` returns the sum over all processes of ``t`` (float64 ``B x U x K``: per unit the
    sums of the samples' components and their counts), e.g. an all-reduce of
    ``torch.distributed``; every process then makes the same update. The sums being float64, N
    processes give one process's maps to the rounding of the order in which the partial sums add."""
    if not isinstance(epochs, int) or epochs < 1:
        raise ValueError(f"epochs: expected a positive int, received {epochs!r}")
    nb = lookup(NEIGHBOURHOODS, neighbourhood, "neighbourhood")
    num_threads = _threads(num_threads)
    schedule_fn = lookup(SCHEDULES, schedule, "schedule")
    sg0, sg1 = _start_end(sigma, (max(som.grid.rows, som.grid.cols) / 2.0, 1.0), som.batch_shape, "sigma", schedule)
    sg = _table(schedule_fn, sg0, sg1, torch.arange(epochs), epochs)  # E x B
    x = som.normalize(data, min_samples=1)
    B, C, U, N = som.batch_shape.numel(), som.n_components, som.n_units, x.shape[-2]
    dt, dev, f64 = som.weights.dtype, som.device, torch.float64
    x = x.reshape(B, N, C)  # B x N x C (float64)
    valid = ~torch.isnan(x)
    has_nan = bool((~valid).any())
    xv = torch.where(valid, x, 0.0)  # B x N x C
    m = (valid & som.active.reshape(B, 1, C)).to(dt)  # B x N x C: distance mask
    xm = xv.to(dt) * m
    counts_src = valid.to(f64) if has_nan else torch.ones(B, N, 1, dtype=f64, device=dev)  # B x N x (C or 1)
    K = counts_src.shape[-1]
    d2grid = som.grid.distances2.to(dev, f64)[None]  # 1 x U x U
    sg = sg.to(dev)
    w = som.weights.reshape(B, U, C)  # B x U x C
    bar = _progress(progress, epochs, "som batch")
    threads = torch.get_num_threads()
    try:
        if num_threads is not None:
            torch.set_num_threads(num_threads)
        for epoch in range(epochs):
            wT = w.transpose(1, 2)  # B x C x U
            d = torch.baddbmm(torch.bmm(m, wT * wT), xm, wT, alpha=-2.0)  # B x N x U (+ |x|^2 omitted)
            idx = d.argmin(-1, keepdim=True)  # B x N x 1
            sums = torch.zeros(B, U, C + K, dtype=f64, device=dev)  # B x U x (C + K): samples, counts
            sums[..., :C].scatter_add_(1, idx.expand(B, N, C), xv)
            sums[..., C:].scatter_add_(1, idx.expand(B, N, K), counts_src)
            if reduce is not None:
                sums = reduce(sums)
            h = nb(d2grid, sg[epoch][:, None, None])  # B x U x U
            num, den = torch.bmm(h, sums).split((C, K), -1)  # B x U x C, B x U x K
            w = torch.where(den > 1e-12, (num / den.clamp_min(1e-30)).to(dt), w)
            som.weights = w.reshape(*som.batch_shape, U, C)  # *batch x U x C
            if bar is not None:
                bar.update(1)
            info = {"step": epoch + 1, "epochs": epochs,
                    "learning_rate": torch.ones(som.batch_shape, dtype=torch.float64),
                    "sigma": sg[epoch].reshape(som.batch_shape)}
            for hook in hooks:
                hook(epoch, som, info)
    finally:
        torch.set_num_threads(threads)
    if bar is not None:
        bar.close()
    return som


def fit(
    som: SOM,
    data: torch.Tensor,
    *,
    mode: str = "online",
    init: str | None = "random",
    normalization: str | None = None,
    seed: int | Sequence[int] | torch.Tensor = 0,
    **train_options,
) -> SOM:
    """Normalize (optional: ``"range"``/``"standard"``), initialize (``"random"``/``"linear"``,
    ``None`` keeps the weights) and train (``mode``: ``"online"`` or ``"batch"``) in place.
    ``train_options`` go to :func:`train_online` / :func:`train_batch`."""
    trainer = lookup({"online": train_online, "batch": train_batch}, mode, "mode")
    if normalization is not None:
        som.fit_normalization(data, normalization)
    if init is not None:
        initialize(som, data, init, seed)
    if mode == "online":
        train_options["seed"] = seed
    return trainer(som, data, **train_options)
