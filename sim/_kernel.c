/* Fused fixed-step two-mass kernel (see sim/_integrate_fast.py for the torch twin; the
   signatures are declared in sim/_kernel.py). Compiled once per float type: -DREAL=float or
   -DREAL=double. Every floating-point operation is written in the same order as the torch eager
   twin, compiled with -ffp-contract=off, so both give the same numbers. */
#ifndef REAL
#error "compile with -DREAL=float or -DREAL=double"
#endif
#include <math.h>
#include <stdint.h>

#define BLK 32

typedef struct {
    REAL iJM[BLK], iJL[BLK], CF[BLK], DF[BLK], s[BLK], MFC[BLK], muF[BLK], Mext[BLK];
    REAL wM[BLK], wL[BLK], dp[BLK], MM[BLK], Mref[BLK];
    REAL cwM[BLK], cwL[BLK], cdp[BLK], cMM[BLK];  /* Kahan compensations */
    double phi[BLK], cntp[BLK];
} block_t;

static inline void rhs(REAL wM, REAL wL, REAL dp, REAL MM, REAL Mref, REAL Mext, int stuck, REAL fric,
                       REAL iJM, REAL iJL, REAL CF, REAL DF, REAL s, REAL muF, REAL iTE,
                       REAL *a, REAL *b, REAL *c, REAL *d) {
    REAL cl = dp < -s ? -s : dp;
    cl = cl > s ? s : cl;
    REAL e = dp - cl;
    REAL MS = CF * e + (e != (REAL)0 ? DF * (wM - wL) : (REAL)0);
    *a = (MM - MS) * iJM;
    *b = stuck ? (REAL)0 : (MS - Mext - fric - muF * wL) * iJL;
    *c = wM - wL;
    *d = (Mref - MM) * iTE;
}

/* S substeps of RK4 for all lanes of a block; the motor-angle increment goes to phi. */
static inline void advance_block(block_t *B, int S, REAL dt, REAL h, REAL k6, REAL iTE) {
    REAL inc[BLK];
    for (int l = 0; l < BLK; ++l) inc[l] = 0;
    for (int j = 0; j < S; ++j) {
#pragma GCC ivdep
        for (int l = 0; l < BLK; ++l) {
            REAL wM = B->wM[l], wL = B->wL[l], dp = B->dp[l], MM = B->MM[l];
            REAL s = B->s[l];
            REAL cl = dp < -s ? -s : dp;
            cl = cl > s ? s : cl;
            REAL e = dp - cl;
            REAL MS = B->CF[l] * e + (e != (REAL)0 ? B->DF[l] * (wM - wL) : (REAL)0);
            REAL net = MS - B->Mext[l];
            int rest = wL == (REAL)0;
            REAL anet = net < 0 ? -net : net;
            int stuck = rest && (anet <= B->MFC[l]);
            REAL sn = (REAL)((net > 0) - (net < 0));
            REAL sw = (REAL)((wL > 0) - (wL < 0));
            REAL sgn = rest ? sn : sw;
            REAL fric = B->MFC[l] * sgn;
            REAL a1, b1, c1, d1, a2, b2, c2, d2, a3, b3, c3, d3, a4, b4, c4, d4;
            rhs(wM, wL, dp, MM, B->Mref[l], B->Mext[l], stuck, fric, B->iJM[l], B->iJL[l], B->CF[l], B->DF[l], s, B->muF[l], iTE, &a1, &b1, &c1, &d1);
            REAL wM2 = wM + h * a1, wL2 = wL + h * b1, dp2 = dp + h * c1, MM2 = MM + h * d1;
            rhs(wM2, wL2, dp2, MM2, B->Mref[l], B->Mext[l], stuck, fric, B->iJM[l], B->iJL[l], B->CF[l], B->DF[l], s, B->muF[l], iTE, &a2, &b2, &c2, &d2);
            REAL wM3 = wM + h * a2, wL3 = wL + h * b2, dp3 = dp + h * c2, MM3 = MM + h * d2;
            rhs(wM3, wL3, dp3, MM3, B->Mref[l], B->Mext[l], stuck, fric, B->iJM[l], B->iJL[l], B->CF[l], B->DF[l], s, B->muF[l], iTE, &a3, &b3, &c3, &d3);
            REAL wM4 = wM + dt * a3, wL4 = wL + dt * b3, dp4 = dp + dt * c3, MM4 = MM + dt * d3;
            rhs(wM4, wL4, dp4, MM4, B->Mref[l], B->Mext[l], stuck, fric, B->iJM[l], B->iJL[l], B->CF[l], B->DF[l], s, B->muF[l], iTE, &a4, &b4, &c4, &d4);
            inc[l] = inc[l] + k6 * (wM + (REAL)2 * wM2 + (REAL)2 * wM3 + wM4);
            REAL y, t;
            y = k6 * (a1 + (REAL)2 * a2 + (REAL)2 * a3 + a4) - B->cwM[l];
            t = wM + y; B->cwM[l] = (t - wM) - y; B->wM[l] = t;
            y = k6 * (b1 + (REAL)2 * b2 + (REAL)2 * b3 + b4) - B->cwL[l];
            t = wL + y;
            int clamp = stuck || t * sgn < (REAL)0;
            B->cwL[l] = clamp ? (REAL)0 : (t - wL) - y;
            B->wL[l] = clamp ? (REAL)0 : t;
            y = k6 * (c1 + (REAL)2 * c2 + (REAL)2 * c3 + c4) - B->cdp[l];
            t = dp + y; B->cdp[l] = (t - dp) - y; B->dp[l] = t;
            y = k6 * (d1 + (REAL)2 * d2 + (REAL)2 * d3 + d4) - B->cMM[l];
            t = MM + y; B->cMM[l] = (t - MM) - y; B->MM[l] = t;
        }
    }
    for (int l = 0; l < BLK; ++l) B->phi[l] = B->phi[l] + (double)inc[l];
}

