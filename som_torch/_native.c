/* The online SOM rule, one call per epoch (see som_torch/_native.py, which declares the signature).
   Compiled once per float type: -DREAL=float or -DREAL=double (EXP is expf or exp to match). */
#ifndef REAL
#error "compile with -DREAL=float or -DREAL=double"
#endif
#include <math.h>
#include <stddef.h>

#define EXP(x) _Generic((x), float: expf, default: exp)(x)
/* Below this argument exp is under the smallest normal number: the neighbourhood weight is 0 there
   (the vector exp then stays on its fast path, which underflowing lanes would leave). */
#define EXP_MIN ((REAL)(sizeof(REAL) == sizeof(float) ? -87 : -708))

/* w: B x C x U (transposed weights); x, valid: N x B x C; act: B x C; d2: U x U; lr, sg: N x B;
   kind: 0 gaussian, 1 bubble, 2 cut_gaussian, 3 epanechnikov; nthreads: OpenMP threads;
   dist_all, h_all: B x U scratch (one row per map); bmus: N x B.
   Maps are independent: the threads take one map at a time, each map's arithmetic is the same
   on any number of threads (bit-identical results). One pass over a map's weights per step: the
   update of step i also accumulates the distances of sample i+1 (known in advance) to the
   updated weights. */
void som_epoch(int B, int U, int C, int N, REAL *restrict w, const REAL *restrict x,
               const REAL *restrict valid, const REAL *restrict act, const REAL *restrict d2,
               const REAL *restrict lr, const REAL *restrict sg, int kind, int nthreads,
               REAL *restrict dist_all, REAL *restrict h_all, long long *restrict bmus)
{
#pragma omp parallel for schedule(dynamic, 1) num_threads(nthreads)
    for (int b = 0; b < B; ++b) {          /* maps are independent: one map's weights stay in cache */
        REAL *restrict dist = dist_all + (size_t)b * U, *restrict h = h_all + (size_t)b * U;
        REAL *restrict wb = w + (size_t)b * C * U;
        const REAL *restrict ab = act + (size_t)b * C;
        for (int u = 0; u < U; ++u) dist[u] = 0;
        {
            const REAL *restrict xv = x + (size_t)b * C;
            const REAL *restrict vv = valid ? valid + (size_t)b * C : NULL;
            for (int c = 0; c < C; ++c) {
                if (ab[c] == 0 || (vv && vv[c] == 0)) continue;
                const REAL xc = xv[c];
                const REAL *restrict wc = wb + (size_t)c * U;
                for (int u = 0; u < U; ++u) { REAL d = xc - wc[u]; dist[u] += d * d; }
            }
        }
        for (int i = 0; i < N; ++i) {
            const REAL *restrict xv = x + ((size_t)i * B + b) * C;
            const REAL *restrict vv = valid ? valid + ((size_t)i * B + b) * C : NULL;
            const REAL *restrict xn = i + 1 < N ? x + ((size_t)(i + 1) * B + b) * C : NULL;
            const REAL *restrict vn = (valid && xn) ? valid + ((size_t)(i + 1) * B + b) * C : NULL;
            REAL bd = dist[0];                 /* min (vectorizes), then its first index */
            for (int u = 1; u < U; ++u) bd = dist[u] < bd ? dist[u] : bd;
            int best = 0;
            while (dist[best] != bd) ++best;
            bmus[(size_t)i * B + b] = best;
            const REAL rate = lr[(size_t)i * B + b], s = sg[(size_t)i * B + b];
            const REAL *restrict row = d2 + (size_t)best * U;
            const REAL q = (REAL)(-0.5) / (s * s), s2 = s * s;
            if (kind == 0) {
                for (int u = 0; u < U; ++u) {
                    const REAL a = row[u] * q;
                    h[u] = a < EXP_MIN ? 0 : rate * EXP(a < EXP_MIN ? EXP_MIN : a);
                }
            } else {
                for (int u = 0; u < U; ++u) {
                    REAL r = row[u], v;
                    if (kind == 1) v = r <= s2 ? 1 : 0;
                    else if (kind == 2) v = r <= s2 ? EXP(r * q) : 0;
                    else { v = 1 - r / s2; v = v > 0 ? v : 0; }
                    h[u] = rate * v;
                }
            }
            for (int u = 0; u < U; ++u) dist[u] = 0;
            for (int c = 0; c < C; ++c) {
                REAL *restrict wc = wb + (size_t)c * U;
                const int move = !(vv && vv[c] == 0);
                const int next = xn && ab[c] != 0 && !(vn && vn[c] == 0);
                const REAL xc = xv[c], xnc = xn ? xn[c] : 0;
                if (move && next) {
                    for (int u = 0; u < U; ++u) {
                        REAL nw = wc[u] + h[u] * (xc - wc[u]);
                        wc[u] = nw;
                        REAL d = xnc - nw;
                        dist[u] += d * d;
                    }
                } else if (move) {
                    for (int u = 0; u < U; ++u) wc[u] += h[u] * (xc - wc[u]);
                } else if (next) {
                    for (int u = 0; u < U; ++u) { REAL d = xnc - wc[u]; dist[u] += d * d; }
                }
            }
        }
    }
}
