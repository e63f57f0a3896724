"""The refinement's search coordinates, their bounds and its settings (:class:`RefineConfig`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from training.identification._one_mass import SECTION_PERIODS

#: Search coordinates and their bounds: log10 f_e [Hz], log10 V_J, d, log10 s_N (normalized
#: backlash; measured better than searching the width itself: 86 vs 66 % of the widths within 30 %).
COORDINATES: tuple[str, ...] = ("log10_f_e", "log10_V_J", "d", "log10_s_N")
LOW = np.array([0.0, math.log10(0.05), 0.001, -3.0])
HIGH = np.array([math.log10(3000.0), math.log10(20.0), 0.5, 2.0])
#: Where STEP 2's one-mass part is not trusted, three more: log10 J_sigma [kg m^2], M_FC [Nm] and
#: mu_F [Nm s/rad], bounded by the record's own scales (:func:`free_bounds`).
FREE_COORDINATES: tuple[str, ...] = COORDINATES + ("log10_J_sigma", "M_FC", "mu_F")
NO_GAP = math.log10(2e-3)  # log10 s_N at or below which a model has no gap (the search's floor is 1e-3)


@dataclass(frozen=True)
class RefineConfig:
    """The refinement's settings, stage by stage.

    Explore: score only the first ``window_periods`` periods (at the start's ``f_e``; at most
    ``window_max`` seconds or ``window_samples`` samples, whichever is longer: the cost is per
    sample, and on a slowly sampled drive 0.1 s held less than one period of a 10 Hz mechanic, too
    little to tell a small gap) after each torque step, with each candidate's best gain projected
    out: a model whose frequency is a few % off does not lose its match to the phase error that
    builds up over a long section, nor a model with the right shape but a wrong ``V_J`` to its
    amplitude (the gain rescales its ``V_J``). A grid of ``grid_f_e`` eigenfrequencies over
    ``+-grid_span`` decades around the start times the normalized backlash values ``grid_s_N``
    (0: the start's own), then
    ``rounds`` rounds of a cross-entropy search: ``candidates`` models around the best so far,
    the ``elites`` best setting the next round's spread (``spread``: the first round's standard
    deviation per coordinate of :data:`COORDINATES`). Each window is simulated on its own from a
    quasi-static state, so exploring costs a few periods per torque step, not the whole record.

    Choose: the maps' answer and the ``elites`` best of the exploration compete on the plain
    detrended error over the whole record, simulated exactly (more rounds there were measured
    not to help). The C kernel runs blocks of 32 models on the CPU's cores: 64 candidates take
    the wall time of 32 on two.

    Climb (stiff shafts with a gap): a softer shaft with a narrower gap reproduces a gap crossing
    nearly as well as the true model, and the maps read the ``f_e`` of a shaft the current loop
    hardly excites low; the exploring error then falls along a narrow ridge of ``f_e`` and width up
    to the truth, often 2-6 x the maps' ``f_e`` (measured on the large axis: the widths came out
    0.5-0.7 x), farther than one exploration reaches. Where the start's ``f_e`` reaches
    ``climb_above`` x the current loop's bandwidth ``1/(2 pi T_Ei)``, the exploration's best model
    has a gap (``s_N >=`` :data:`sim.S_N_ELASTIC`) and lies ``climb_after`` decades or more above
    the start, a second exploration runs from ``climb`` decades above that model at the same
    backlash width: a grid of ``climb_grid_f_e`` eigenfrequencies over ``+-climb_span`` decades (the
    ridge from the first's best up to 10 x its ``f_e``), then ``far_rounds`` rounds. Where its
    exploring error is below ``switch_win`` x the first's (a clear win only: a narrow one added
    false gaps on stiff shafts of a coarse drive), it replaces the first exploration: its elites
    become the finalists, and the rattle starts from its best; where it loses, the answer is the one
    without it (it draws from a random stream of its own). It replaces the first's elites rather
    than joining them because the whole-record error of a lightly damped shaft rattling in its gap
    is needle-sharp (+-5 % in ``f_e`` scores like no fit at all): the climb's near-true models would
    lose the choice to the first's soft, narrow ones.

    Rescue (answers that explain little): where the exploration's best leaves more than
    ``rescue_above`` of the windows' measured energy unexplained while that energy is
    ``rescue_signal`` x or more the speed's quantization noise (``q_w^2 / 6`` per sample: there is
    a response to explain), the maps' answer is taken to be far off (measured on the large axis: a
    stiff shaft with a wide gap answered ``elastic`` at 13 Hz, the truth at 232 Hz; on the noisy
    drive a shaft with a gap of ``s_N`` 0.57 answered at 75 Hz and ``V_J`` 0.32 leaving 0.70 of the
    windows' energy, the truth at 95 Hz and 0.68 leaving 0.02: so a far-off answer can still
    explain half the energy, and the threshold is 0.5). A grid over
    the whole range, ``rescue_grid_f_e`` eigenfrequencies from the drive envelope's lowest to the Nyquist
    frequency times ``rescue_V_J`` times ``grid_s_N``, then ``far_rounds`` rounds, with a random
    stream of its own (where it loses, the answer is the one without it). Where it beats the
    exploration by ``switch_win``, its elites join the finalists beside the exploration's (the
    whole-record choice decides: a model that is wrong in the windows' way can still lose there),
    and the climb and the rattle go on from its best.

    Rattle (gaps): after the torque drops to zero the masses rattle in the gap, and where the next
    torque step finds them decides how far the motor runs free before it takes the load. The
    quasi-static start puts the motor against the load there, and an exploration scored that way
    reads the gap narrower than it is (measured on the large axis: 0.6-0.7 x, with the truth
    scoring worse than the answer on exactly the two windows after the zero-torque sections).
    Where the exploration's best has a gap (``s_N >= rattle_s_N``) and the record a zero-torque
    section before a torque step, the search goes on with those windows simulated from their
    zero-torque section's start (whose state is quasi-static: the section before it held one
    torque): the exploration's elites and its best with ``s_N`` moved by ``rattle_shift`` decades,
    then ``rattle_rounds`` rounds; its ``rattle_finalists`` best join the finalists. This costs a
    replay of the two zero-torque sections per model for those records only (`twomass identify`
    of 1000 reference records: 8-11 % longer).

    Polish (whole record, local): around the chosen model the whole-record error is nearly linear
    in :data:`COORDINATES`, and a model a few % off in ``f_e``, ``V_J`` or ``d`` still scores 10-1000
    x worse than the truth over a record of many periods (measured on every elastic reference
    system outside ``E_10``). Up to ``polish_iterations`` Levenberg-Marquardt steps: a forward-
    difference Jacobian (``polish_steps`` per coordinate), the damped steps ``(J^T J + lambda
    diag(J^T J)) delta = -J^T r`` for each ``lambda`` of ``polish_damping``, the best kept where it
    lowers the error; a problem stops when an iteration gains less than ``polish_tolerance``
    (measured: lightly damped records of many periods whose answers the windows left 30-40 % off
    in ``V_J`` and ``d``, with the truth 100-1000 x better on the whole record, came back only with
    ``lambda`` up to 10, a full step overshooting in the needle-sharp ``f_e``, and some only after
    10-20 iterations; most records stop after a few). The
    polished model replaces the chosen one only where its error is below ``polish_win`` times the
    chosen one's (measured on the reference drive: the polish's wins were 2-80 x lower, its losses,
    models that were wrong in another way, 1.0-1.7 x). The error is scored on every ``k``-th sample
    only, ``polish_samples_per_period`` per period at the chosen ``f_e`` (a slow mechanic's record
    holds hundreds per period; the replay still runs over every sample). ``s_N`` moves only where
    the chosen model has a gap, or where one of ``polish_gap_seeds`` scores better than the chosen
    model without it: the polish then starts from the best of them (a gap of ``s_N`` 0.02 on a
    lightly damped shaft is a needle in ``s_N`` that the searches miss; measured on the large axis,
    they answered without it and bent ``V_J`` 30 % instead, once unwarned). A free stage's model
    moves over all seven :data:`FREE_COORDINATES` (``polish_free_steps``, relative to the
    coordinates' scales, see below) on the plain error, as its stage scored it (measured on the
    fast spindle: without the polish, free models came out with ``V_J`` 10-45 % off where the
    chosen model's was within 3 %). Where the polished model still leaves more than
    ``polish_retry_residual`` of the measured speed (relative rms over the scored samples) and more
    than ``polish_retry_above`` x the speed's quantization noise, the polish runs once more from it
    with its ``d`` times ``polish_retry_damping``, and once from the maps' answer (with the gap
    seeds where it has no gap), and the lowest error stands: too much damping is
    where the lightly damped shafts' valleys hold it (measured: a noisy drive's ``d`` 0.012 at
    20 Hz stopped at ``d`` 0.028 and ``V_J`` 41 % high, unwarned, the truth scoring 300 x better;
    from half the damping it reaches the truth; about 10 % of the reference drive's records are
    retried, and retrying every fit above 4 x the noise took twice as long for the same answers).
    The maps' answer, where it was near, is the other way out (measured: a fast spindle's 88 Hz
    shaft, ``d`` 0.011, answered with ``V_J`` 33 % low and ``d`` 0.004, unwarned at a residual of
    0.48; the maps had ``V_J`` 7 % low and no gap, and from there, with the gap seeds, the polish
    reaches the truth).

    Free one-mass part (problems with ``free_one_mass``: STEP 2 flagged its fit, as for very soft
    mechanics whose test sections are shorter than an oscillation period; and wherever the
    shortest section holds fewer than ``free_periods`` periods of the chosen model: a test whose
    time scale ``J_sigma w_max / M*`` is a fraction of the period ends before the load follows,
    and STEP 2's fit, unflagged, reads about the motor's inertia, 0.15-0.2 x ``J_sigma`` on the
    servo of the drive matrix): ``J_sigma``, ``M_FC`` and ``mu_F`` join the search
    (:data:`FREE_COORDINATES`), scored by the plain error over the whole record (an exact
    replay from rest; nothing to detrend once the one-mass part is fitted). Their bounds and
    steps follow the record's own scales: ``J_sigma`` within 2 decades of STEP 2's, ``M_FC``
    up to ``M*``, ``mu_F`` up to ``M* / w_max`` (``w_max``: the record's top speed). Each model is
    scored at its best ``J_sigma``, exactly: ``J_sigma / k`` and ``mu_F / k`` make the replayed speed
    ``k`` times itself (:func:`scaled_fit`), so ``J_sigma`` needs no grid. Grids over ``f_e`` (x 1/16
    .. 2 in steps of 2^0.25: such a mechanic is softer than it looks, and the whole-record error is
    needle-sharp in ``f_e``, a few % wide), ``V_J`` and the friction (STEP 2's, capped at a tenth of
    its bound; or 2.5 % of ``M*`` and 1 % of ``M* / w_max``) around the chosen model and around the
    maps' answer, then ``free_rounds`` rounds (``free_spread``: the first spread of the three new
    coordinates, in units of their scales 1, ``M*``, ``M* / w_max``): one search with ``V_J`` x 0.5,
    1, 2 of the centre's, one (a random stream of its own) with 5 ``V_J`` over the drive envelope's
    range, for a STEP 2 that read the motor alone (a load 3-5 x the motor lies beyond the first).
    The exact scale takes ``J_sigma`` out of the grids because a grid over it (and over ``f_e`` in
    steps of 2) left the search in a broad valley beside the needle in ``f_e``. The free
    model replaces the chosen one only when its plain squared error is below ``free_win`` times the
    chosen one's with STEP 2's own one-mass values, uncapped (against the capped friction, a 2 Hz
    model 3 x worse than the chosen 37 Hz one would win on a commissioning plant with motor friction).

    Angle (:mod:`training.identification._refine._angle`, run by the identifier where the answer is
    ``stiff`` on a record whose speed could hide a backlash, or where the refinement dropped the
    maps' gap): models with and without a gap compete on the whole record's angle error,
    ``angle_rounds`` cross-entropy rounds on each side."""

    grid_f_e: int = 11  # explore: eigenfrequencies of the first grid
    grid_s_N: tuple[float, ...] = (0.0, 0.05, 0.3, 1.0, 3.0)  # explore: s_N of the first grid (0: the start's)
    grid_span: float = 0.25  # explore: the grid's half width [decades of f_e]
    window_periods: float = 4.0  # explore: periods scored after each torque step
    window_max: float = 0.1  # explore: at most this long [s] ...
    window_samples: int = 400  # ... or this many samples, whichever is longer (0.1 s at 250 us)
    rounds: int = 3  # explore: cross-entropy rounds
    candidates: int = 64  # models per round
    elites: int = 12  # best models that set the next spread (and the finalists)
    spread: tuple[float, float, float, float] = (0.05, 0.12, 0.03, 0.3)  # first spread over COORDINATES
    climb: float = 0.5  # climb: the second exploration's centre above the first's best [decades of f_e]
    climb_span: float = 0.5  # climb: its grid's half width [decades] ...
    climb_grid_f_e: int = 21  # ... over this many eigenfrequencies
    climb_after: float = 0.0  # climb: only where the first's best lies this far above the start [decades]
    climb_above: float = 0.4  # climb: only where the start's f_e reaches this x the current loop's bandwidth
    rescue_above: float = 0.5  # rescue: only where the first's best leaves this share of the windows' energy ...
    rescue_signal: float = 3.0  # ... and that energy is at least this x the speed's quantization noise
    rescue_grid_f_e: int = 16  # rescue: eigenfrequencies of its grid, SPEC 3.1's lowest to Nyquist
    rescue_V_J: tuple[float, ...] = (0.25, 0.6, 1.5, 3.5)  # rescue: V_J of its grid
    far_rounds: int = 6  # climb, rescue: cross-entropy rounds
    switch_win: float = 0.9  # climb, rescue: replace the first exploration below this error ratio
    rattle_s_N: float = 0.1  # rattle: only where the exploration's best has s_N >= this
    rattle_shift: tuple[float, ...] = (-0.2, -0.1, 0.1, 0.2)  # rattle: its best's s_N moved [decades]
    rattle_rounds: int = 2  # rattle: cross-entropy rounds
    rattle_finalists: int = 4  # rattle: its best models that join the finalists
    polish_iterations: int = 20  # polish: Gauss-Newton iterations at most (0: no polish)
    polish_tolerance: float = 0.01  # polish: a problem stops once an iteration gains less than this share
    polish_steps: tuple[float, float, float, float] = (1e-3, 5e-3, 2e-3, 2e-2)  # polish: difference steps
    polish_damping: tuple[float, ...] = (0.01, 0.1, 1.0, 10.0)  # polish: the lambdas tried per iteration
    polish_win: float = 0.5  # polish: replaces the chosen model only below this error ratio
    polish_samples_per_period: float = 16.0  # polish: the error scored on this many samples per period
    polish_free_steps: tuple[float, float, float] = (1e-3, 1e-3, 1e-3)  # polish: the free stage's three, in scales
    polish_gap_seeds: tuple[float, ...] = (0.003, 0.005, 0.01, 0.02, 0.04)  # polish: s_N tried on a model without a gap
    polish_retry_residual: float = 0.3  # polish: once more where the relative error stays above this ...
    polish_retry_above: float = 30.0  # ... and above this x the speed's quantization noise ...
    polish_retry_damping: float = 0.5  # ... from the polished model with its d times this
    free_rounds: int = 5  # free one-mass part: cross-entropy rounds
    # free one-mass part: first spread of log10 J_sigma, M_FC / M*, mu_F w_max / M*
    free_spread: tuple[float, float, float] = (0.1, 0.01, 0.01)
    free_win: float = 0.25  # free one-mass part: error ratio it must beat
    # free one-mass part: also where a section holds fewer periods of the chosen model (STEP 2's own rule)
    free_periods: float = SECTION_PERIODS
    angle_rounds: int = 4  # angle: cross-entropy rounds on each side of the class threshold
    seed: int = 0  # every search starts from this seed

    def __post_init__(self) -> None:
        if (self.elites < 2 or self.candidates < self.elites or self.rounds < 0 or self.window_periods <= 0
                or self.window_samples < 0 or self.polish_iterations < 0 or self.angle_rounds < 0
                or self.far_rounds < 0 or min(self.grid_f_e, self.climb_grid_f_e, self.rescue_grid_f_e) < 1
                or len(self.free_spread) != 3 or len(self.polish_free_steps) != 3 or self.free_rounds < 0
                or any(not g > 10.0 ** NO_GAP for g in self.polish_gap_seeds)
                or not 0.0 < self.polish_retry_damping <= 1.0 or self.polish_retry_above < 0
                or self.polish_retry_residual < 0):
            raise ValueError(f"RefineConfig: expected rounds >= 0, far_rounds >= 0, free_rounds >= 0, "
                             f"polish_iterations >= 0, angle_rounds >= 0, grid_f_e >= 1, climb_grid_f_e >= 1, "
                             f"rescue_grid_f_e >= 1, window_periods > 0, window_samples >= 0, "
                             f"candidates >= elites >= 2, "
                             f"three values each in free_spread and polish_free_steps (log10 J_sigma, M_FC, mu_F) "
                             f"polish_gap_seeds above {10.0 ** NO_GAP:g}, 0 < polish_retry_damping <= 1 and "
                             f"polish_retry_above >= 0, polish_retry_residual >= 0, "
                             f"received {self}")
