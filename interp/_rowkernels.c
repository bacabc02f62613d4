/* Compiled render kernels of the pair interpolators (posecast.interp._rowkernels).
 *
 * A receiver's render frame brackets every remote stream at its playout time and
 * interpolates each bracket with the pair methods. In numpy that is about fifty
 * calls on a few dozen poses, each costing more than its arithmetic; here it is
 * two calls:
 *
 *   bracket_rows  the bracket of every row of a padded time table at once (the
 *                 rule of client.render._bracket_rows / StreamBuffer.bracket)
 *   pair_rows     soa, motor-lerp or dq-slerp of every bracket, reading the
 *                 keyframes where they lie, a pose table (N, 7) (interp.kernels'
 *                 soa_rows, motor_lerp_rows, dq_slerp_rows on gathered rows)
 *   render_rows   both in one call, every method of a frame
 *   Renderer      a room's tables held between frames: render_rows taking only
 *                 the frame's own arrays
 *
 * The numpy kernels are the reference. The formulas, their half-angle sines and
 * the order of their sums are theirs; the elementary functions are libm's, which
 * numpy's may not be (SIMD builds), so results agree to float rounding (bit for
 * bit where numpy calls libm). s = 0 and s = 1 give the keyframes bit for bit. interp/accel.py picks which
 * path runs; tests compare both. Built without FMA contraction (setup.py).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

#ifndef SOURCE_HASH
#define SOURCE_HASH "unknown"
#endif

enum { SOA = 0, MOTOR_LERP = 1, DQ_SLERP = 2 };

/* ------------------------------------------------------------------ buffers */

/* Whether a buffer's items are of the struct format char ``c`` (native order). */
static int format_is(const Py_buffer *v, const char *chars) {
    const char *f = v->format ? v->format : "B";
    if (*f == '@' || *f == '=' || *f == '<') f++;
    return f[0] != 0 && f[1] == 0 && strchr(chars, f[0]) != NULL;
}

/* A C-contiguous buffer of ``ndim`` dimensions whose items are one of ``chars``
 * and ``itemsize`` bytes (writable if asked); -1 with TypeError otherwise. */
static int get_buffer(PyObject *o, Py_buffer *v, int writable, int ndim, const char *chars,
                      Py_ssize_t itemsize, const char *name) {
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(o, v, flags) < 0) {
        PyErr_Clear();
        PyErr_Format(PyExc_TypeError, "%s: expected a C-contiguous%s array", name,
                     writable ? " writeable" : "");
        return -1;
    }
    if (v->ndim != ndim || v->itemsize != itemsize || !format_is(v, chars)) {
        PyErr_Format(PyExc_TypeError, "%s: expected a %d-d array of %s", name, ndim,
                     chars[0] == 'd' ? "float64" : chars[0] == '?' ? "bool" : "intp");
        PyBuffer_Release(v);
        return -1;
    }
    return 0;
}

#define INTP "lqn"

/* ------------------------------------------------------------------ bracket_rows */

/* Row i's keyframes are times[base[i] .. newest[i]] (sorted, at least one), its
 * playout time t[i]: lo, hi, s and whether it stalled, as client.render does it
 * (hold the newest past it and before the first; exactly on a keyframe is no
 * stall). lo_out holds a guess on entry (any value). Returns whether any bracket
 * is held or has s == 1. */
static int bracket_all(const double *times, const Py_ssize_t *base, const Py_ssize_t *newest,
                       const double *ts, double t1, Py_ssize_t n, Py_ssize_t *lo_out,
                       Py_ssize_t *hi_out, double *s_out, char *stalled) {
    int ends = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        double t = ts ? ts[i] : t1;
        Py_ssize_t first = base[i], last = newest[i], h = lo_out[i];
        /* a: the first slot after t (bisect_right), in [first, last + 1]. Every slot
         * before a is at or before t, every slot from b on after it. The search
         * starts at the row's last bracket (lo_out on entry): playout time moves
         * forward, so the answer is mostly there or one slot on. */
        Py_ssize_t a = first, b = last + 1;
        if (h >= first && h <= last) {
            if (times[h] <= t) {
                a = h + 1;
                if (a < b && !(times[a] <= t)) b = a;
                else if (a < b) a++;
            } else {
                b = h;
                if (b > a && times[b - 1] <= t) a = b;
                else if (b > a) b--;
            }
        }
        while (a < b) {
            Py_ssize_t mid = a + (b - a) / 2;
            if (times[mid] <= t)
                a = mid + 1;
            else
                b = mid;
        }
        Py_ssize_t lo = a == first ? last : a - 1;
        double t_lo = times[lo];
        int on = t_lo == t, at_end = lo == last;
        lo_out[i] = lo;
        stalled[i] = at_end && !on;
        if (at_end || on) {
            hi_out[i] = lo;
            s_out[i] = 0.0;
            ends = 1;
        } else {
            double s = t - t_lo;
            s /= times[lo + 1] - t_lo;
            hi_out[i] = lo + 1;
            s_out[i] = s;
            if (s == 1.0) ends = 1;
        }
    }
    return ends;
}

