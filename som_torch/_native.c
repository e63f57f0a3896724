/* The online SOM rule, one call per epoch (see som_torch/_native.py, which declares the signature).
   Compiled once per float type: -DREAL=float or -DREAL=double (EXP is expf or exp to match). */
#ifndef REAL
#error "compile with -DREAL=float or -DREAL=double"
#endif
#include <math.h>
#include <stddef.h>
#include <stdlib.h>

#define EXP(x) _Generic((x), float: expf, default: exp)(x)
/* Below this argument exp is under the smallest normal number: the neighbourhood weight is 0 there
   (the vector exp then stays on its fast path, which underflowing lanes would leave). */
#define EXP_MIN ((REAL)(sizeof(REAL) == sizeof(float) ? -87 : -708))
/* The first best match is searched in chunks of SCAN units (a chunk's test vectorizes). */
#define SCAN 32

enum { MOVE = 1, NEXT = 2 };  /* a component in a step: its weights move; it counts in the next distance */

/* MOVE | NEXT of component c in a step: x_c present (vv: its validity, NULL: all); active and present
   in the next sample (xn: NULL at the epoch's last step; vn its validity). */
static inline int plan_of(int c, const REAL *vv, const REAL *xn, const REAL *vn, const REAL *ab)
{
    return !(vv && vv[c] == 0) * MOVE + (xn && ab[c] != 0 && !(vn && vn[c] == 0)) * NEXT;
}

#if defined(__GNUC__) && !defined(SOM_TORCH_SCALAR)  /* GCC and clang: vector extensions (else, or with
   -DSOM_TORCH_SCALAR, blocks of one unit in loops over units) */
#if defined(__AVX512F__)
#define VBYTES 64
#elif defined(__AVX__)
#define VBYTES 32
#else
#define VBYTES 16
#endif
typedef REAL vec __attribute__((vector_size(VBYTES)));
typedef REAL vec_u __attribute__((vector_size(VBYTES), aligned(sizeof(REAL)), may_alias));  /* any alignment */
#define NV 4  /* vectors per block: 4 independent sums over the components hide the FMA latency */
#define BLK (NV * (int)(VBYTES / sizeof(REAL)))

/* One step on the BLK units of a block (w: the block's BLK x C weights, component-major):
   the neighbourhood weights h and the next sample's distances stay in registers while the loop runs
   over the components, so each weight is loaded and stored once (the loops over units in som_epoch
   load h and the distances and store the distances again for every component). Per unit the same
   operations in the same order as those loops: the same numbers. */
static inline __attribute__((always_inline)) void pass_block(REAL *restrict w, int C,
        const unsigned char *restrict plan, const REAL *restrict xv, const REAL *restrict xn,
        const REAL *restrict h, REAL *restrict dist)
{
    vec hb[NV], db[NV];
    for (int k = 0; k < NV; ++k) {
        hb[k] = ((const vec_u *)h)[k];
        db[k] = (vec){0};
    }
    for (int c = 0; c < C; ++c) {
        vec_u *restrict wc = (vec_u *)(w + (size_t)c * BLK);
        if (plan[c] == (MOVE | NEXT)) {
            const REAL xc = xv[c], xnc = xn[c];
            for (int k = 0; k < NV; ++k) {
                vec a = wc[k];
                a = a + hb[k] * (xc - a);
                wc[k] = a;
                a = xnc - a;
                db[k] += a * a;
            }
        } else if (plan[c] == MOVE) {
            const REAL xc = xv[c];
            for (int k = 0; k < NV; ++k) wc[k] = wc[k] + hb[k] * (xc - wc[k]);
        } else if (plan[c] == NEXT) {
            const REAL xnc = xn[c];
            for (int k = 0; k < NV; ++k) {
                vec a = xnc - wc[k];
                db[k] += a * a;
            }
        }
    }
    for (int k = 0; k < NV; ++k) ((vec_u *)dist)[k] = db[k];
}
#define VECTORS 1
#else
#define BLK 1  /* no vector extensions: the blocked layout with one unit per block, no pass_block */
#endif