static inline int load_block(block_t *B, int64_t i0, int64_t n,
                             const REAL *iJM, const REAL *iJL, const REAL *CF, const REAL *DF, const REAL *s,
                             const REAL *MFC, const REAL *muF, const REAL *Mext,
                             const REAL *wM, const REAL *wL, const REAL *dp, const REAL *MM, const REAL *Mref,
                             const double *phi, const double *cntp, const REAL *comp) {
    int m = (int)((n - i0) < BLK ? (n - i0) : BLK);
    for (int l = 0; l < BLK; ++l) {
        int64_t i = i0 + (l < m ? l : 0);  /* pad lanes repeat lane 0 */
        B->iJM[l] = iJM[i]; B->iJL[l] = iJL[i]; B->CF[l] = CF[i]; B->DF[l] = DF[i]; B->s[l] = s[i];
        B->MFC[l] = MFC[i]; B->muF[l] = muF[i]; B->Mext[l] = Mext[i];
        B->wM[l] = wM[i]; B->wL[l] = wL[i]; B->dp[l] = dp[i]; B->MM[l] = MM[i]; B->Mref[l] = Mref[i];
        B->phi[l] = phi[i]; B->cntp[l] = cntp[i];
        B->cwM[l] = comp[4 * i]; B->cwL[l] = comp[4 * i + 1]; B->cdp[l] = comp[4 * i + 2]; B->cMM[l] = comp[4 * i + 3];
    }
    return m;
}

static inline void store_block(const block_t *B, int64_t i0, int m, REAL *wM, REAL *wL, REAL *dp, REAL *MM,
                               REAL *Mref, double *phi, double *cntp, REAL *comp) {
    for (int l = 0; l < m; ++l) {
        int64_t i = i0 + l;
        wM[i] = B->wM[l]; wL[i] = B->wL[l]; dp[i] = B->dp[l]; MM[i] = B->MM[l]; Mref[i] = B->Mref[l];
        phi[i] = B->phi[l]; cntp[i] = B->cntp[l];
        comp[4 * i] = B->cwM[l]; comp[4 * i + 1] = B->cwL[l]; comp[4 * i + 2] = B->cdp[l]; comp[4 * i + 3] = B->cMM[l];
    }
}

