/* Fused fixed-step two-mass kernel (see sim/_integrate_fast.py for the torch twin; the
   signatures are declared in sim/_kernel.py). Compiled once per float type: -DREAL=float or
   -DREAL=double. Every floating-point operation is written in the same order as the torch eager
   twin, compiled with -ffp-contract=off, so both give the same numbers.

   Systems run in blocks of BLK lanes (one thread's unit of work). A substep runs as four loops
   over the block's lanes (mode and stage 1; stage 2; stage 3; stage 4 and the update), each
   vectorized by the compiler, the values between them kept in the block: the lanes' RK4 chains
   are independent, so the CPU overlaps them instead of waiting on one chain's latency. The
   substeps and the switching test's controller are branch-free (compares and selects). */
#ifndef REAL
#error "compile with -DREAL=float or -DREAL=double"
#endif
#include <math.h>
#include <stdint.h>
#include <string.h>

#define BLK 32
/* |M_M| below this [Nm] is 0 (with its compensation): at zero torque the current loop's lag decays
   exponentially and would pass through subnormal numbers (float32 from 69 T_Ei on), each operation
   on which costs a microcode assist: the kernel ran 2.4x slower over a whole test. */
#define TORQUE_FLOOR 1e-30
/* The substep's phases take `motor` (0 or 1, a constant at each call: advance_block compiles them
   twice): 1 with SPEC 1.1's motor friction, 0 without (SPEC 1's motor, its arithmetic as before:
   the blocks of plants without motor friction run as fast as before it was added). */
#define PHASE static inline __attribute__((always_inline))

typedef struct {
    REAL iJM[BLK], iJL[BLK], CF[BLK], DF[BLK], s[BLK], ns[BLK], MFC[BLK], muF[BLK], Mext[BLK];
    REAL MFCM[BLK], muFM[BLK], hasM[BLK];  /* motor friction (SPEC 1.1); hasM: 1 where MFCM > 0 (it may stick) */
    int anyM;  /* some lane has motor friction (MFCM or muFM not 0) */
    REAL wM[BLK], wL[BLK], dp[BLK], MM[BLK], Mref[BLK];
    REAL cwM[BLK], cwL[BLK], cdp[BLK], cMM[BLK];  /* Kahan compensations */
    double phi[BLK], cntp[BLK];
    /* within a substep: the mode (iJLf: 1/J_L, or 0 while stuck), the next stage's state, the stage
       sums, the angle increment */
    REAL stuck[BLK], sgn[BLK], fric[BLK], iJLf[BLK];
    REAL stuckM[BLK], sgnM[BLK], fricM[BLK], iJMf[BLK];  /* the motor's mode, likewise */
    REAL xwM[BLK], xwL[BLK], xdp[BLK], xMM[BLK];
    REAL sa[BLK], sb[BLK], sc[BLK], sd[BLK], sw[BLK], inc[BLK];
} block_t;

/* Shaft torque M_S = C_F e + [e != 0] D_F dw, e = dp - clamp(dp, -s, s), dw = w_M - w_L (ns = -s). */
static inline REAL shaft(const block_t *B, int l, REAL dp, REAL dw) {
    REAL ns = B->ns[l];
    REAL cl = dp < ns ? ns : dp;
    cl = cl > B->s[l] ? B->s[l] : cl;
    REAL e = dp - cl, Ddw = B->DF[l] * dw;  /* computed, then selected (a conditional load would be masked) */
    return B->CF[l] * e + (e != (REAL)0 ? Ddw : (REAL)0);
}

/* The right-hand side's dw_M, dw_L, dM_M given the shaft torque MS and net = MS - Mext (ddphi is dw).
   A stuck load's dw_L is a product with 0 (+-0, as in the torch twin; its speed is reset to +0 at the
   end of the substep, so the states are those of a select, with no compare and select per stage);
   a stuck motor's dw_M likewise. */
PHASE void rhs(const block_t *B, int l, REAL wM, REAL wL, REAL MM, REAL MS, REAL net, REAL iTE, REAL *a,
               REAL *b, REAL *d, const int motor) {
    *a = motor ? (MM - MS - B->fricM[l] - B->muFM[l] * wM) * B->iJMf[l] : (MM - MS) * B->iJM[l];
    *b = (net - B->fric[l] - B->muF[l] * wL) * B->iJLf[l];
    *d = (B->Mref[l] - MM) * iTE;
}

