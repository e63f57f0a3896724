/* Rows of comma-separated numbers, parsed with the C library's strtod (the record reader's fast path,
   see sim/_csv.py, which declares the signature). REAL is unused: the kernel convention compiles
   every kernel once per float type. */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>

/* Parse up to `rows` rows of `ncols` numbers from text[0..n) into out (row-major). A row ends with
   '\n' (a '\r' before it and blanks around fields are allowed; empty lines are skipped). Returns the
   rows parsed, or -1 - r at the first row r that is not `ncols` numbers (the caller then reads the
   text with its reference parser, which names the problem). */
int64_t parse_rows(int64_t n, const int8_t *text, int32_t ncols, int64_t rows, double *out) {
    const char *p = (const char *)text, *end = p + n;
    int64_t r = 0;
    for (;;) {
        while (p < end && (*p == '\n' || *p == '\r' || *p == ' ' || *p == '\t')) ++p;
        if (p >= end) return r;
        if (r >= rows) return -1 - r;
        for (int32_t c = 0; c < ncols; ++c) {
            while (p < end && (*p == ' ' || *p == '\t')) ++p;
            if (p >= end || *p == '\n' || *p == ',') return -1 - r;
            char *q;
            double v = strtod(p, &q);  /* stops at the terminating NUL the caller appends at text[n] */
            if (q == p) return -1 - r;
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