/* One sample for n systems: S substeps with the applied Mref; phi accumulates the angle. */
void advance(int64_t n, int S, REAL dt, REAL h, REAL k6, REAL iTE, int nthreads,
             const REAL *iJM, const REAL *iJL, const REAL *CF, const REAL *DF, const REAL *s,
             const REAL *MFC, const REAL *muF, const REAL *Mext,
             REAL *wM, REAL *wL, REAL *dp, REAL *MM, REAL *Mref, double *phi, double *cntp, REAL *comp) {
    int64_t nb = (n + BLK - 1) / BLK;
#pragma omp parallel for schedule(static) num_threads(nthreads)
    for (int64_t b = 0; b < nb; ++b) {
        block_t B;
        int m = load_block(&B, b * BLK, n, iJM, iJL, CF, DF, s, MFC, muF, Mext, wM, wL, dp, MM, Mref, phi, cntp, comp);
        advance_block(&B, S, dt, h, k6, iTE);
        store_block(&B, b * BLK, m, wM, wL, dp, MM, Mref, phi, cntp, comp);
    }
}

/* Up to nk samples (k0 .. k0+nk-1) of the switching test (SPEC 2) for n systems, fused:
   measure, record, controller step, advance. Controller state per system: sec (1..6, 7 tail,
   8 done), cnt (samples in section), nI, nIV, len (record length once done), tmo (bit per
   section that timed out). Returns the number of systems not yet done. */
int64_t run_test(int64_t n, int S, REAL dt, REAL h, REAL k6, REAL iTE, int nthreads,
                 const REAL *iJM, const REAL *iJL, const REAL *CF, const REAL *DF, const REAL *s,
                 const REAL *MFC, const REAL *muF, const REAL *Mext,
                 REAL *wM, REAL *wL, REAL *dp, REAL *MM, REAL *Mref, double *phi, double *cntp, REAL *comp,
                 int32_t *sec, int32_t *cnt, int32_t *nI, int32_t *nIV, int32_t *len, int32_t *tmo,
                 double qw, double scale, REAL Mstar, REAL Mlow, REAL wmax, REAL wlow, REAL Mmax,
                 int32_t n_timeout, int32_t n_tail, int64_t k0, int64_t nk, int64_t ostride, int64_t ocol0,
                 REAL *o_speed, REAL *o_torque, REAL *o_tref, int8_t *o_sec) {
    int64_t nb = (n + BLK - 1) / BLK;
    int64_t left = 0;
#pragma omp parallel for schedule(dynamic, 1) num_threads(nthreads) reduction(+:left)
    for (int64_t b = 0; b < nb; ++b) {
        block_t B;
        int64_t i0 = b * BLK;
        int m = load_block(&B, i0, n, iJM, iJL, CF, DF, s, MFC, muF, Mext, wM, wL, dp, MM, Mref, phi, cntp, comp);
        int32_t csec[BLK], ccnt[BLK], cnI[BLK], cnIV[BLK], clen[BLK], ctmo[BLK];
        for (int l = 0; l < BLK; ++l) {
            int64_t i = i0 + (l < m ? l : 0);
            csec[l] = l < m ? sec[i] : 8; ccnt[l] = cnt[i]; cnI[l] = nI[i]; cnIV[l] = nIV[i];
            clen[l] = len[i]; ctmo[l] = tmo[i];
        }
        REAL newref[BLK];
        for (int64_t kk = 0; kk < nk; ++kk) {
            int64_t k = k0 + kk;
            int active = 0;
            for (int l = 0; l < BLK; ++l) newref[l] = B.Mref[l];
            for (int l = 0; l < m; ++l) {
                if (csec[l] >= 8) continue;
                active = 1;
                double c = floor(B.phi[l] * scale);
                REAL w = (REAL)((c - B.cntp[l]) * qw);
                B.cntp[l] = c;
                int64_t o = (i0 + l) * ostride + ocol0 + kk;
                o_speed[o] = w; o_torque[o] = B.MM[l]; o_tref[o] = B.Mref[l];
                o_sec[o] = (int8_t)(csec[l] == 7 ? 0 : csec[l]);
                int q = csec[l];
                int32_t t = ccnt[l] + 1;
                int end;
                switch (q) {
                    case 1: end = w >= wmax; break;
                    case 2: end = (t >= cnI[l]) || (w <= wlow); break;
                    case 3: end = w <= (REAL)0; break;
                    case 4: end = w <= -wmax; break;
                    case 5: end = (t >= cnIV[l]) || (w >= -wlow); break;
                    case 6: end = w >= (REAL)0; break;
                    default: end = t >= n_tail; break;
                }
                if (!end && q <= 6 && t >= n_timeout) { end = 1; ctmo[l] |= (1 << (q - 1)); }
                if (end) {
                    if (q == 1) cnI[l] = t;
                    if (q == 4) cnIV[l] = t;
                    q += 1; t = 0;
                    if (q == 8) clen[l] = (int32_t)(k + 1);
                }
                csec[l] = q; ccnt[l] = t;
                REAL mr = (q == 1) ? Mstar : (q == 3) ? -Mlow : (q == 4) ? -Mstar
                        : (q == 6) ? Mlow : (REAL)0;
                mr = mr < -Mmax ? -Mmax : mr;
                mr = mr > Mmax ? Mmax : mr;
                newref[l] = mr;
            }
            if (!active) break;
            advance_block(&B, S, dt, h, k6, iTE);
            for (int l = 0; l < BLK; ++l) B.Mref[l] = newref[l];
        }
        for (int l = 0; l < m; ++l) {
            int64_t i = i0 + l;
            sec[i] = csec[l]; cnt[i] = ccnt[l]; nI[i] = cnI[l]; nIV[i] = cnIV[l]; len[i] = clen[l]; tmo[i] = ctmo[l];
            left += csec[l] < 8;
        }
        store_block(&B, i0, m, wM, wL, dp, MM, Mref, phi, cntp, comp);
    }
    return left;
}