/* The phases of one RK4 substep for lane l: the mode (frozen over the substep: stuck, friction
   sign) and stage 1, whose shaft torque is the mode's; stage 2 or 3 (f = h, then dt: the next
   stage's state); stage 4 and the Kahan-compensated update (a load that changed sign against its
   friction stops; a motor torque below TORQUE_FLOOR is 0). Stage sums as ((k1 + 2 k2) + 2 k3) + k4. */
PHASE void stage1(block_t *B, int l, REAL h, REAL iTE, const int motor) {
    REAL wM = B->wM[l], wL = B->wL[l], dp = B->dp[l], MM = B->MM[l];
    REAL dw = wM - wL;
    REAL MS = shaft(B, l, dp, dw);
    REAL net = MS - B->Mext[l];
    int rest = wL == (REAL)0;
    REAL anet = net < 0 ? -net : net;
    int stuck = rest && (anet <= B->MFC[l]);
    REAL sn = (REAL)((net > 0) - (net < 0));
    REAL sw = (REAL)((wL > 0) - (wL < 0));
    REAL sgn = rest ? sn : sw;
    B->stuck[l] = (REAL)stuck; B->sgn[l] = sgn; B->fric[l] = B->MFC[l] * sgn;
    B->iJLf[l] = stuck ? (REAL)0 : B->iJL[l];
    if (motor) {  /* the motor's mode: net torque M_M - M_S; stuck only with Coulomb friction (hasM) */
        REAL netM = MM - MS;
        int restM = wM == (REAL)0;
        REAL anetM = netM < 0 ? -netM : netM;
        int stuckM = restM && (anetM <= B->MFCM[l]) && (B->hasM[l] != (REAL)0);
        REAL snM = (REAL)((netM > 0) - (netM < 0));
        REAL swM = (REAL)((wM > 0) - (wM < 0));
        REAL sgnM = restM ? snM : swM;
        B->stuckM[l] = (REAL)stuckM; B->sgnM[l] = sgnM; B->fricM[l] = B->MFCM[l] * sgnM;
        B->iJMf[l] = stuckM ? (REAL)0 : B->iJM[l];
    }
    REAL a, b, d;
    rhs(B, l, wM, wL, MM, MS, net, iTE, &a, &b, &d, motor);
    B->sa[l] = a; B->sb[l] = b; B->sc[l] = dw; B->sd[l] = d; B->sw[l] = wM;
    B->xwM[l] = wM + h * a; B->xwL[l] = wL + h * b; B->xdp[l] = dp + h * dw; B->xMM[l] = MM + h * d;
}

/* The slopes at the stage's state xw*: its w_M, dw (= ddphi), dw_M, dw_L, dM_M. */
PHASE void stage_slopes(const block_t *B, int l, REAL iTE, REAL *wM, REAL *dw, REAL *a, REAL *b, REAL *d,
                        const int motor) {
    REAL wL = B->xwL[l];
    *wM = B->xwM[l];
    *dw = *wM - wL;
    REAL MS = shaft(B, l, B->xdp[l], *dw);
    rhs(B, l, *wM, wL, B->xMM[l], MS, MS - B->Mext[l], iTE, a, b, d, motor);
}

PHASE void stage23(block_t *B, int l, REAL f, REAL iTE, const int motor) {
    REAL wM, dw, a, b, d;
    stage_slopes(B, l, iTE, &wM, &dw, &a, &b, &d, motor);
    B->sa[l] = B->sa[l] + (REAL)2 * a; B->sb[l] = B->sb[l] + (REAL)2 * b; B->sc[l] = B->sc[l] + (REAL)2 * dw;
    B->sd[l] = B->sd[l] + (REAL)2 * d; B->sw[l] = B->sw[l] + (REAL)2 * wM;
    B->xwM[l] = B->wM[l] + f * a; B->xwL[l] = B->wL[l] + f * b; B->xdp[l] = B->dp[l] + f * dw;
    B->xMM[l] = B->MM[l] + f * d;
}