/* ------------------------------------------------------------------ pair kernels */

/* q1 = b in q0's hemisphere; returns q0.q1 >= 0. At an exact half turn the
 * largest component of the vector part of q0* b decides (interp.kernels'
 * hemisphere_sign). */
static double align(const double *q0, const double *b, double *q1) {
    double dot = q0[0] * b[0] + q0[1] * b[1];
    dot += q0[2] * b[2];
    dot += q0[3] * b[3];
    double sign;
    if (dot != 0.0) {
        sign = copysign(1.0, dot);
    } else {
        double rel[3];
        rel[0] = q0[0] * b[1] - q0[1] * b[0] - q0[2] * b[3] + q0[3] * b[2];
        rel[1] = q0[0] * b[2] + q0[1] * b[3] - q0[2] * b[0] - q0[3] * b[1];
        rel[2] = q0[0] * b[3] - q0[1] * b[2] + q0[2] * b[1] - q0[3] * b[0];
        int j = 0;
        if (fabs(rel[1]) > fabs(rel[j])) j = 1;
        if (fabs(rel[2]) > fabs(rel[j])) j = 2;
        sign = rel[j] < 0.0 ? -1.0 : 1.0;
    }
    for (int c = 0; c < 4; c++) q1[c] = b[c] * sign;
    return dot * sign;
}

/* Vector part of q0 q1*, summed in the order of interp.rowops.C_ROWS. */
static void conj_product(const double *p, const double *q, double *cv) {
    cv[0] = -q[1] * p[0] + q[0] * p[1] + -q[3] * p[2] + q[2] * p[3];
    cv[1] = -q[2] * p[0] + q[3] * p[1] + q[0] * p[2] + -q[1] * p[3];
    cv[2] = -q[3] * p[0] + -q[2] * p[1] + q[1] * p[2] + q[0] * p[3];
}

static void cross(const double *u, const double *v, double *out) {
    out[0] = u[1] * v[2] - u[2] * v[1];
    out[1] = u[2] * v[0] - u[0] * v[2];
    out[2] = u[0] * v[1] - u[1] * v[0];
}

/* sin and cos of x; in [0, pi/2] through t = tan(x/2), as interp.rowops.sincos_rows
 * (``half``: x/2 if the caller has it, else negative). */
static void sincos_half(double x, double half, double *sin_x, double *cos_x) {
    if (!(x >= 0.0 && x <= M_PI_2)) {
        *sin_x = sin(x);
        *cos_x = cos(x);
        return;
    }
    double t = tan(half >= 0.0 ? half : x * 0.5);
    double t2 = t * t;
    double inv = 1.0 / (t2 + 1.0);
    *sin_x = t * 2.0 * inv;
    *cos_x = (1.0 - t2) * inv;
}

/* Position LERP + quaternion SLERP (interp.methods.soa). */
static void soa_one(const double *t0, const double *q0, const double *t1, const double *b,
                    double s, double *out) {
    double q1[4], d2 = 0.0, m2 = 0.0;
    double dot = align(q0, b, q1), r = 1.0 - s;
    for (int c = 0; c < 4; c++) {
        double d = q1[c] - q0[c], m = q1[c] + q0[c];
        d2 += d * d;
        m2 += m * m;
    }
    double nd = sqrt(d2), nm = sqrt(m2);
    double sin_w = 0.5 * nd * nm;
    double half = s * atan2(nd, nm), sw = half * 2.0, sin_sw, cos_sw, c0, c1;
    sincos_half(sw, half, &sin_sw, &cos_sw);
    if (sin_w != 0.0) {
        c0 = (sin_w * cos_sw - dot * sin_sw) / sin_w;
        c1 = sin_sw / sin_w;
    } else {
        c0 = r;
        c1 = s;
    }
    for (int c = 0; c < 3; c++) out[c] = t0[c] + s * (t1[c] - t0[c]);
    for (int c = 0; c < 4; c++) out[3 + c] = c0 * q0[c] + c1 * q1[c];
}

