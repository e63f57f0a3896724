/* ZOH responses of the resonance filter s / (s^2 + 2 d w0 s + w0^2) to one sampled torque, for
   many (coefficient) sets at once (see training/identification/_resonance.py, which declares the
   signature and holds the numpy reference). Compiled once per float type (REAL); the work is in
   double. */
#include <math.h>
#include <stdint.h>

/* out[k, i] for i < n: x[i] = c_k (M[i-1] - M[i-2]) + a1_k x[i-1] - a2_k x[i-2] (M, x zero before
   0), values below 1e-150 in magnitude set to 0 (decayed transients would end in subnormals, which
   make the arithmetic that follows 100x slower). */
#define LANES 8  /* filters run side by side: independent recursions fill the pipeline */

void zoh_responses(int64_t n, const double *M, int64_t K, const double *c, const double *a1, const double *a2,
                   double *out) {
    for (int64_t k0 = 0; k0 < K; k0 += LANES) {
        const int m = (int)(K - k0 < LANES ? K - k0 : LANES);
        if (m == 1) {  /* one filter alone: the plain recursion */
            double *x = out + k0 * n, x1 = 0.0, x2 = 0.0, m1 = 0.0, m2 = 0.0;
            for (int64_t i = 0; i < n; ++i) {
                double u = c[k0] * (m1 - m2) + a1[k0] * x1 - a2[k0] * x2;
                x[i] = fabs(u) < 1e-150 ? 0.0 : u;
                x2 = x1; x1 = x[i];
                m2 = m1; m1 = M[i];
            }
            continue;
        }
        double ck[LANES], p[LANES], q[LANES], x1[LANES], x2[LANES];
        for (int j = 0; j < LANES; ++j) {
            const int64_t k = k0 + (j < m ? j : 0);  /* pad lanes repeat the first */
            ck[j] = c[k]; p[j] = a1[k]; q[j] = a2[k]; x1[j] = 0.0; x2[j] = 0.0;
        }
        double m1 = 0.0, m2 = 0.0;
        for (int64_t i = 0; i < n; ++i) {
            const double dm = m1 - m2;
            double v[LANES];
            for (int j = 0; j < LANES; ++j) {
                double u = ck[j] * dm + p[j] * x1[j] - q[j] * x2[j];
                v[j] = fabs(u) < 1e-150 ? 0.0 : u;
                x2[j] = x1[j]; x1[j] = v[j];
            }
            for (int j = 0; j < m; ++j) out[(k0 + j) * n + i] = v[j];
            m2 = m1; m1 = M[i];
        }
    }
}