PHASE void stage4(block_t *B, int l, REAL k6, REAL iTE, const int motor) {
    REAL wM, dw, a, b, d;
    stage_slopes(B, l, iTE, &wM, &dw, &a, &b, &d, motor);
    B->inc[l] = B->inc[l] + k6 * (B->sw[l] + wM);
    REAL y, t, x;
    x = B->wM[l]; y = k6 * (B->sa[l] + a) - B->cwM[l];
    t = x + y;
    if (motor) {  /* a motor with Coulomb friction that changed sign against it stops, as the load */
        int clampM = (B->hasM[l] != (REAL)0) & ((B->stuckM[l] != (REAL)0) | (t * B->sgnM[l] < (REAL)0));
        B->cwM[l] = clampM ? (REAL)0 : (t - x) - y;
        B->wM[l] = clampM ? (REAL)0 : t;
    } else {
        B->cwM[l] = (t - x) - y; B->wM[l] = t;
    }
    x = B->wL[l]; y = k6 * (B->sb[l] + b) - B->cwL[l];
    t = x + y;
    int clamp = (B->stuck[l] != (REAL)0) | (t * B->sgn[l] < (REAL)0);
    B->cwL[l] = clamp ? (REAL)0 : (t - x) - y;
    B->wL[l] = clamp ? (REAL)0 : t;
    x = B->dp[l]; y = k6 * (B->sc[l] + dw) - B->cdp[l];
    t = x + y; B->cdp[l] = (t - x) - y; B->dp[l] = t;
    x = B->MM[l]; y = k6 * (B->sd[l] + d) - B->cMM[l];
    t = x + y;
    int gone = (t < (REAL)0 ? -t : t) < (REAL)TORQUE_FLOOR;
    B->cMM[l] = gone ? (REAL)0 : (t - x) - y; B->MM[l] = gone ? (REAL)0 : t;
}

/* S substeps of RK4 for all lanes of a block (with or without the motor's friction); the
   motor-angle increment goes to phi. */
PHASE void advance_substeps(block_t *B, int S, REAL dt, REAL h, REAL k6, REAL iTE, const int motor) {
    for (int l = 0; l < BLK; ++l) B->inc[l] = 0;
    for (int j = 0; j < S; ++j) {
#pragma GCC ivdep
        for (int l = 0; l < BLK; ++l) stage1(B, l, h, iTE, motor);
#pragma GCC ivdep
        for (int l = 0; l < BLK; ++l) stage23(B, l, h, iTE, motor);
#pragma GCC ivdep
        for (int l = 0; l < BLK; ++l) stage23(B, l, dt, iTE, motor);
#pragma GCC ivdep
        for (int l = 0; l < BLK; ++l) stage4(B, l, k6, iTE, motor);
    }
    for (int l = 0; l < BLK; ++l) B->phi[l] = B->phi[l] + (double)B->inc[l];
}

static void advance_block(block_t *B, int S, REAL dt, REAL h, REAL k6, REAL iTE) {
    if (B->anyM)
        advance_substeps(B, S, dt, h, k6, iTE, 1);
    else
        advance_substeps(B, S, dt, h, k6, iTE, 0);
}

static inline int load_block(block_t *B, int64_t i0, int64_t n,
                             const REAL *iJM, const REAL *iJL, const REAL *CF, const REAL *DF, const REAL *s,
                             const REAL *MFC, const REAL *muF, const REAL *Mext, const REAL *MFCM, const REAL *muFM,
                             const REAL *wM, const REAL *wL, const REAL *dp, const REAL *MM, const REAL *Mref,
                             const double *phi, const double *cntp, const REAL *comp) {
    int m = (int)((n - i0) < BLK ? (n - i0) : BLK);
    B->anyM = 0;
    for (int l = 0; l < BLK; ++l) {
        int64_t i = i0 + (l < m ? l : 0);  /* pad lanes repeat lane 0 */
        B->iJM[l] = iJM[i]; B->iJL[l] = iJL[i]; B->CF[l] = CF[i]; B->DF[l] = DF[i]; B->s[l] = s[i]; B->ns[l] = -s[i];
        B->MFC[l] = MFC[i]; B->muF[l] = muF[i]; B->Mext[l] = Mext[i];
        B->MFCM[l] = MFCM[i]; B->muFM[l] = muFM[i]; B->hasM[l] = (REAL)(MFCM[i] > (REAL)0);
        B->anyM |= (MFCM[i] != (REAL)0) | (muFM[i] != (REAL)0);
        B->wM[l] = wM[i]; B->wL[l] = wL[i]; B->dp[l] = dp[i]; B->MM[l] = MM[i]; B->Mref[l] = Mref[i];
        B->phi[l] = phi[i]; B->cntp[l] = cntp[i];
        B->cwM[l] = comp[i]; B->cwL[l] = comp[n + i]; B->cdp[l] = comp[2 * n + i]; B->cMM[l] = comp[3 * n + i];
    }
    return m;
}