/* Motor LERP with Study normalisation (interp.methods.motor_lerp). */
static void motor_one(const double *t0, const double *q0, const double *t1, const double *b,
                      double s, double *out) {
    double q1[4], cv[3], u[3], cr[3];
    double dot = align(q0, b, q1), r = 1.0 - s;
    conj_product(q0, q1, cv);
    for (int c = 0; c < 3; c++) u[c] = t0[c] - t1[c];
    cross(u, cv, cr);
    double rr = r * r, ss = s * s, rs = r * s;
    double den = rr + ss + rs * 2.0 * dot;
    for (int c = 0; c < 3; c++) {
        double mix = rs * (dot * (t0[c] + t1[c]) + cr[c]);
        out[c] = (rr * t0[c] + ss * t1[c] + mix) / den;
    }
    double bl[4], n2 = 0.0;
    for (int c = 0; c < 4; c++) {
        bl[c] = r * q0[c] + s * q1[c];
        n2 += bl[c] * bl[c];
    }
    double norm = sqrt(n2);
    for (int c = 0; c < 4; c++) out[3 + c] = bl[c] / norm;
}

/* Dual-quaternion ScLERP in the world frame (interp.kernels.dq_slerp_rows). */
static void dq_one(const double *t0, const double *q0, const double *t1, const double *b,
                   double s, double *out) {
    double q1[4], vec[3], d[3], u[3], vd[3];
    double cos_phi = align(q0, b, q1), r = 1.0 - s;
    conj_product(q0, q1, vec);
    for (int c = 0; c < 3; c++) vec[c] = -vec[c]; /* vector part of q1 q0* */
    double sin_phi = sqrt(vec[0] * vec[0] + vec[1] * vec[1] + vec[2] * vec[2]);
    double sphi = s * atan2(sin_phi, cos_phi);
    double sin_s, cos_s;
    sincos_half(sphi, -1.0, &sin_s, &cos_s);
    double sin_r = sin_phi * cos_s - cos_phi * sin_s;
    double cos_r = cos_phi * cos_s + sin_phi * sin_s;
    double div = sin_phi != 0.0 ? sin_phi : 1.0;
    double k = sin_phi != 0.0 ? sin_s / div : s;
    double kr = sin_phi != 0.0 ? sin_r / div : r;
    double kc = k * cos_r;
    for (int c = 0; c < 3; c++) {
        d[c] = t1[c] - t0[c];
        u[c] = vec[c] / div;
    }
    double along = (s - kc) * (d[0] * u[0] + d[1] * u[1] + d[2] * u[2]);
    cross(vec, d, vd);
    double kk = k * kr;
    for (int c = 0; c < 3; c++) out[c] = t0[c] + (kc * d[c] + along * u[c] - kk * vd[c]);
    for (int c = 0; c < 4; c++) out[3 + c] = kr * q0[c] + k * q1[c];
}

typedef void (*pair_fn)(const double *, const double *, const double *, const double *,
                        double, double *);

static pair_fn kernel_of(long kind) {
    pair_fn fn = kind == SOA ? soa_one : kind == MOTOR_LERP ? motor_one
                                       : kind == DQ_SLERP   ? dq_one
                                                            : NULL;
    if (fn == NULL) PyErr_Format(PyExc_ValueError, "unknown pair kind %ld", kind);
    return fn;
}

/* Method ``fn`` between slots lo[i] and hi[i] of poses (N, 7) at s[i], into
 * out (n, 7); the keyframes themselves at s 0 and 1. The slots are valid. */
static void pairs_into(pair_fn fn, const double *poses, const Py_ssize_t *lo,
                       const Py_ssize_t *hi, const double *S, Py_ssize_t n, double *out) {
    for (Py_ssize_t i = 0; i < n; i++) {
        const double *a = poses + 7 * lo[i], *b = poses + 7 * hi[i];
        double s = S[i], *o = out + 7 * i;
        if (s == 0.0)
            memcpy(o, a, 7 * sizeof(double));
        else if (s == 1.0)
            memcpy(o, b, 7 * sizeof(double));
        else
            fn(a, a + 3, b, b + 3, s, o);
    }
}

