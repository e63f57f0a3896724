/* Rows of comma-separated numbers, parsed by Clinger's fast path, an x87 extended-precision path or
   else the C library's strtod, each the double strtod gives (the record reader's fast path, see
   sim/_csv.py, which declares the signature). REAL is unused: the kernel convention compiles every
   kernel once per float type. */
#include <float.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* x87 extended precision (a 64-bit significand, stored first, little-endian): decimals of up to 19
   digits, such as the %.17g time column, need no strtod (see extended_decimal) */
#if LDBL_MANT_DIG == 64 && (defined(__x86_64__) || defined(__i386__))
#define EXTENDED 1
#endif

#ifdef EXTENDED
/* m * 10^e for m < 2^64 and |e| <= 27 (m and 10^|e| = 2^|e| 5^|e| are exact in a 64-bit
   significand, so the product or quotient is rounded once, to 64 bits) as the correctly rounded
   double, or 0 where that second rounding to 53 bits could differ from one rounding of the exact
   value: where the 64-bit result lies on, or next to, the midpoint of two doubles (its 11 lowest
   significand bits 0x3ff-0x401; the exact value lies within half a unit of the 64th bit). */
static int extended_decimal(uint64_t m, int e, double *value) {
    static const long double pow10[28] = {1e0L, 1e1L, 1e2L, 1e3L, 1e4L, 1e5L, 1e6L, 1e7L, 1e8L, 1e9L, 1e10L,
                                          1e11L, 1e12L, 1e13L, 1e14L, 1e15L, 1e16L, 1e17L, 1e18L, 1e19L, 1e20L,
                                          1e21L, 1e22L, 1e23L, 1e24L, 1e25L, 1e26L, 1e27L};
    if (e < -27 || e > 27) return 0;
    const long double x = e >= 0 ? (long double)m * pow10[e] : (long double)m / pow10[-e];
    uint64_t significand;
    memcpy(&significand, &x, sizeof significand);
    const unsigned low = (unsigned)(significand & 0x7ff);
    if (low >= 0x3ff && low <= 0x401) return 0;
    *value = (double)x;
    return 1;
}
#endif

/* Clinger's fast path: a plain decimal [sign] digits [. digits] [e [sign] digits] whose digits form an
   integer m <= 2^53 and whose decimal exponent e has |e| <= 22 is m * 10^e or m / 10^-e, both exact
   operands, so one IEEE operation rounds it correctly: the same double as strtod; other decimals of
   up to 19 digits go through extended_decimal where it exists. Sets *end past the number and returns
   1, or returns 0 (anything else: strtod decides). */
static int fast_decimal(const char *p, const char **end, double *value) {
    static const double pow10[23] = {1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11,
                                     1e12, 1e13, 1e14, 1e15, 1e16, 1e17, 1e18, 1e19, 1e20, 1e21, 1e22};
    const int negative = *p == '-';
    if (*p == '-' || *p == '+') ++p;
    uint64_t m = 0;
    int digits = 0, seen = 0, e = 0, dot = 0;
    for (;; ++p) {  /* the digits before and after one '.': the ones after lower the exponent */
        if (*p == '.' && !dot) {
            dot = 1;
            continue;
        }
        if (!(*p >= '0' && *p <= '9')) break;
        ++seen;
        e -= dot;
        if (m || *p != '0') ++digits;
        if (digits > 19) return 0;
        m = 10 * m + (uint64_t)(*p - '0');
    }
    if (!seen) return 0;
    if (*p == 'e' || *p == 'E') {
        const char *q = p + 1;
        const int negative_e = *q == '-';
        if (*q == '-' || *q == '+') ++q;
        if (!(*q >= '0' && *q <= '9')) return 0;
        int x = 0;
        for (; *q >= '0' && *q <= '9'; ++q) {
            if (x > 1000) return 0;
            x = 10 * x + (*q - '0');
        }
        e += negative_e ? -x : x;
        p = q;
    }
    double v;
    if (m <= (UINT64_C(1) << 53) && e >= -22 && e <= 22)
        v = e >= 0 ? (double)m * pow10[e] : (double)m / pow10[-e];
#ifdef EXTENDED
    else if (!extended_decimal(m, e, &v))
        return 0;
#else
    else
        return 0;
#endif
    *value = negative ? -v : v;
    *end = p;
    return 1;
}

/* Parse up to `rows` rows of `ncols` numbers from text[0..n) into out (row-major). A row ends with
   '\n' (a '\r' before it and blanks around fields are allowed; empty lines are skipped). Returns the
   rows parsed, or -1 - r at the first row r that is not `ncols` numbers (the caller then reads the
   text with its reference parser, which names the problem by its line). */
int64_t parse_rows(int64_t n, const int8_t *text, int32_t ncols, int64_t rows, double *out) {
    const char *p = (const char *)text, *end = p + n;
    int64_t r = 0;
    for (;;) {
        while (p < end && (*p == '\n' || *p == '\r' || *p == ' ' || *p == '\t')) ++p;
        if (p >= end) return r;
        if (r >= rows) return -1 - r;
        for (int32_t c = 0; c < ncols; ++c) {
            while (p < end && (*p == ' ' || *p == '\t')) ++p;
            /* an empty field, or a line break strtod would skip: a row never continues on the next line */
            if (p >= end || *p == '\n' || *p == '\r' || *p == '\v' || *p == '\f' || *p == ',') return -1 - r;
            const char *q;
            double v;
            if (!fast_decimal(p, &q, &v)) {  /* both stop at the terminating NUL the caller appends */
                char *s;
                v = strtod(p, &s);
                if (s == p) return -1 - r;
                q = s;
            }
            out[r * ncols + c] = v;
            p = q;
            while (p < end && (*p == ' ' || *p == '\t')) ++p;
            if (c + 1 < ncols) {
                if (p >= end || *p != ',') return -1 - r;
                ++p;
            }
        }
        while (p < end && (*p == ' ' || *p == '\t' || *p == '\r')) ++p;
        if (p < end && *p != '\n') return -1 - r;
        ++r;
    }
}

/* Write `rows` rows of `ncols` numbers (row-major `data`) as text into out[0..cap): per column
   `digits[c]` significant digits in %g notation, or 0 for an integer (%lld of the value truncated,
   as Python's "%d"); fields joined by ',' and rows ended by '\n'. Returns the bytes written, or -1
   when `cap` is too small. */
int64_t format_rows(int64_t rows, int32_t ncols, const double *data, const int32_t *digits, int64_t cap,
                    int8_t *out) {
    char *p = (char *)out, *end = p + cap;
    for (int64_t r = 0; r < rows; ++r) {
        for (int32_t c = 0; c < ncols; ++c) {
            const double v = data[r * ncols + c];
            const int room = (int)(end - p < 64 ? end - p : 64);
            int k = digits[c] > 0 ? snprintf(p, (size_t)room, "%.*g", digits[c], v)
                                  : snprintf(p, (size_t)room, "%lld", (long long)v);
            if (k < 0 || k + 1 >= room) return -1;
            p += k;
            *p++ = c + 1 < ncols ? ',' : '\n';
        }
    }
    return (int64_t)(p - (char *)out);
}