static inline void store_block(const block_t *B, int64_t i0, int m, int64_t n, REAL *wM, REAL *wL, REAL *dp, REAL *MM,
                               REAL *Mref, double *phi, double *cntp, REAL *comp) {
    for (int l = 0; l < m; ++l) {
        int64_t i = i0 + l;
        wM[i] = B->wM[l]; wL[i] = B->wL[l]; dp[i] = B->dp[l]; MM[i] = B->MM[l]; Mref[i] = B->Mref[l];
        phi[i] = B->phi[l]; cntp[i] = B->cntp[l];
        comp[i] = B->cwM[l]; comp[n + i] = B->cwL[l]; comp[2 * n + i] = B->cdp[l]; comp[3 * n + i] = B->cMM[l];
    }
}

/* One sample for n systems: S substeps with the applied Mref; phi accumulates the angle. */
void advance(int64_t n, int S, REAL dt, REAL h, REAL k6, REAL iTE, int nthreads,
             const REAL *iJM, const REAL *iJL, const REAL *CF, const REAL *DF, const REAL *s,
             const REAL *MFC, const REAL *muF, const REAL *Mext, const REAL *MFCM, const REAL *muFM,
             REAL *wM, REAL *wL, REAL *dp, REAL *MM, REAL *Mref, double *phi, double *cntp, REAL *comp) {
    int64_t nb = (n + BLK - 1) / BLK;
#pragma omp parallel for schedule(static) num_threads(nthreads)
    for (int64_t b = 0; b < nb; ++b) {
        block_t B;
        int m = load_block(&B, b * BLK, n, iJM, iJL, CF, DF, s, MFC, muF, Mext, MFCM, muFM, wM, wL, dp, MM, Mref, phi, cntp, comp);
        advance_block(&B, S, dt, h, k6, iTE);
        store_block(&B, b * BLK, m, n, wM, wL, dp, MM, Mref, phi, cntp, comp);
    }
}

/* Up to nk samples (k0 .. k0+nk-1) of the switching test (SPEC 2) for n systems, fused:
   measure, record, controller step, advance. Controller state per system: sec (1..6, 7 tail,
   8 done), cnt (samples in section), nI, nIV, len (record length once done), tmo (bit per
   section that timed out). Returns the number of systems not yet done. */