/* ------------------------------------------------------------------ entry points */

/* The buffers an entry point holds, released together. */
typedef struct {
    Py_buffer views[12];
    int count;
} Held;

static Py_buffer *hold(Held *h, PyObject *o, int writable, int ndim, const char *chars,
                       Py_ssize_t itemsize, const char *name) {
    Py_buffer *v = &h->views[h->count];
    if (get_buffer(o, v, writable, ndim, chars, itemsize, name) < 0) return NULL;
    h->count++;
    return v;
}

static void release(Held *h) {
    while (h->count > 0) PyBuffer_Release(&h->views[--h->count]);
}

/* The rows' arguments of a bracket (times, base, newest, t, lo, hi, s, stalled),
 * checked: every row has keyframes in the table. */
typedef struct {
    const double *times, *t;
    double t1;
    const Py_ssize_t *base, *newest;
    Py_ssize_t *lo, *hi;
    double *s;
    char *stalled;
    Py_ssize_t n;
} Rows;

static int rows_of(Held *h, PyObject *const *a, Rows *r) {
    Py_buffer *bt, *bb, *bn, *btt = NULL, *blo, *bhi, *bs, *bst;
    if (!(bt = hold(h, a[0], 0, 1, "d", 8, "times")) ||
        !(bb = hold(h, a[1], 0, 1, INTP, sizeof(Py_ssize_t), "base")) ||
        !(bn = hold(h, a[2], 0, 1, INTP, sizeof(Py_ssize_t), "newest")))
        return -1;
    r->t = NULL;
    r->t1 = 0.0;
    if (PyFloat_Check(a[3]) || PyLong_Check(a[3])) {
        r->t1 = PyFloat_AsDouble(a[3]);
        if (r->t1 == -1.0 && PyErr_Occurred()) return -1;
    } else if (!(btt = hold(h, a[3], 0, 1, "d", 8, "t"))) {
        return -1;
    }
    if (!(blo = hold(h, a[4], 1, 1, INTP, sizeof(Py_ssize_t), "lo")) ||
        !(bhi = hold(h, a[5], 1, 1, INTP, sizeof(Py_ssize_t), "hi")) ||
        !(bs = hold(h, a[6], 1, 1, "d", 8, "s")) || !(bst = hold(h, a[7], 1, 1, "?", 1, "stalled")))
        return -1;
    Py_ssize_t n = bb->shape[0], size = bt->shape[0];
    if (bn->shape[0] != n || blo->shape[0] != n || bhi->shape[0] != n || bs->shape[0] != n ||
        bst->shape[0] != n || (btt && btt->shape[0] != n)) {
        PyErr_SetString(PyExc_ValueError, "the rows' arrays differ in length");
        return -1;
    }
    const Py_ssize_t *base = bb->buf, *newest = bn->buf;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (base[i] < 0 || newest[i] < base[i] || newest[i] >= size) {
            PyErr_Format(PyExc_ValueError, "row %zd has no keyframes in the table (%zd..%zd)", i,
                         base[i], newest[i]);
            return -1;
        }
    }
    r->times = bt->buf;
    r->t = btt ? btt->buf : NULL;
    r->base = base;
    r->newest = newest;
    r->lo = blo->buf;
    r->hi = bhi->buf;
    r->s = bs->buf;
    r->stalled = bst->buf;
    r->n = n;
    return 0;
}

static int bracket(const Rows *r) {
    return bracket_all(r->times, r->base, r->newest, r->t, r->t1, r->n, r->lo, r->hi, r->s,
                       r->stalled);
}

static PyObject *py_bracket_rows(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != 8) {
        PyErr_SetString(PyExc_TypeError,
                        "bracket_rows(times, base, newest, t, lo, hi, s, stalled)");
        return NULL;
    }
    Held h = {.count = 0};
    Rows r;
    PyObject *result = rows_of(&h, args, &r) < 0 ? NULL : PyBool_FromLong(bracket(&r));
    release(&h);
    return result;
}