/* The gaussian weights h[u] = rate exp(-d_u^2 / (2 s^2)) of the units of a rows x cols grid around
   unit best, separably (MiniSom's form): exp(q dy^2) exp(q dx^2) with q = -1 / (2 s^2), dy the
   difference of the row coordinates yr, dx that of the column coordinates xc[r & 1] (hexagonal
   grids shift odd rows): rows + 2 cols exponentials per step instead of one per unit, and no U x U
   distance table. A unit whose q d^2 = q dy^2 + q dx^2 is below EXP_MIN gets 0. scratch: 2 rows +
   4 cols values (ar, er: rows; ac, ec: 2 cols), or NULL (it could not be allocated): the same formula
   unit by unit. */
static void gaussian_weights(int rows, int cols, const REAL *restrict yr, const REAL *restrict xc, int best,
                             REAL rate, REAL q, REAL *restrict scratch, REAL *restrict h)
{
    const int br = best / cols;
    const REAL yb = yr[br], xb = xc[(br & 1) * cols + best % cols];
    if (!scratch) {
        for (int u = 0; u < rows * cols; ++u) {
            const int r = u / cols;
            const REAL dy = yr[r] - yb, dx = xc[(r & 1) * cols + u % cols] - xb, ay = dy * dy * q, ax = dx * dx * q;
            h[u] = ay + ax < EXP_MIN ? 0 : (rate * EXP(ay < EXP_MIN ? EXP_MIN : ay)) * EXP(ax < EXP_MIN ? EXP_MIN : ax);
        }
        return;
    }
    REAL *restrict ar = scratch, *restrict er = ar + rows, *restrict ac = er + rows, *restrict ec = ac + 2 * cols;
    for (int r = 0; r < rows; ++r) {
        const REAL d = yr[r] - yb, a = d * d * q;
        ar[r] = a;
        er[r] = rate * EXP(a < EXP_MIN ? EXP_MIN : a);
    }
    for (int c = 0; c < 2 * cols; ++c) {
        const REAL d = xc[c] - xb, a = d * d * q;
        ac[c] = a;
        ec[c] = EXP(a < EXP_MIN ? EXP_MIN : a);
    }
    for (int r = 0; r < rows; ++r) {
        const REAL a = ar[r], e = er[r];
        const REAL *restrict acr = ac + (r & 1) * cols, *restrict ecr = ec + (r & 1) * cols;
        REAL *restrict hr = h + (size_t)r * cols;
        for (int c = 0; c < cols; ++c) hr[c] = a + acr[c] < EXP_MIN ? 0 : e * ecr[c];
    }
}

/* Units per block of the weights' layout (BLK: 4 vectors of this build): the caller lays the weights out in blocks. */
int som_lanes(void) { return BLK; }

/* Weight of unit u, component c, in a map's blocked weights (NB x C x BLK). */
#define W(wb, u, c, C) ((wb)[((size_t)((u) / BLK) * (C) + (c)) * BLK + (u) % BLK])

/* NB, L: the caller's blocks of units (NB = ceil(U / L), L = som_lanes(); the call returns -1 where they
   do not fit U and this build, else 0); w: B x NB x C x L (the weights in blocks of L units,
   component-major within a block, so that each block's weights are contiguous; units from U on are
   padding); x, valid: N x B x C; act: B x C; the grid: rows x cols = U units, row coordinates yr
   (rows), column coordinates xc (2 x cols: even, odd rows); d2: U x U squared grid distances (NULL
   for the gaussian, which needs only yr and xc); lr, sg: N x B; kind: 0 gaussian, 1 bubble,
   2 cut_gaussian, 3 epanechnikov; nthreads: OpenMP threads; dist_all, h_all: B x NB x L scratch (one
   row per map); bmus: N x B. Maps are independent: the threads take one map at a time, each map's
   arithmetic is the same on any number of threads (bit-identical results). One pass over a map's
   weights per step: the update of step i also accumulates the distances of sample i+1 (known in
   advance) to the updated weights; block by block (pass_block), or where the plan cannot be
   allocated in loops over units, with the same numbers. Padding units get the neighbourhood weight
   0 (their weights stay) and never win the best match. */