int64_t run_test(int64_t n, int S, REAL dt, REAL h, REAL k6, REAL iTE, int nthreads,
                 const REAL *iJM, const REAL *iJL, const REAL *CF, const REAL *DF, const REAL *s,
                 const REAL *MFC, const REAL *muF, const REAL *Mext, const REAL *MFCM, const REAL *muFM,
                 REAL *wM, REAL *wL, REAL *dp, REAL *MM, REAL *Mref, double *phi, double *cntp, REAL *comp,
                 int32_t *sec, int32_t *cnt, int32_t *nI, int32_t *nIV, int32_t *len, int32_t *tmo, const REAL *Mhold,
                 double qw, double scale, REAL Mstar, REAL Mlow, REAL wmax, REAL wlow, REAL Mmax,
                 int32_t n_timeout, int32_t n_tail, int64_t k0, int64_t nk, int64_t ostride, int64_t ocol0,
                 REAL *o_speed, REAL *o_torque, REAL *o_tref, int8_t *o_sec) {
    int64_t nb = (n + BLK - 1) / BLK;
    int64_t left = 0;
    /* the level of each section state (0 unused, 1..6, 7 tail, 8 done); the reference is
       Mhold + level clamped to +-Mmax (SPEC 1.1: the levels around the holding torque; Mhold 0: plain) */
    REAL lev[9] = {0, Mstar, 0, -Mlow, -Mstar, 0, Mlow, 0, 0};
#pragma omp parallel for schedule(dynamic, 1) num_threads(nthreads) reduction(+:left)
    for (int64_t b = 0; b < nb; ++b) {
        block_t B __attribute__((aligned(64)));
        int64_t i0 = b * BLK;
        int m = load_block(&B, i0, n, iJM, iJL, CF, DF, s, MFC, muF, Mext, MFCM, muFM, wM, wL, dp, MM, Mref, phi, cntp, comp);
        int32_t csec[BLK], ccnt[BLK], cnI[BLK], cnIV[BLK], clen[BLK], ctmo[BLK], osec[BLK];
        REAL wv[BLK], hold[BLK];
        for (int l = 0; l < BLK; ++l) {
            int64_t i = i0 + (l < m ? l : 0);
            hold[l] = Mhold[i];
            csec[l] = l < m ? sec[i] : 8; ccnt[l] = cnt[i]; cnI[l] = nI[i]; cnIV[l] = nIV[i];
            clen[l] = len[i]; ctmo[l] = tmo[i];
        }
        for (int64_t kk = 0; kk < nk; ++kk) {
            int32_t kp1 = (int32_t)(k0 + kk + 1);
            int active = 0;
            /* measure, then the controller's step, branch-free over the lanes */
            for (int l = 0; l < BLK; ++l) {
                int32_t q = csec[l], act = q < 8;
                double c = floor(B.phi[l] * scale);
                REAL w = (REAL)((c - B.cntp[l]) * qw);
                B.cntp[l] = act ? c : B.cntp[l];
                wv[l] = w;
                osec[l] = q;
                int32_t t = ccnt[l] + 1;
                int32_t end = ((q == 1) & (w >= wmax)) | ((q == 2) & ((t >= cnI[l]) | (w <= wlow)))
                            | ((q == 3) & (w <= (REAL)0)) | ((q == 4) & (w <= -wmax))
                            | ((q == 5) & ((t >= cnIV[l]) | (w >= -wlow))) | ((q == 6) & (w >= (REAL)0))
                            | ((q >= 7) & (t >= n_tail));
                int32_t tmo_now = !end & (q <= 6) & (t >= n_timeout);
                ctmo[l] |= (act & tmo_now) << ((q - 1) & 7);
                end = (end | tmo_now) & act;
                /* selects as masks: the compiler's conditional stores would be masked stores, slow on some CPUs */
                int32_t mI = -(end & (q == 1)), mIV = -(end & (q == 4)), mlen = -(end & (q == 7));
                cnI[l] = (t & mI) | (cnI[l] & ~mI);
                cnIV[l] = (t & mIV) | (cnIV[l] & ~mIV);
                clen[l] = (kp1 & mlen) | (clen[l] & ~mlen);
                q += end;
                ccnt[l] = act ? (end ? 0 : t) : ccnt[l];
                csec[l] = q;
                active |= act;
            }
            if (!active) break;
            /* record (the reference applied over this sample) */
            for (int l = 0; l < m; ++l) {
                if (osec[l] >= 8) continue;
                int64_t o = (i0 + l) * ostride + ocol0 + kk;
                o_speed[o] = wv[l]; o_torque[o] = B.MM[l]; o_tref[o] = B.Mref[l];
                o_sec[o] = (int8_t)(osec[l] == 7 ? 0 : osec[l]);
            }
            advance_block(&B, S, dt, h, k6, iTE);
            /* the controller's new reference applies from the next sample */
            for (int l = 0; l < BLK; ++l) {
                REAL r = lev[csec[l]] + hold[l];
                r = r < -Mmax ? -Mmax : r;
                r = r > Mmax ? Mmax : r;
                B.Mref[l] = osec[l] < 8 ? r : B.Mref[l];
            }
        }
        for (int l = 0; l < m; ++l) {
            int64_t i = i0 + l;
            sec[i] = csec[l]; cnt[i] = ccnt[l]; nI[i] = cnI[l]; nIV[i] = cnIV[l]; len[i] = clen[l]; tmo[i] = ctmo[l];
            left += csec[l] < 8;
        }
        store_block(&B, i0, m, n, wM, wL, dp, MM, Mref, phi, cntp, comp);
    }
    return left;
}