/* poses (N, 7) and out (k, n, 7): their data, or -1 with an error. */
static int pose_tables(Held *h, PyObject *poses, PyObject *out, Py_ssize_t k, Py_ssize_t n,
                       const double **p, Py_ssize_t *size, double **o) {
    Py_buffer *bp, *bo;
    if (!(bp = hold(h, poses, 0, 2, "d", 8, "poses")) || !(bo = hold(h, out, 1, 3, "d", 8, "out")))
        return -1;
    if (bp->shape[1] != 7 || bo->shape[0] != k || bo->shape[1] != n || bo->shape[2] != 7) {
        PyErr_Format(PyExc_ValueError, "poses must be (N, 7) and out (%zd, %zd, 7)", k, n);
        return -1;
    }
    *p = bp->buf;
    *size = bp->shape[0];
    *o = bo->buf;
    return 0;
}

static PyObject *py_pair_rows(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != 6) {
        PyErr_SetString(PyExc_TypeError, "pair_rows(kind, poses, lo, hi, s, out)");
        return NULL;
    }
    long kind = PyLong_AsLong(args[0]);
    if (kind == -1 && PyErr_Occurred()) return NULL;
    pair_fn fn = kernel_of(kind);
    if (fn == NULL) return NULL;
    Held h = {.count = 0};
    PyObject *result = NULL;
    Py_buffer *blo, *bhi, *bs, *bp, *bo;
    if (!(bp = hold(&h, args[1], 0, 2, "d", 8, "poses")) ||
        !(blo = hold(&h, args[2], 0, 1, INTP, sizeof(Py_ssize_t), "lo")) ||
        !(bhi = hold(&h, args[3], 0, 1, INTP, sizeof(Py_ssize_t), "hi")) ||
        !(bs = hold(&h, args[4], 0, 1, "d", 8, "s")) ||
        !(bo = hold(&h, args[5], 1, 2, "d", 8, "out")))
        goto done;
    Py_ssize_t n = blo->shape[0], size = bp->shape[0];
    if (bp->shape[1] != 7 || bo->shape[1] != 7) {
        PyErr_SetString(PyExc_ValueError, "pair_rows: poses must be (N, 7) and out (n, 7)");
        goto done;
    }
    if (bhi->shape[0] != n || bs->shape[0] != n || bo->shape[0] != n) {
        PyErr_SetString(PyExc_ValueError, "pair_rows: lo, hi, s and out differ in length");
        goto done;
    }
    const Py_ssize_t *lo = blo->buf, *hi = bhi->buf;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (lo[i] < 0 || lo[i] >= size || hi[i] < 0 || hi[i] >= size) {
            PyErr_Format(PyExc_IndexError, "pair_rows: slot out of 0..%zd at row %zd", size - 1,
                         i);
            goto done;
        }
    }
    pairs_into(fn, bp->buf, lo, hi, bs->buf, n, bo->buf);
    result = Py_NewRef(Py_None);
done:
    release(&h);
    return result;
}

#define MAX_KINDS 8

/* The kernels of a tuple of interpolator kinds, into fns: their count, or -1 with an error. */
static Py_ssize_t kernels_of(PyObject *kinds, pair_fn *fns) {
    if (!PyTuple_Check(kinds) || PyTuple_GET_SIZE(kinds) > MAX_KINDS) {
        PyErr_Format(PyExc_TypeError, "kinds: expected a tuple of at most %d ints", MAX_KINDS);
        return -1;
    }
    Py_ssize_t k = PyTuple_GET_SIZE(kinds);
    for (Py_ssize_t j = 0; j < k; j++) {
        long kind = PyLong_AsLong(PyTuple_GET_ITEM(kinds, j));
        if (kind == -1 && PyErr_Occurred()) return -1;
        if ((fns[j] = kernel_of(kind)) == NULL) return -1;
    }
    return k;
}

static PyObject *py_render_rows(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != 11) {
        PyErr_SetString(PyExc_TypeError,
                        "render_rows(times, base, newest, t, lo, hi, s, stalled, poses, kinds, "
                        "out)");
        return NULL;
    }
    PyObject *kinds = args[9];
    pair_fn fns[MAX_KINDS];
    Py_ssize_t k = kernels_of(kinds, fns);
    if (k < 0) return NULL;
    Held h = {.count = 0};
    Rows r;
    const double *poses;
    double *out;
    Py_ssize_t size;
    PyObject *result = NULL;
    if (rows_of(&h, args, &r) < 0 ||
        pose_tables(&h, args[8], args[10], k, r.n, &poses, &size, &out) < 0)
        goto done;
    for (Py_ssize_t i = 0; i < r.n; i++) { /* a bracket's slots are at most newest */
        if (r.newest[i] >= size) {
            PyErr_Format(PyExc_IndexError, "render_rows: row %zd beyond the poses", i);
            goto done;
        }
    }
    int ends = bracket(&r);
    for (Py_ssize_t j = 0; j < k; j++)
        pairs_into(fns[j], poses, r.lo, r.hi, r.s, r.n, out + j * r.n * 7);
    result = PyBool_FromLong(ends);