int som_epoch(int B, int U, int C, int N, int NB, int L, REAL *restrict w, const REAL *restrict x,
               const REAL *restrict valid, const REAL *restrict act, int rows, int cols,
               const REAL *restrict yr, const REAL *restrict xc, const REAL *restrict d2,
               const REAL *restrict lr, const REAL *restrict sg, int kind, int nthreads,
               REAL *restrict dist_all, REAL *restrict h_all, long long *restrict bmus)
{
    if (L != BLK || NB != (U + BLK - 1) / BLK) return -1;
    const int UP = NB * BLK;
#pragma omp parallel for schedule(dynamic, 1) num_threads(nthreads)
    for (int b = 0; b < B; ++b) {          /* maps are independent: one map's weights stay in cache */
        REAL *restrict dist = dist_all + (size_t)b * UP, *restrict h = h_all + (size_t)b * UP;
        REAL *restrict wb = w + (size_t)b * C * UP;
        const REAL *restrict ab = act + (size_t)b * C;
#ifdef VECTORS
        unsigned char *plan = malloc((size_t)C);  /* per component: MOVE | NEXT (NULL: loops over units) */
#endif
        REAL *axes = kind == 0 ? malloc(sizeof(REAL) * (size_t)(2 * rows + 4 * cols)) : NULL;  /* gaussian scratch */
        for (int u = 0; u < UP; ++u) dist[u] = 0;
        for (int u = U; u < UP; ++u) h[u] = 0;  /* padding: weight 0 (each step rewrites h[0..U)) */
        {
            const REAL *restrict xv = x + (size_t)b * C;
            const REAL *restrict vv = valid ? valid + (size_t)b * C : NULL;
            for (int k = 0; k < NB; ++k) {
                for (int c = 0; c < C; ++c) {
                    if (ab[c] == 0 || (vv && vv[c] == 0)) continue;
                    const REAL xvc = xv[c];
                    const REAL *restrict wc = wb + ((size_t)k * C + c) * BLK;
                    REAL *restrict dk = dist + (size_t)k * BLK;
                    for (int l = 0; l < BLK; ++l) { REAL d = xvc - wc[l]; dk[l] += d * d; }
                }
            }
        }
        for (int i = 0; i < N; ++i) {
            const REAL *restrict xv = x + ((size_t)i * B + b) * C;
            const REAL *restrict vv = valid ? valid + ((size_t)i * B + b) * C : NULL;
            const REAL *restrict xn = i + 1 < N ? x + ((size_t)(i + 1) * B + b) * C : NULL;
            const REAL *restrict vn = (valid && xn) ? valid + ((size_t)(i + 1) * B + b) * C : NULL;
            REAL bd = dist[0];                 /* min over the U units (vectorizes), then its first index */
            for (int u = 1; u < U; ++u) bd = dist[u] < bd ? dist[u] : bd;
            int best = 0;
            for (int hit = 0; best + SCAN <= U; best += SCAN) {
                for (int j = 0; j < SCAN; ++j) hit |= dist[best + j] == bd;
                if (hit) break;
            }
            while (dist[best] != bd) ++best;
            bmus[(size_t)i * B + b] = best;
            const REAL rate = lr[(size_t)i * B + b], s = sg[(size_t)i * B + b];
            const REAL q = (REAL)(-0.5) / (s * s), s2 = s * s;
            if (kind == 0) {
                gaussian_weights(rows, cols, yr, xc, best, rate, q, axes, h);
            } else {
                const REAL *restrict row = d2 + (size_t)best * U;
                for (int u = 0; u < U; ++u) {
                    REAL r = row[u], v;
                    if (kind == 1) v = r <= s2 ? 1 : 0;
                    else if (kind == 2) v = r <= s2 ? EXP(r * q) : 0;
                    else { v = 1 - r / s2; v = v > 0 ? v : 0; }
                    h[u] = rate * v;
                }
            }
#ifdef VECTORS
            if (plan) {
                for (int c = 0; c < C; ++c) plan[c] = (unsigned char)plan_of(c, vv, xn, vn, ab);
                for (int k = 0; k < NB; ++k)
                    pass_block(wb + (size_t)k * C * BLK, C, plan, xv, xn, h + (size_t)k * BLK, dist + (size_t)k * BLK);
                continue;
            }
#endif
            for (int u = 0; u < UP; ++u) dist[u] = 0;
            for (int c = 0; c < C; ++c) {
                const int how = plan_of(c, vv, xn, vn, ab), move = how & MOVE, next = how & NEXT;
                const REAL xvc = xv[c], xnc = xn ? xn[c] : 0;
                for (int u = 0; u < UP; ++u) {
                    REAL *restrict wu = &W(wb, u, c, C);
                    if (move) *wu += h[u] * (xvc - *wu);
                    if (next) { REAL d = xnc - *wu; dist[u] += d * d; }
                }
            }
        }
#ifdef VECTORS
        free(plan);
#endif
        free(axes);
    }
    return 0;
}