/* Open-loop replay of a piecewise-constant torque reference for n systems, fused: measure,
   record the speed, set M_ref, advance. System i applies lev[i*K + j] over samples
   start[i*K + j] <= k < start[i*K + j + 1] (start ascending; the last segment runs to the end).
   Writes the speed of samples k0 .. k0+nk-1 time-major to o_speed[(k - k0)*ostride + i] (ostride >= n;
   a multiple of BLK lets each block write whole cache lines): the encoder's
   (quantized) when quantize is set, else the mean motor speed over the past sample interval
   (the expected value of the encoder's, for fits). */
void run_replay(int64_t n, int S, REAL dt, REAL h, REAL k6, REAL iTE, int nthreads,
                const REAL *iJM, const REAL *iJL, const REAL *CF, const REAL *DF, const REAL *s,
                const REAL *MFC, const REAL *muF, const REAL *Mext, const REAL *MFCM, const REAL *muFM,
                REAL *wM, REAL *wL, REAL *dp, REAL *MM, REAL *Mref, double *phi, double *cntp, REAL *comp,
                double qw, double scale, int32_t quantize, int32_t K, const int32_t *start, const REAL *lev,
                int64_t k0, int64_t nk, int64_t ostride, REAL *o_speed) {
    int64_t nb = (n + BLK - 1) / BLK;
#pragma omp parallel for schedule(dynamic, 1) num_threads(nthreads)
    for (int64_t b = 0; b < nb; ++b) {
        block_t B;
        int64_t i0 = b * BLK;
        int m = load_block(&B, i0, n, iJM, iJL, CF, DF, s, MFC, muF, Mext, MFCM, muFM, wM, wL, dp, MM, Mref, phi, cntp, comp);
        /* a row with room for the whole block takes its pad lanes too: whole, aligned cache lines */
        size_t row = (size_t)(i0 + BLK <= ostride ? BLK : m) * sizeof(REAL);
        int32_t seg[BLK];
        for (int l = 0; l < BLK; ++l) {
            int64_t i = i0 + (l < m ? l : 0);
            int32_t j = 0;
            while (j + 1 < K && start[i * K + j + 1] <= k0) ++j;
            seg[l] = j;
        }
        int64_t next = k0;  /* the first sample at which a lane's segment may change */
        REAL wv[BLK];
        for (int64_t kk = 0; kk < nk; ++kk) {
            int64_t k = k0 + kk;
            if (quantize) {  /* two loops, not a select per lane: measured 1.2-1.6x faster */
                for (int l = 0; l < BLK; ++l) {
                    double c = floor(B.phi[l] * scale);
                    wv[l] = (REAL)((c - B.cntp[l]) * qw);
                    B.cntp[l] = c;
                }
            } else {
                for (int l = 0; l < BLK; ++l) {
                    double c = B.phi[l] * scale;
                    wv[l] = (REAL)((c - B.cntp[l]) * qw);
                    B.cntp[l] = c;
                }
            }
            memcpy(o_speed + kk * ostride + i0, wv, row);
            if (k >= next) {  /* segments are long: most samples skip this */
                next = INT64_MAX;
                for (int l = 0; l < BLK; ++l) {
                    int64_t i = i0 + (l < m ? l : 0);
                    while (seg[l] + 1 < K && start[i * K + seg[l] + 1] <= k) ++seg[l];
                    B.Mref[l] = lev[i * K + seg[l]];
                    if (seg[l] + 1 < K && start[i * K + seg[l] + 1] < next) next = start[i * K + seg[l] + 1];
                }
            }
            advance_block(&B, S, dt, h, k6, iTE);
        }
        store_block(&B, i0, m, n, wM, wL, dp, MM, Mref, phi, cntp, comp);
    }
}