done:
    release(&h);
    return result;
}

/* ------------------------------------------------------------------ Renderer */

/* A room's tables, held between frames: a frame's call then takes only its own
 * arrays (two buffers, not nine), which is most of what a call costs when the
 * caches are cold (a bot renders between other processes' time slices). */
enum { R_TIMES, R_BASE, R_NEWEST, R_LO, R_HI, R_S, R_POSES, R_COUNT };

typedef struct {
    PyObject_HEAD
    Py_buffer views[R_COUNT];
    int held;
} Renderer;

static void renderer_release(Renderer *self) {
    while (self->held > 0) PyBuffer_Release(&self->views[--self->held]);
}

static void renderer_dealloc(Renderer *self) {
    renderer_release(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int renderer_init(Renderer *self, PyObject *args, PyObject *kwds) {
    static const char *names[R_COUNT] = {"times", "base", "newest", "lo", "hi", "s", "poses"};
    static const int writable[R_COUNT] = {0, 0, 0, 1, 1, 1, 0};
    static const int ndims[R_COUNT] = {1, 1, 1, 1, 1, 1, 2};
    PyObject *o[R_COUNT];
    if (kwds != NULL && PyDict_GET_SIZE(kwds) != 0) {
        PyErr_SetString(PyExc_TypeError, "Renderer takes no keyword arguments");
        return -1;
    }
    if (!PyArg_ParseTuple(args, "OOOOOOO:Renderer", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5],
                          &o[6]))
        return -1;
    renderer_release(self);
    for (int j = 0; j < R_COUNT; j++) {
        int is_f = j == R_TIMES || j == R_S || j == R_POSES;
        if (get_buffer(o[j], &self->views[j], writable[j], ndims[j], is_f ? "d" : INTP,
                       is_f ? 8 : (Py_ssize_t)sizeof(Py_ssize_t), names[j]) < 0) {
            renderer_release(self);
            return -1;
        }
        self->held++;
    }
    Py_ssize_t rows = self->views[R_BASE].shape[0];
    for (int j = R_NEWEST; j <= R_S; j++) {
        if (self->views[j].shape[0] != rows) {
            PyErr_SetString(PyExc_ValueError, "Renderer: the rows' arrays differ in length");
            renderer_release(self);
            return -1;
        }
    }
    if (self->views[R_POSES].shape[1] != 7 ||
        self->views[R_POSES].shape[0] != self->views[R_TIMES].shape[0]) {
        PyErr_SetString(PyExc_ValueError, "Renderer: poses must be (N, 7), N the times' length");
        renderer_release(self);
        return -1;
    }
    return 0;
}

/* render(n, t, kinds, out, stalled) -> bool: render_rows on the first n rows of the
 * held tables (the same brackets and poses). */
static PyObject *renderer_render(Renderer *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 5) {
        PyErr_SetString(PyExc_TypeError, "render(n, t, kinds, out, stalled)");
        return NULL;
    }
    if (self->held != R_COUNT) {
        PyErr_SetString(PyExc_ValueError, "Renderer: not initialised");
        return NULL;
    }
    Py_ssize_t n = PyLong_AsSsize_t(args[0]);
    if (n == -1 && PyErr_Occurred()) return NULL;
    if (n < 0 || n > self->views[R_BASE].shape[0]) {
        PyErr_Format(PyExc_ValueError, "render: n must be in 0..%zd", self->views[R_BASE].shape[0]);
        return NULL;
    }
    PyObject *kinds = args[2];
    pair_fn fns[MAX_KINDS];
    Py_ssize_t k = kernels_of(kinds, fns);
    if (k < 0) return NULL;
    Held h = {.count = 0};
    PyObject *result = NULL;
    Py_buffer *bt = NULL, *bo, *bst;
    const double *ts = NULL;
    double t1 = 0.0;
    if (PyFloat_Check(args[1]) || PyLong_Check(args[1])) {
        t1 = PyFloat_AsDouble(args[1]);
        if (t1 == -1.0 && PyErr_Occurred()) return NULL;
    } else if (!(bt = hold(&h, args[1], 0, 1, "d", 8, "t"))) {
        goto done;
    }
    if (!(bo = hold(&h, args[3], 1, 3, "d", 8, "out")) ||
        !(bst = hold(&h, args[4], 1, 1, "?", 1, "stalled")))
        goto done;
    if ((bt && bt->shape[0] != n) || bst->shape[0] != n || bo->shape[0] != k ||
        bo->shape[1] != n || bo->shape[2] != 7) {
        PyErr_Format(PyExc_ValueError, "render: t and stalled must be (%zd,), out (%zd, %zd, 7)",
                     n, k, n);
        goto done;
    }
    if (bt) ts = bt->buf;
    const Py_ssize_t *base = self->views[R_BASE].buf, *newest = self->views[R_NEWEST].buf;
    Py_ssize_t size = self->views[R_TIMES].shape[0];
    for (Py_ssize_t i = 0; i < n; i++) {
        if (base[i] < 0 || newest[i] < base[i] || newest[i] >= size) {
            PyErr_Format(PyExc_ValueError, "row %zd has no keyframes in the table (%zd..%zd)", i,
                         base[i], newest[i]);
            goto done;
        }
    }
    Py_ssize_t *lo = self->views[R_LO].buf, *hi = self->views[R_HI].buf;
    double *s = self->views[R_S].buf, *out = bo->buf;
    int ends = bracket_all(self->views[R_TIMES].buf, base, newest, ts, t1, n, lo, hi, s, bst->buf);
    for (Py_ssize_t j = 0; j < k; j++)
        pairs_into(fns[j], self->views[R_POSES].buf, lo, hi, s, n, out + j * n * 7);
    result = PyBool_FromLong(ends);
done:
    release(&h);
    return result;
}