/* Open-loop replay of a piecewise-constant torque reference for n systems, fused: measure,
   record the speed, set M_ref, advance. System i applies lev[i*K + j] over samples
   start[i*K + j] <= k < start[i*K + j + 1] (start ascending; the last segment runs to the end).
   Writes the speed of samples k0 .. k0+nk-1 time-major to o_speed[(k - k0)*n + i]: the encoder's
   (quantized) when quantize is set, else the mean motor speed over the past sample interval
   (the expected value of the encoder's, for fits). */
void run_replay(int64_t n, int S, REAL dt, REAL h, REAL k6, REAL iTE, int nthreads,
                const REAL *iJM, const REAL *iJL, const REAL *CF, const REAL *DF, const REAL *s,
                const REAL *MFC, const REAL *muF, const REAL *Mext,
                REAL *wM, REAL *wL, REAL *dp, REAL *MM, REAL *Mref, double *phi, double *cntp, REAL *comp,
                double qw, double scale, int32_t quantize, int32_t K, const int32_t *start, const REAL *lev,
                int64_t k0, int64_t nk, REAL *o_speed) {
    int64_t nb = (n + BLK - 1) / BLK;
#pragma omp parallel for schedule(dynamic, 1) num_threads(nthreads)
    for (int64_t b = 0; b < nb; ++b) {
        block_t B;
        int64_t i0 = b * BLK;
        int m = load_block(&B, i0, n, iJM, iJL, CF, DF, s, MFC, muF, Mext, wM, wL, dp, MM, Mref, phi, cntp, comp);
        int32_t seg[BLK];
        for (int l = 0; l < BLK; ++l) {
            int64_t i = i0 + (l < m ? l : 0);
            int32_t j = 0;
            while (j + 1 < K && start[i * K + j + 1] <= k0) ++j;
            seg[l] = j;
        }
        for (int64_t kk = 0; kk < nk; ++kk) {
            int64_t k = k0 + kk;
            for (int l = 0; l < BLK; ++l) {
                int64_t i = i0 + (l < m ? l : 0);
                double c = quantize ? floor(B.phi[l] * scale) : B.phi[l] * scale;
                REAL w = (REAL)((c - B.cntp[l]) * qw);
                B.cntp[l] = c;
                if (l < m) o_speed[kk * n + i0 + l] = w;
                while (seg[l] + 1 < K && start[i * K + seg[l] + 1] <= k) ++seg[l];
                B.Mref[l] = lev[i * K + seg[l]];
            }
            advance_block(&B, S, dt, h, k6, iTE);
        }
        store_block(&B, i0, m, wM, wL, dp, MM, Mref, phi, cntp, comp);
    }
}