static PyMethodDef renderer_methods[] = {
    {"render", (PyCFunction)(void (*)(void))renderer_render, METH_FASTCALL,
     "render(n, t, kinds, out, stalled) -> bool: render_rows on the first n rows of the "
     "tables given at construction."},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject RendererType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "posecast.interp._rowkernels.Renderer",
    .tp_basicsize = sizeof(Renderer),
    .tp_dealloc = (destructor)renderer_dealloc,
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Renderer(times, base, newest, lo, hi, s, poses): a room's tables held for "
              "render(n, t, kinds, out, stalled), render_rows without passing them each frame.",
    .tp_methods = renderer_methods,
    .tp_init = (initproc)renderer_init,
    .tp_new = PyType_GenericNew,
};

/* ------------------------------------------------------------------ module */

static PyMethodDef methods[] = {
    {"bracket_rows", (PyCFunction)(void (*)(void))py_bracket_rows, METH_FASTCALL,
     "bracket_rows(times, base, newest, t, lo, hi, s, stalled) -> bool: every row's bracket "
     "at t (a float, or one per row) into lo, hi, s, stalled; whether any is held or s == 1."},
    {"pair_rows", (PyCFunction)(void (*)(void))py_pair_rows, METH_FASTCALL,
     "pair_rows(kind, poses, lo, hi, s, out): pair method `kind` (0 soa, 1 motor-lerp, "
     "2 dq-slerp) between slots lo and hi of poses (N, 7) at s, into out (n, 7)."},
    {"render_rows", (PyCFunction)(void (*)(void))py_render_rows, METH_FASTCALL,
     "render_rows(times, base, newest, t, lo, hi, s, stalled, poses, kinds, out) -> bool: "
     "bracket_rows, then pair method kinds[j] of every bracket into out[j] (k, n, 7)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "posecast.interp._rowkernels",
    "Compiled render kernels of the pair interpolators (see interp/accel.py).", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__rowkernels(void) {
    if (PyType_Ready(&RendererType) < 0) return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m == NULL) return NULL;
    if (PyModule_AddObjectRef(m, "Renderer", (PyObject *)&RendererType) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    if (PyModule_AddStringConstant(m, "SOURCE_HASH", SOURCE_HASH) < 0 ||
        PyModule_AddIntConstant(m, "SOA", SOA) < 0 ||
        PyModule_AddIntConstant(m, "MOTOR_LERP", MOTOR_LERP) < 0 ||
        PyModule_AddIntConstant(m, "DQ_SLERP", DQ_SLERP) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
