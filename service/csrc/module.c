/*
 * module.c — the only file of the core that knows CPython and NumPy.
 *
 * Each Python function converts its arguments to C-contiguous float64 arrays, checks their
 * trailing ("core") shapes, broadcasts the leading dimensions, and runs a kernel over every
 * element with the GIL released for batches. A kernel validates its element and returns a
 * DQ_E* code; the first failure becomes a ValueError naming the argument, the index and the
 * problem. Nothing here does geometry: that is in dq.c, blend.c and fusion.c.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <numpy/arrayobject.h>

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "blend.h"
#include "dq.h"
#include "fusion.h"
#include "trajectory.h"
#include "wire.h"

#define MAX_IN 3
#define MAX_OUT 3
/* Below this many elements releasing the GIL costs more than it gives. */
#define GIL_RELEASE_MIN 64

/* ---- arguments ---------------------------------------------------------------------------- */

typedef struct {
    const char *name;
    int ncore;          /* trailing dims that belong to one element: 0, 1 or 2 */
    npy_intp core[2];   /* their sizes; -1 = any (the set size n of a blend) */
    int optional;       /* None allowed (weights) */
} in_spec;

typedef struct {
    int ncore;
    npy_intp core[2];   /* -1 = the n of input 0 */
} out_spec;

typedef struct {
    PyArrayObject *arr;
    const double *data;
    npy_intp core_size;
    int lead_nd;
    npy_intp lead[NPY_MAXDIMS];
    npy_intp stride[NPY_MAXDIMS]; /* in elements of core_size, 0 where broadcast */
} arg;

/* What a kernel gets for one element. */
typedef struct {
    const double *in[MAX_IN];
    double *out[MAX_OUT];
    npy_intp n;        /* set size for blends */
    void *ctx;
    int bad_arg;       /* set by a kernel on failure: which input */
    npy_intp bad_sub;  /* and which sub-element of it (pose in a set, weight index) */
    double *scratch;
} elem;

typedef int (*kernel_fn)(elem *e);

static void format_shape(char *buf, size_t len, int nd, const npy_intp *shape)
{
    size_t k = (size_t)snprintf(buf, len, "(");
    for (int i = 0; i < nd && k < len; i++)
        k += (size_t)snprintf(buf + k, len - k, i + 1 < nd ? "%ld, " : "%ld", (long)shape[i]);
    if (nd == 1 && k < len) k += (size_t)snprintf(buf + k, len - k, ",");
    if (k < len) snprintf(buf + k, len - k, ")");
}

static const char *core_text(const in_spec *s)
{
    if (s->ncore == 0) return "(...)";
    if (s->ncore == 1) {
        switch (s->core[0]) {
        case 8: return "(..., 8)";
        case 6: return "(..., 6)";
        case 4: return "(..., 4)";
        case 3: return "(..., 3)";
        default: return "(..., n)";
        }
    }
    if (s->core[0] == 4 && s->core[1] == 4) return "(..., 4, 4)";
    return "(..., n, 8)";
}

/* Problem text for a code, with the details of the offending values where it helps. */
static void problem_text(int code, const double *v, int kind, char *buf, size_t len)
{
    switch (code) {
    case DQ_E_NONFINITE:
        snprintf(buf, len, "contains NaN or infinity");
        return;
    case DQ_E_ZERO:
        snprintf(buf, len, "zero quaternion");
        return;
    case DQ_E_NOT_UNIT: {
        double n = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2] + v[3] * v[3]);
        snprintf(buf, len,
                 "quaternion norm %.9g is not unit (off by %.6g, beyond the tolerance %g within "
                 "which it is normalised); if it is a rotation, divide it by its norm",
                 n, fabs(n - 1.0), DQ_UNIT_TOL);
        return;
    }
    case DQ_E_DUAL: {
        double rd = v[0] * v[4] + v[1] * v[5] + v[2] * v[6] + v[3] * v[7];
        snprintf(buf, len,
                 "dual part is not orthogonal to the real part (<r, d> = %.3g, tolerance %g of "
                 "max(|d|, 1)): not a rigid motion", rd, DQ_UNIT_TOL);
        return;
    }
    case DQ_E_NOT_RIGID: {
        if (kind == 16) {
            double worst = dq_rotation_error(v);
            if (fabs(v[12]) > DQ_UNIT_TOL || fabs(v[13]) > DQ_UNIT_TOL ||
                fabs(v[14]) > DQ_UNIT_TOL || fabs(v[15] - 1.0) > DQ_UNIT_TOL)
                snprintf(buf, len, "not a rigid transform: bottom row is not [0, 0, 0, 1]");
            else if (worst > DQ_UNIT_TOL)
                snprintf(buf, len,
                         "not a rigid transform: rotation block is not orthonormal "
                         "(|R^T R - I| = %.3g, beyond the tolerance %g within which it is "
                         "projected to the nearest rotation)", worst, DQ_UNIT_TOL);
            else
                snprintf(buf, len, "not a rigid transform: det(R) = %.6g, not 1 (a reflection)",
                         dq_det3(v));
            return;
        }
        snprintf(buf, len, "not a rigid transform");
        return;
    }
    case DQ_E_WEIGHT_NEG:
        snprintf(buf, len, "negative weight %g", v[0]);
        return;
    case DQ_E_WEIGHT_SUM:
        snprintf(buf, len, "all weights are zero (the weights need a positive sum)");
        return;
    case DQ_E_OVERFLOW:
        snprintf(buf, len, "result is not finite (input too large)");
        return;
    default:
        snprintf(buf, len, "invalid value");
    }
}

/* Converts one argument and checks its core shape. */
static int load_arg(PyObject *obj, const in_spec *s, arg *a, npy_intp *n_io)
{
    a->arr = (PyArrayObject *)PyArray_FROM_OTF(obj, NPY_DOUBLE, NPY_ARRAY_IN_ARRAY);
    if (!a->arr) {
        PyObject *type, *value, *tb;
        PyErr_Fetch(&type, &value, &tb);
        PyErr_Format(PyExc_ValueError, "%s: not convertible to a float64 array (%S)", s->name,
                     value ? value : Py_None);
        Py_XDECREF(type); Py_XDECREF(value); Py_XDECREF(tb);
        return -1;
    }
    int nd = PyArray_NDIM(a->arr);
    npy_intp *sh = PyArray_DIMS(a->arr);
    int ok = nd >= s->ncore;
    for (int k = 0; ok && k < s->ncore; k++) {
        npy_intp want = s->core[k], got = sh[nd - s->ncore + k];
        if (want >= 0 && got != want) ok = 0;
    }
    if (!ok) {
        char shape[160];
        format_shape(shape, sizeof shape, nd, sh);
        PyErr_Format(PyExc_ValueError, "%s: expected shape %s, got %s", s->name, core_text(s),
                     shape);
        return -1;
    }
    /* The set size n: the first input with a free core dimension defines it. */
    for (int k = 0; k < s->ncore; k++) {
        if (s->core[k] < 0) {
            npy_intp got = sh[nd - s->ncore + k];
            if (*n_io < 0) {
                *n_io = got;
            } else if (got != *n_io) {
                PyErr_Format(PyExc_ValueError,
                             "%s: length %zd does not match the number of poses (%zd)", s->name,
                             (Py_ssize_t)got, (Py_ssize_t)*n_io);
                return -1;
            }
        }
    }
    a->lead_nd = nd - s->ncore;
    a->core_size = 1;
    for (int k = 0; k < s->ncore; k++) a->core_size *= sh[nd - s->ncore + k];
    for (int k = 0; k < a->lead_nd; k++) a->lead[k] = sh[k];
    a->data = (const double *)PyArray_DATA(a->arr);
    return 0;
}

/* Writes "name[i, j]" for the element at flat sub-index `flat` of an array whose index space
 * is `shape`. */
static void format_index(char *buf, size_t len, const char *name, int nd, const npy_intp *shape,
                         npy_intp flat)
{
    if (nd == 0) {
        snprintf(buf, len, "%s", name);
        return;
    }
    npy_intp idx[NPY_MAXDIMS];
    for (int k = nd - 1; k >= 0; k--) {
        npy_intp d = shape[k] > 0 ? shape[k] : 1;
        idx[k] = flat % d;
        flat /= d;
    }
    size_t p = (size_t)snprintf(buf, len, "%s[", name);
    for (int k = 0; k < nd && p < len; k++)
        p += (size_t)snprintf(buf + p, len - p, k + 1 < nd ? "%ld, " : "%ld", (long)idx[k]);
    if (p < len) snprintf(buf + p, len - p, "]");
}

/*
 * Runs `kern` over the broadcast of the inputs. objs[i] may be NULL/None for optional inputs.
 * Returns a new reference: the single output, or a tuple when nout > 1.
 */
static PyObject *run(kernel_fn kern, void *ctx, int nin, PyObject **objs, const in_spec *is,
                     int nout, const out_spec *os, size_t scratch_per_n)
{
    arg a[MAX_IN];
    PyArrayObject *outs[MAX_OUT] = {NULL, NULL, NULL};
    int present[MAX_IN];
    npy_intp n = -1;
    PyObject *result = NULL;
    double *scratch = NULL;
    memset(a, 0, sizeof a);

    for (int i = 0; i < nin; i++) {
        present[i] = !(objs[i] == NULL || (is[i].optional && objs[i] == Py_None));
        if (!present[i]) continue;
        if (load_arg(objs[i], &is[i], &a[i], &n) < 0) goto done;
    }
    if (n == 0) {
        PyErr_Format(PyExc_ValueError, "%s: empty set of poses", is[0].name);
        goto done;
    }

    /* Broadcast the leading dimensions (right-aligned, as NumPy does). */
    int out_nd = 0;
    npy_intp out_lead[NPY_MAXDIMS];
    for (int i = 0; i < nin; i++)
        if (present[i] && a[i].lead_nd > out_nd) out_nd = a[i].lead_nd;
    for (int k = 0; k < out_nd; k++) out_lead[k] = 1;
    for (int i = 0; i < nin; i++) {
        if (!present[i]) continue;
        int off = out_nd - a[i].lead_nd;
        for (int k = 0; k < a[i].lead_nd; k++) {
            npy_intp d = a[i].lead[k];
            if (d == 1) continue;
            if (out_lead[off + k] == 1) {
                out_lead[off + k] = d;
            } else if (out_lead[off + k] != d) {
                char s1[160], s2[160];
                format_shape(s1, sizeof s1, a[i].lead_nd, a[i].lead);
                format_shape(s2, sizeof s2, out_nd, out_lead);
                PyErr_Format(PyExc_ValueError,
                             "shape mismatch: %s has leading shape %s, which does not broadcast "
                             "with %s",
                             is[i].name, s1, s2);
                goto done;
            }
        }
    }
    npy_intp total = 1;
    for (int k = 0; k < out_nd; k++) total *= out_lead[k];
    for (int i = 0; i < nin; i++) {
        if (!present[i]) continue;
        int off = out_nd - a[i].lead_nd;
        npy_intp st = 1;
        for (int k = out_nd - 1; k >= 0; k--) {
            int ak = k - off;
            if (ak < 0 || a[i].lead[ak] == 1) {
                a[i].stride[k] = 0;
            } else {
                a[i].stride[k] = st;
                st *= a[i].lead[ak];
            }
        }
    }

    for (int j = 0; j < nout; j++) {
        npy_intp dims[NPY_MAXDIMS + 2];
        for (int k = 0; k < out_nd; k++) dims[k] = out_lead[k];
        for (int k = 0; k < os[j].ncore; k++) dims[out_nd + k] = os[j].core[k] < 0 ? n : os[j].core[k];
        outs[j] = (PyArrayObject *)PyArray_SimpleNew(out_nd + os[j].ncore, dims, NPY_DOUBLE);
        if (!outs[j]) goto done;
    }
    npy_intp out_core[MAX_OUT];
    for (int j = 0; j < nout; j++) {
        out_core[j] = 1;
        for (int k = 0; k < os[j].ncore; k++) out_core[j] *= os[j].core[k] < 0 ? n : os[j].core[k];
    }
    if (scratch_per_n) {
        scratch = (double *)malloc(sizeof(double) * scratch_per_n * (size_t)(n > 0 ? n : 1));
        if (!scratch) {
            PyErr_NoMemory();
            goto done;
        }
    }

    elem e;
    memset(&e, 0, sizeof e);
    e.ctx = ctx;
    e.n = n;
    e.scratch = scratch;
    int code = DQ_OK;
    npy_intp bad_off = 0;
    npy_intp idx[NPY_MAXDIMS];
    npy_intp off[MAX_IN];
    for (int k = 0; k < out_nd; k++) idx[k] = 0;
    for (int i = 0; i < nin; i++) off[i] = 0;

    NPY_BEGIN_THREADS_DEF;
    if (total >= GIL_RELEASE_MIN) NPY_BEGIN_THREADS;
    for (npy_intp t = 0; t < total; t++) {
        for (int i = 0; i < nin; i++) e.in[i] = present[i] ? a[i].data + off[i] * a[i].core_size : NULL;
        for (int j = 0; j < nout; j++) e.out[j] = (double *)PyArray_DATA(outs[j]) + t * out_core[j];
        code = kern(&e);
        if (code != DQ_OK) {
            bad_off = off[e.bad_arg];
            break;
        }
        /* odometer over the broadcast index */
        for (int k = out_nd - 1; k >= 0; k--) {
            idx[k]++;
            for (int i = 0; i < nin; i++) off[i] += a[i].stride[k];
            if (idx[k] < out_lead[k]) break;
            for (int i = 0; i < nin; i++) off[i] -= a[i].stride[k] * out_lead[k];
            idx[k] = 0;
        }
    }
    NPY_END_THREADS;

    if (code == DQ_E_SET_SIZE) { /* every set has the same size: no index to name */
        PyErr_Format(PyExc_ValueError, "%s: sclerp blends exactly 2 poses, got %zd", is[0].name,
                     (Py_ssize_t)n);
        goto done;
    }
    if (code != DQ_OK) {
        int bi = e.bad_arg;
        const in_spec *s = &is[bi];
        /* Index within the argument: its own leading index, then the sub-element of the set. */
        int nd = a[bi].lead_nd;
        npy_intp shape[NPY_MAXDIMS + 1];
        for (int k = 0; k < nd; k++) shape[k] = a[bi].lead[k];
        npy_intp flat = bad_off;
        npy_intp sub_size = a[bi].core_size;
        int has_sub = s->ncore >= 1 && s->core[0] < 0;
        if (has_sub) {
            shape[nd++] = n;
            flat = flat * n + e.bad_sub;
            sub_size = a[bi].core_size / (n > 0 ? n : 1);
        }
        char where[256], what[256];
        if (code == DQ_E_WEIGHT_SUM) {
            format_index(where, sizeof where, s->name, a[bi].lead_nd, a[bi].lead, bad_off);
        } else {
            format_index(where, sizeof where, s->name, nd, shape, flat);
        }
        const double *v = a[bi].data + flat * sub_size;
        problem_text(code, v, (int)sub_size, what, sizeof what);
        PyErr_Format(PyExc_ValueError, "%s: %s", where, what);
        goto done;
    }

    if (nout == 1) {
        result = (PyObject *)outs[0];
        outs[0] = NULL;
    } else {
        result = PyTuple_New(nout);
        if (!result) goto done;
        for (int j = 0; j < nout; j++) {
            PyTuple_SET_ITEM(result, j, (PyObject *)outs[j]);
            outs[j] = NULL;
        }
    }

done:
    free(scratch);
    for (int i = 0; i < nin; i++) Py_XDECREF(a[i].arr);
    for (int j = 0; j < nout; j++) Py_XDECREF(outs[j]);
    return result;
}

/* ---- kernels ------------------------------------------------------------------------------ */

/* Validates a pose input into buf; sets the failing argument on error. */
#define UNIT_IN(e, i, buf)                                   \
    do {                                                     \
        int rc_ = dq_unit((e)->in[i], (buf));                \
        if (rc_) { (e)->bad_arg = (i); return rc_; }         \
    } while (0)

static int k_mul(elem *e)
{
    if (!dq_finite8(e->in[0])) { e->bad_arg = 0; return DQ_E_NONFINITE; }
    if (!dq_finite8(e->in[1])) { e->bad_arg = 1; return DQ_E_NONFINITE; }
    dq_mul(e->in[0], e->in[1], e->out[0]);
    if (!dq_finite8(e->out[0])) { e->bad_arg = 0; return DQ_E_OVERFLOW; }
    return DQ_OK;
}

static int k_conj(elem *e)
{
    if (!dq_finite8(e->in[0])) { e->bad_arg = 0; return DQ_E_NONFINITE; }
    dq_conj(e->in[0], e->out[0]);
    return DQ_OK;
}

static int k_normalize(elem *e)
{
    int rc = dq_normalize(e->in[0], e->out[0]);
    if (rc) e->bad_arg = 0;
    return rc;
}

static int k_log(elem *e)
{
    double q[8];
    UNIT_IN(e, 0, q);
    dq_log(q, e->out[0]);
    return DQ_OK;
}

static int k_exp(elem *e)
{
    if (!dq_finite_n(e->in[0], 6)) { e->bad_arg = 0; return DQ_E_NONFINITE; }
    dq_exp(e->in[0], e->out[0]);
    if (!dq_finite8(e->out[0])) { e->bad_arg = 0; return DQ_E_OVERFLOW; }
    return DQ_OK;
}

static int k_power(elem *e)
{
    double q[8];
    UNIT_IN(e, 0, q);
    double tau = e->in[1][0];
    if (!(tau * 0.0 == 0.0)) { e->bad_arg = 1; return DQ_E_NONFINITE; }
    dq_pow(q, tau, e->out[0]);
    if (!dq_finite8(e->out[0])) { e->bad_arg = 1; return DQ_E_OVERFLOW; }
    return DQ_OK;
}

/* The pair's screw is cached between elements: with one pair and many tau (the usual
 * trajectory case) it is validated and prepared once. */
typedef struct {
    const double *a, *b;
    dq_sclerp_pair pair;
} sclerp_ctx;

static int k_sclerp(elem *e)
{
    sclerp_ctx *c = (sclerp_ctx *)e->ctx;
    if (e->in[0] != c->a || e->in[1] != c->b) {
        double a[8], b[8];
        UNIT_IN(e, 0, a);
        UNIT_IN(e, 1, b);
        dq_sclerp_prepare(a, b, &c->pair);
        c->a = e->in[0];
        c->b = e->in[1];
    }
    double tau = e->in[2][0];
    if (!(tau * 0.0 == 0.0)) { e->bad_arg = 2; return DQ_E_NONFINITE; }
    dq_sclerp_eval(&c->pair, tau, e->out[0]);
    if (!dq_finite8(e->out[0])) { e->bad_arg = 2; return DQ_E_OVERFLOW; }
    return DQ_OK;
}

static int k_from_matrix(elem *e)
{
    int rc = dq_from_matrix(e->in[0], e->out[0]);
    if (rc) e->bad_arg = 0;
    return rc;
}

static int k_to_matrix(elem *e)
{
    double q[8];
    UNIT_IN(e, 0, q);
    dq_to_matrix(q, e->out[0]);
    return DQ_OK;
}

static int k_from_pose(elem *e)
{
    int rc = dq_from_pose(e->in[0], e->in[1], e->out[0]);
    /* A unit q cannot overflow the result, so then the translation is to blame. */
    if (rc) e->bad_arg = ((rc == DQ_E_NONFINITE || rc == DQ_E_OVERFLOW) && dq_finite_n(e->in[0], 4)) ? 1 : 0;
    return rc;
}

static int k_to_pose(elem *e)
{
    double q[8];
    UNIT_IN(e, 0, q);
    dq_to_pose(q, e->out[0], e->out[1]);
    return DQ_OK;
}

static int k_transform(elem *e)
{
    double q[8];
    UNIT_IN(e, 0, q);
    if (!dq_finite_n(e->in[1], 3)) { e->bad_arg = 1; return DQ_E_NONFINITE; }
    dq_transform_point(q, e->in[1], e->out[0]);
    if (!dq_finite_n(e->out[0], 3)) { e->bad_arg = 1; return DQ_E_OVERFLOW; }
    return DQ_OK;
}

static int k_screw(elem *e)
{
    double q[8];
    UNIT_IN(e, 0, q);
    dq_screw(q, e->out[0], e->out[1], e->out[2], e->out[2] + 3);
    return DQ_OK;
}

/* Blends: scratch holds n unit poses then n normalised weights. */
static int load_set(elem *e)
{
    npy_intp n = e->n;
    double *q = e->scratch, *w = e->scratch + 8 * n;
    for (npy_intp i = 0; i < n; i++) {
        int rc = dq_unit(e->in[0] + 8 * i, q + 8 * i);
        if (rc) { e->bad_arg = 0; e->bad_sub = i; return rc; }
    }
    size_t bad = 0;
    int rc = dq_weights(e->in[1], (size_t)n, w, &bad);
    if (rc) { e->bad_arg = 1; e->bad_sub = (npy_intp)bad; return rc; }
    return DQ_OK;
}

static int k_blend(elem *e)
{
    const dq_blend_params *p = (const dq_blend_params *)e->ctx;
    e->bad_arg = 0;
    e->bad_sub = 0;
    /* the set size before the poses: it is wrong for every set alike */
    int rc = dq_blend_check(p->method, (size_t)e->n);
    if (!rc) rc = load_set(e);
    if (rc) return rc;
    int iters;
    double residual;
    const double *q = e->scratch, *w = e->scratch + 8 * e->n;
    rc = dq_blend_set(q, w, (size_t)e->n, p, e->out[0], &iters, &residual);
    if (rc) { e->bad_arg = 0; e->bad_sub = 0; return rc; }
    if (e->out[1]) e->out[1][0] = (double)iters;
    if (e->out[2]) e->out[2][0] = residual;
    return DQ_OK;
}

/* Lin's raw matrix blend (dq.lin), which dq_blend_set projects. */
static int k_lin(elem *e)
{
    int rc = load_set(e);
    if (rc) return rc;
    const double *q = e->scratch, *w = e->scratch + 8 * e->n;
    dq_lin(q, w, (size_t)e->n, e->out[0]);
    if (!dq_finite_n(e->out[0], 16)) { e->bad_arg = 0; e->bad_sub = 0; return DQ_E_OVERFLOW; }
    return DQ_OK;
}

/* ---- Python functions ------------------------------------------------------------------- */

static const in_spec S_DQ_A = {"a", 1, {8, 0}, 0};
static const in_spec S_DQ_B = {"b", 1, {8, 0}, 0};
static const out_spec O_DQ = {1, {8, 0}};

static PyObject *call1(kernel_fn k, PyObject *x, in_spec s, out_spec o)
{
    PyObject *objs[1] = {x};
    return run(k, NULL, 1, objs, &s, 1, &o, 0);
}

static PyObject *py_mul(PyObject *self, PyObject *args)
{
    PyObject *objs[2];
    if (!PyArg_ParseTuple(args, "OO:mul", &objs[0], &objs[1])) return NULL;
    in_spec is[2] = {S_DQ_A, S_DQ_B};
    return run(k_mul, NULL, 2, objs, is, 1, &O_DQ, 0);
}

static PyObject *py_conj(PyObject *self, PyObject *x) { return call1(k_conj, x, S_DQ_A, O_DQ); }
static PyObject *py_normalize(PyObject *self, PyObject *x) { return call1(k_normalize, x, S_DQ_A, O_DQ); }
static PyObject *py_log(PyObject *self, PyObject *x)
{
    out_spec o = {1, {6, 0}};
    return call1(k_log, x, S_DQ_A, o);
}
static PyObject *py_exp(PyObject *self, PyObject *x)
{
    in_spec s = {"x", 1, {6, 0}, 0};
    return call1(k_exp, x, s, O_DQ);
}
static PyObject *py_from_matrix(PyObject *self, PyObject *x)
{
    in_spec s = {"T", 2, {4, 4}, 0};
    return call1(k_from_matrix, x, s, O_DQ);
}
static PyObject *py_to_matrix(PyObject *self, PyObject *x)
{
    out_spec o = {2, {4, 4}};
    return call1(k_to_matrix, x, S_DQ_A, o);
}

static PyObject *py_power(PyObject *self, PyObject *args)
{
    PyObject *objs[2];
    if (!PyArg_ParseTuple(args, "OO:power", &objs[0], &objs[1])) return NULL;
    in_spec is[2] = {S_DQ_A, {"tau", 0, {0, 0}, 0}};
    return run(k_power, NULL, 2, objs, is, 1, &O_DQ, 0);
}

/* Independent pairs of one shape (a, b (..., 8), tau (...)): validated into one buffer and
 * interpolated by the vectorised dq_sclerp_pairs, without the per-element kernel call. Returns
 * NULL without an exception when the fast path does not apply or an element is invalid; the
 * general path then runs (and names the bad element). */
#define SCLERP_PAIRS_MIN 16
static PyObject *sclerp_pairs_fast(PyObject **objs)
{
    for (int i = 0; i < 3; i++)
        if (!PyArray_CheckExact(objs[i])) return NULL;
    PyArrayObject *A = (PyArrayObject *)objs[0], *B = (PyArrayObject *)objs[1],
                  *T = (PyArrayObject *)objs[2];
    int nd = PyArray_NDIM(A);
    if (nd < 1 || PyArray_DIM(A, nd - 1) != 8 || PyArray_NDIM(B) != nd || PyArray_NDIM(T) != nd - 1)
        return NULL;
    for (int i = 0; i < 3; i++) {
        PyArrayObject *x = (PyArrayObject *)objs[i];
        if (PyArray_TYPE(x) != NPY_DOUBLE || !PyArray_IS_C_CONTIGUOUS(x) || !PyArray_ISALIGNED(x) ||
            PyArray_ISBYTESWAPPED(x))
            return NULL;
    }
    if (!PyArray_CompareLists(PyArray_DIMS(A), PyArray_DIMS(B), nd) ||
        !PyArray_CompareLists(PyArray_DIMS(A), PyArray_DIMS(T), nd - 1))
        return NULL;
    npy_intp n = PyArray_SIZE(T);
    if (n < SCLERP_PAIRS_MIN) return NULL;
    PyArrayObject *out = (PyArrayObject *)PyArray_SimpleNew(nd, PyArray_DIMS(A), NPY_DOUBLE);
    double *buf = (double *)malloc(sizeof(double) * 16 * (size_t)n);
    if (!out || !buf) {
        Py_XDECREF(out);
        free(buf);
        PyErr_Clear();
        return NULL;
    }
    const double *a = PyArray_DATA(A), *b = PyArray_DATA(B), *t = PyArray_DATA(T);
    double *ua = buf, *ub = buf + 8 * n, *o = PyArray_DATA(out);
    int ok = 1;
    NPY_BEGIN_THREADS_DEF;
    NPY_BEGIN_THREADS;
    for (npy_intp i = 0; ok && i < n; i++)
        ok = dq_unit(a + 8 * i, ua + 8 * i) == DQ_OK && dq_unit(b + 8 * i, ub + 8 * i) == DQ_OK &&
             t[i] * 0.0 == 0.0;
    if (ok) {
        dq_sclerp_pairs(ua, ub, t, (size_t)n, o);
        ok = dq_finite_n(o, 8 * (size_t)n);
    }
    NPY_END_THREADS;
    free(buf);
    if (!ok) {
        Py_DECREF(out);
        return NULL;
    }
    return (PyObject *)out;
}

static PyObject *py_sclerp(PyObject *self, PyObject *args)
{
    PyObject *objs[3];
    if (!PyArg_ParseTuple(args, "OOO:sclerp", &objs[0], &objs[1], &objs[2])) return NULL;
    PyObject *fast = sclerp_pairs_fast(objs);
    if (fast) return fast;
    in_spec is[3] = {S_DQ_A, S_DQ_B, {"tau", 0, {0, 0}, 0}};
    sclerp_ctx c;
    memset(&c, 0, sizeof c);
    return run(k_sclerp, &c, 3, objs, is, 1, &O_DQ, 0);
}

static PyObject *py_from_pose(PyObject *self, PyObject *args)
{
    PyObject *objs[2];
    if (!PyArg_ParseTuple(args, "OO:from_pose", &objs[0], &objs[1])) return NULL;
    in_spec is[2] = {{"q", 1, {4, 0}, 0}, {"t", 1, {3, 0}, 0}};
    return run(k_from_pose, NULL, 2, objs, is, 1, &O_DQ, 0);
}

static PyObject *py_to_pose(PyObject *self, PyObject *x)
{
    PyObject *objs[1] = {x};
    in_spec is[1] = {S_DQ_A};
    out_spec os[2] = {{1, {4, 0}}, {1, {3, 0}}};
    return run(k_to_pose, NULL, 1, objs, is, 2, os, 0);
}

static PyObject *py_transform(PyObject *self, PyObject *args)
{
    PyObject *objs[2];
    if (!PyArg_ParseTuple(args, "OO:transform", &objs[0], &objs[1])) return NULL;
    in_spec is[2] = {S_DQ_A, {"p", 1, {3, 0}, 0}};
    out_spec o = {1, {3, 0}};
    return run(k_transform, NULL, 2, objs, is, 1, &o, 0);
}

static PyObject *py_screw(PyObject *self, PyObject *x)
{
    PyObject *objs[1] = {x};
    in_spec is[1] = {S_DQ_A};
    /* theta, d, and [l | m] packed as 6 values; the Python side splits them. */
    out_spec os[3] = {{0, {0, 0}}, {0, {0, 0}}, {1, {6, 0}}};
    return run(k_screw, NULL, 1, objs, is, 3, os, 0);
}

static const in_spec S_SET[2] = {{"dqs", 2, {-1, 8}, 0}, {"weights", 1, {-1, 0}, 1}};

/* The stopping rule of an iteration (DIB, DEC, fusion): 0, or -1 with a ValueError. */
static int check_iteration(double tol, int max_iter)
{
    if (!(tol >= 0.0) || !(tol * 0.0 == 0.0)) {
        PyErr_SetString(PyExc_ValueError, "tol: must be finite and >= 0");
        return -1;
    }
    if (max_iter < 0) {
        PyErr_SetString(PyExc_ValueError, "max_iter: must be >= 0");
        return -1;
    }
    return 0;
}

/* blend(dqs, weights, method, tol, max_iter) -> out, or (out, iterations, residual) for DIB */
static PyObject *py_blend(PyObject *self, PyObject *args)
{
    PyObject *objs[2];
    dq_blend_params p = {DQ_DIB, 1e-12, 100};
    if (!PyArg_ParseTuple(args, "OOi|di:blend", &objs[0], &objs[1], &p.method, &p.tol, &p.max_iter))
        return NULL;
    if (!dq_method_known(p.method)) {
        PyErr_SetString(PyExc_ValueError, "method: unknown blending method");
        return NULL;
    }
    if (check_iteration(p.tol, p.max_iter) < 0) return NULL;
    if (p.method == DQ_DIB) {
        out_spec os[3] = {O_DQ, {0, {0, 0}}, {0, {0, 0}}};
        return run(k_blend, &p, 2, objs, S_SET, 3, os, 9);
    }
    return run(k_blend, &p, 2, objs, S_SET, 1, &O_DQ, 9);
}

/* lin(dqs, weights) -> the raw matrix blend (..., 4, 4) */
static PyObject *py_lin(PyObject *self, PyObject *args)
{
    PyObject *objs[2];
    if (!PyArg_ParseTuple(args, "OO:lin", &objs[0], &objs[1])) return NULL;
    out_spec o = {2, {4, 4}};
    return run(k_lin, NULL, 2, objs, S_SET, 1, &o, 9);
}

/* blend_request_from_wire(bytes) -> (poses (n, 7) [qw qx qy qz x y z], weights (m,), method,
 * tolerance, max_iterations), or None when the bytes are not a BlendRequest this decoder
 * understands (the caller then uses the protobuf parser, which says what is wrong). */
static PyObject *py_blend_request_from_wire(PyObject *self, PyObject *arg)
{
    Py_buffer view;
    if (PyObject_GetBuffer(arg, &view, PyBUF_SIMPLE) < 0) return NULL;
    dq_blend_request r;
    memset(&r, 0, sizeof r);
    PyObject *result = NULL;
    PyArrayObject *poses = NULL, *weights = NULL;
    if (dq_wire_blend_request((const uint8_t *)view.buf, (size_t)view.len, &r) < 0) {
        result = Py_None;
        Py_INCREF(result);
        goto done;
    }
    npy_intp pd[2] = {(npy_intp)r.n_poses, 7}, wd[1] = {(npy_intp)r.n_weights};
    poses = (PyArrayObject *)PyArray_SimpleNew(2, pd, NPY_DOUBLE);
    weights = (PyArrayObject *)PyArray_SimpleNew(1, wd, NPY_DOUBLE);
    if (!poses || !weights) goto done;
    r.poses = r.n_poses ? (double *)PyArray_DATA(poses) : NULL;
    r.weights = r.n_weights ? (double *)PyArray_DATA(weights) : NULL;
    if (dq_wire_blend_request((const uint8_t *)view.buf, (size_t)view.len, &r) < 0) {
        result = Py_None;
        Py_INCREF(result);
        goto done;
    }
    result = Py_BuildValue("(OOLdK)", poses, weights, (long long)r.method, r.tolerance,
                           (unsigned long long)r.max_iterations);
done:
    Py_XDECREF(poses);
    Py_XDECREF(weights);
    PyBuffer_Release(&view);
    return result;
}

/* blend_wire(bytes, max_poses, default_tol, default_max_iter, max_iter_limit) -> BlendResponse
 * bytes, or None outside the plain case (see dq_wire_blend); the caller then takes the full path. */
static PyObject *py_blend_wire(PyObject *self, PyObject *args)
{
    Py_buffer view;
    Py_ssize_t max_poses;
    dq_wire_config cfg;
    unsigned int dmi, lim;
    if (!PyArg_ParseTuple(args, "y*ndII:blend_wire", &view, &max_poses, &cfg.default_tol, &dmi,
                          &lim))
        return NULL;
    cfg.max_poses = max_poses > 0 ? (size_t)max_poses : 0;
    cfg.default_max_iter = dmi;
    cfg.max_iter_limit = lim;
    uint8_t out[DQ_WIRE_RESPONSE_MAX];
    size_t n = 0;
    int rc;
    if (view.len > 65536) { /* thousands of poses: let other threads run meanwhile */
        Py_BEGIN_ALLOW_THREADS
        rc = dq_wire_blend((const uint8_t *)view.buf, (size_t)view.len, &cfg, out, &n);
        Py_END_ALLOW_THREADS
    } else {
        rc = dq_wire_blend((const uint8_t *)view.buf, (size_t)view.len, &cfg, out, &n);
    }
    PyBuffer_Release(&view);
    if (rc) Py_RETURN_NONE;
    return PyBytes_FromStringAndSize((const char *)out, (Py_ssize_t)n);
}

/* blend_batch_wire(bytes, max_requests, max_total_poses, max_poses, default_tol,
 * default_max_iter, max_iter_limit) -> (BlendBatchResponse bytes, number of requests), or None
 * outside the plain case (an empty batch, limits exceeded, any request not plain). */
static PyObject *py_blend_batch_wire(PyObject *self, PyObject *args)
{
    Py_buffer view;
    Py_ssize_t max_requests, max_total, max_poses;
    dq_wire_config cfg;
    unsigned int dmi, lim;
    if (!PyArg_ParseTuple(args, "y*nnndII:blend_batch_wire", &view, &max_requests, &max_total,
                          &max_poses, &cfg.default_tol, &dmi, &lim))
        return NULL;
    cfg.max_poses = max_poses > 0 ? (size_t)max_poses : 0;
    cfg.default_max_iter = dmi;
    cfg.max_iter_limit = lim;
    PyObject *result = NULL;
    size_t n_req = 0, n_poses = 0, n = 0;
    if (dq_wire_batch_count((const uint8_t *)view.buf, (size_t)view.len, &n_req, &n_poses) ||
        n_req == 0 || n_req > (size_t)max_requests || n_poses > (size_t)max_total) {
        result = Py_None;
        Py_INCREF(result);
        goto done;
    }
    uint8_t *out = PyMem_Malloc(n_req * DQ_WIRE_BATCH_ITEM_MAX);
    if (!out) {
        PyErr_NoMemory();
        goto done;
    }
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = dq_wire_blend_batch((const uint8_t *)view.buf, (size_t)view.len, &cfg, out, &n);
    Py_END_ALLOW_THREADS
    if (rc) {
        result = Py_None;
        Py_INCREF(result);
    } else {
        result = Py_BuildValue("(y#n)", (const char *)out, (Py_ssize_t)n, (Py_ssize_t)n_req);
    }
    PyMem_Free(out);
done:
    PyBuffer_Release(&view);
    return result;
}

/* fuse_stream_from_wire(bytes, sym_tol) -> (poses (n, 8), covariances (n, 6, 6), times (n,),
 * codes (n,) uint8, bodies, sources (tuples of str), spans (n, 2): each measurement's offset and
 * length in the bytes), or None outside the plain case (see dq_wire_fuse_stream). */
static PyObject *py_fuse_stream_from_wire(PyObject *self, PyObject *args)
{
    Py_buffer view;
    double sym_tol;
    if (!PyArg_ParseTuple(args, "y*d:fuse_stream_from_wire", &view, &sym_tol)) return NULL;
    const uint8_t *buf = (const uint8_t *)view.buf;
    PyObject *result = NULL, *bodies = NULL, *sources = NULL;
    PyArrayObject *poses = NULL, *covs = NULL, *times = NULL, *codes = NULL, *spans = NULL;
    uint32_t *sp = NULL;
    dq_fuse_stream r;
    memset(&r, 0, sizeof r);
    if (dq_wire_fuse_count(buf, (size_t)view.len, &r)) goto none;
    npy_intp n = (npy_intp)r.n;
    npy_intp d8[2] = {n, 8}, d36[3] = {n, 6, 6}, d1[1] = {n}, d2[2] = {n, 2};
    poses = (PyArrayObject *)PyArray_ZEROS(2, d8, NPY_DOUBLE, 0);
    covs = (PyArrayObject *)PyArray_ZEROS(3, d36, NPY_DOUBLE, 0);
    times = (PyArrayObject *)PyArray_ZEROS(1, d1, NPY_DOUBLE, 0);
    codes = (PyArrayObject *)PyArray_ZEROS(1, d1, NPY_UINT8, 0);
    spans = (PyArrayObject *)PyArray_ZEROS(2, d2, NPY_INT64, 0);
    sp = PyMem_Malloc((size_t)(6 * n + 1) * sizeof *sp);
    if (!poses || !covs || !times || !codes || !spans || !sp) {
        if (!PyErr_Occurred()) PyErr_NoMemory();
        goto done;
    }
    r.poses = (double *)PyArray_DATA(poses);
    r.covs = (double *)PyArray_DATA(covs);
    r.times = (double *)PyArray_DATA(times);
    r.codes = (uint8_t *)PyArray_DATA(codes);
    r.spans = sp;
    if (dq_wire_fuse_stream(buf, (size_t)view.len, sym_tol, &r)) goto none;
    bodies = PyTuple_New(n);
    sources = PyTuple_New(n);
    if (!bodies || !sources) goto done;
    int64_t *out = (int64_t *)PyArray_DATA(spans);
    for (npy_intp i = 0; i < n; i++) {
        const uint32_t *s = sp + 6 * i;
        PyObject *src = PyUnicode_DecodeASCII((const char *)buf + s[2], s[3], NULL);
        if (!src) goto done;
        PyTuple_SET_ITEM(sources, i, src);
        PyObject *body = PyUnicode_DecodeASCII((const char *)buf + s[4], s[5], NULL);
        if (!body) goto done;
        PyTuple_SET_ITEM(bodies, i, body);
        out[2 * i] = s[0];
        out[2 * i + 1] = s[1];
    }
    result = PyTuple_Pack(7, poses, covs, times, codes, bodies, sources, spans);
    goto done;
none:
    result = Py_None;
    Py_INCREF(result);
done:
    Py_XDECREF(poses);
    Py_XDECREF(covs);
    Py_XDECREF(times);
    Py_XDECREF(codes);
    Py_XDECREF(spans);
    Py_XDECREF(bodies);
    Py_XDECREF(sources);
    PyMem_Free(sp);
    PyBuffer_Release(&view);
    return result;
}

static PyObject *double_rows(PyObject *obj, npy_intp n, npy_intp width, const char *name)
{
    if (obj == Py_None) return NULL;
    PyObject *a = PyArray_FROM_OTF(obj, NPY_DOUBLE, NPY_ARRAY_IN_ARRAY);
    if (a && PyArray_SIZE((PyArrayObject *)a) != n * width) {
        PyErr_Format(PyExc_ValueError, "%s: expected %zd values, got %zd", name,
                     (Py_ssize_t)(n * width), (Py_ssize_t)PyArray_SIZE((PyArrayObject *)a));
        Py_CLEAR(a);
    }
    return a;
}

static int name_at(PyObject *seq, npy_intp i, const char *field, const char **s, Py_ssize_t *n)
{
    *s = "";
    *n = 0;
    if (!seq) return 0;
    PyObject *item = PySequence_Fast_GET_ITEM(seq, i);
    if (!PyUnicode_Check(item)) {
        PyErr_Format(PyExc_ValueError, "%s[%zd]: expected a string, got %s", field, (Py_ssize_t)i,
                     Py_TYPE(item)->tp_name);
        return -1;
    }
    *s = PyUnicode_AsUTF8AndSize(item, n);
    return *s ? 0 : -1;
}

/* measurements_wire(q (n, 4), t (n, 3), covariances (n, 36) or None, weights (n,) or None,
 * times (n,) or None, sources or None, bodies or None) -> bytes: the measurements as repeated
 * FuseStreamRequest.measurements (dq_wire_measurement). The caller has checked the shapes;
 * a name that is not a str is a ValueError naming it. */
static PyObject *py_measurements_wire(PyObject *self, PyObject *args)
{
    PyObject *oq, *ot, *ocov, *ow, *otimes, *osrc, *obody;
    if (!PyArg_ParseTuple(args, "OOOOOOO:measurements_wire", &oq, &ot, &ocov, &ow, &otimes, &osrc,
                          &obody))
        return NULL;
    PyObject *q = NULL, *t = NULL, *cov = NULL, *w = NULL, *times = NULL, *src = NULL,
             *body = NULL, *result = NULL;
    uint8_t *buf = NULL;
    Py_ssize_t n = PySequence_Size(oq);
    if (n < 0) return NULL;
    if (!(q = double_rows(oq, n, 4, "q")) || !(t = double_rows(ot, n, 3, "t"))) goto done;
    if ((ocov != Py_None && !(cov = double_rows(ocov, n, 36, "covariances"))) ||
        (ow != Py_None && !(w = double_rows(ow, n, 1, "weights"))) ||
        (otimes != Py_None && !(times = double_rows(otimes, n, 1, "times"))))
        goto done;
    if (osrc != Py_None && !(src = PySequence_Fast(osrc, "sources: expected a sequence"))) goto done;
    if (obody != Py_None && !(body = PySequence_Fast(obody, "bodies: expected a sequence"))) goto done;
    if ((src && PySequence_Fast_GET_SIZE(src) != n) || (body && PySequence_Fast_GET_SIZE(body) != n)) {
        PyErr_SetString(PyExc_ValueError, "sources, bodies: expected one name a measurement");
        goto done;
    }
    size_t room = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        const char *a, *b;
        Py_ssize_t na, nb;
        if (name_at(src, i, "names", &a, &na) || name_at(body, i, "bodies", &b, &nb)) goto done;
        room += DQ_WIRE_MEASUREMENT_MAX + (size_t)na + (size_t)nb;
    }
    buf = PyMem_Malloc(room ? room : 1);
    if (!buf) {
        PyErr_NoMemory();
        goto done;
    }
    const double *pq = PyArray_DATA((PyArrayObject *)q), *pt = PyArray_DATA((PyArrayObject *)t);
    const double *pc = cov ? PyArray_DATA((PyArrayObject *)cov) : NULL;
    const double *pw = w ? PyArray_DATA((PyArrayObject *)w) : NULL;
    const double *ptm = times ? PyArray_DATA((PyArrayObject *)times) : NULL;
    size_t len = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        const char *a, *b;
        Py_ssize_t na, nb;
        name_at(src, i, "names", &a, &na); /* checked above */
        name_at(body, i, "bodies", &b, &nb);
        len += dq_wire_measurement(buf + len, a, (size_t)na, b, (size_t)nb, ptm ? ptm[i] : 0.0,
                                   pq + 4 * i, pt + 3 * i, pc ? pc + 36 * i : NULL,
                                   pw ? pw[i] : 0.0);
    }
    result = PyBytes_FromStringAndSize((const char *)buf, (Py_ssize_t)len);
done:
    Py_XDECREF(q);
    Py_XDECREF(t);
    Py_XDECREF(cov);
    Py_XDECREF(w);
    Py_XDECREF(times);
    Py_XDECREF(src);
    Py_XDECREF(body);
    PyMem_Free(buf);
    return result;
}

/* fuse(poses (..., n, 8), covariances (..., n, 6, 6), inliers (..., n) bool or None, tol,
 * max_iter, nis) -> (mean, covariance, residuals, distances, nis, tested, status, iterations,
 * chi2), each with the leading shape; nis and tested are None when nis is false. The leading
 * shapes of the arguments must be equal (a batch of independent problems, no broadcasting). */
/* A tuple of the n outputs (None for a NULL one), taking their references: outs[j] is left
 * NULL so the caller's cleanup does not release them again. NULL when the tuple cannot be made
 * (then outs keeps its references). */
static PyObject *steal_tuple(PyArrayObject **outs, int n)
{
    PyObject *t = PyTuple_New(n);
    if (!t) return NULL;
    for (int j = 0; j < n; j++) {
        PyObject *o = outs[j] ? (PyObject *)outs[j] : Py_None;
        if (!outs[j]) Py_INCREF(Py_None);
        PyTuple_SET_ITEM(t, j, o);
        outs[j] = NULL;
    }
    return t;
}

static PyObject *py_fuse(PyObject *self, PyObject *args)
{
    PyObject *zo, *so, *io;
    dq_fuse_params p = {1e-12, 100};
    int want_nis = 1;
    if (!PyArg_ParseTuple(args, "OOO|dip:fuse", &zo, &so, &io, &p.tol, &p.max_iter, &want_nis))
        return NULL;
    if (check_iteration(p.tol, p.max_iter) < 0) return NULL;
    PyArrayObject *Z = NULL, *S = NULL, *M = NULL, *outs[9] = {NULL};
    PyObject *result = NULL;
    double *work = NULL, *zu = NULL;
    Z = (PyArrayObject *)PyArray_FROM_OTF(zo, NPY_DOUBLE, NPY_ARRAY_IN_ARRAY);
    if (!Z) goto done;
    S = (PyArrayObject *)PyArray_FROM_OTF(so, NPY_DOUBLE, NPY_ARRAY_IN_ARRAY);
    if (!S) goto done;
    int nd = PyArray_NDIM(Z);
    npy_intp *zs = PyArray_DIMS(Z), *ss = PyArray_DIMS(S);
    if (nd < 2 || zs[nd - 1] != 8) {
        char sh[160];
        format_shape(sh, sizeof sh, nd, zs);
        PyErr_Format(PyExc_ValueError, "poses: expected shape (..., n, 8), got %s", sh);
        goto done;
    }
    int lead = nd - 2;
    npy_intp n = zs[lead];
    if (PyArray_NDIM(S) != nd + 1 || !PyArray_CompareLists(ss, zs, lead + 1) || ss[nd - 1] != 6 ||
        ss[nd] != 6) {
        char sh[160];
        format_shape(sh, sizeof sh, PyArray_NDIM(S), ss);
        PyErr_Format(PyExc_ValueError,
                     "covariances: expected shape (..., n, 6, 6) matching poses, got %s", sh);
        goto done;
    }
    if (io != Py_None) {
        M = (PyArrayObject *)PyArray_FROM_OTF(io, NPY_BOOL, NPY_ARRAY_IN_ARRAY);
        if (!M) goto done;
        if (PyArray_NDIM(M) != lead + 1 || !PyArray_CompareLists(PyArray_DIMS(M), zs, lead + 1)) {
            char sh[160];
            format_shape(sh, sizeof sh, PyArray_NDIM(M), PyArray_DIMS(M));
            PyErr_Format(PyExc_ValueError, "inliers: expected shape (..., n) matching poses, got %s",
                         sh);
            goto done;
        }
    }
    if (n == 0) {
        PyErr_SetString(PyExc_ValueError, "poses: no measurements");
        goto done;
    }
    npy_intp batch = 1;
    for (int k = 0; k < lead; k++) batch *= zs[k];
    /* outputs: mean, covariance, residuals, distances, nis, tested, status, iterations, chi2 */
    {
        npy_intp d[NPY_MAXDIMS + 2];
        for (int k = 0; k < lead; k++) d[k] = zs[k];
        int types[9] = {NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE, NPY_BOOL,
                        NPY_INT64, NPY_INT64, NPY_DOUBLE};
        int core[9] = {1, 2, 2, 1, 1, 1, 0, 0, 0};
        npy_intp cd[9][2] = {{8, 0}, {6, 6}, {n, 6}, {n, 0}, {n, 0}, {n, 0}, {0, 0}, {0, 0}, {0, 0}};
        for (int j = 0; j < 9; j++) {
            if ((j == 4 || j == 5) && !want_nis) continue;
            for (int k = 0; k < core[j]; k++) d[lead + k] = cd[j][k];
            outs[j] = (PyArrayObject *)PyArray_SimpleNew(lead + core[j], d, types[j]);
            if (!outs[j]) goto done;
        }
    }
    size_t nw = dq_fuse_workspace((size_t)n);
    work = (double *)malloc(sizeof(double) * nw);
    zu = (double *)malloc(sizeof(double) * 8 * (size_t)n);
    if (!work || !zu) {
        PyErr_NoMemory();
        goto done;
    }
    const double *zd = PyArray_DATA(Z), *sd = PyArray_DATA(S);
    const unsigned char *id = M ? (const unsigned char *)PyArray_DATA(M) : NULL;
    int code = DQ_OK;
    npy_intp bad_b = 0;
    size_t bad_i = 0;
    const char *bad_name = "poses";
    NPY_BEGIN_THREADS_DEF;
    if (batch * n >= GIL_RELEASE_MIN) NPY_BEGIN_THREADS;
    for (npy_intp b = 0; b < batch && code == DQ_OK; b++) {
        const double *zb = zd + 8 * n * b, *sb = sd + 36 * n * b;
        for (npy_intp i = 0; i < n && code == DQ_OK; i++) {
            code = dq_unit(zb + 8 * i, zu + 8 * i);
            if (code) { bad_i = (size_t)i; bad_name = "poses"; }
            else if (!dq_finite_n(sb + 36 * i, 36)) {
                code = DQ_E_NONFINITE; bad_i = (size_t)i; bad_name = "covariances";
            }
        }
        if (code) { bad_b = b; break; }
        dq_fused f;
        dq_fuse_outputs per = {
            (double *)PyArray_DATA(outs[2]) + 6 * n * b, (double *)PyArray_DATA(outs[3]) + n * b,
            want_nis ? (double *)PyArray_DATA(outs[4]) + n * b : NULL,
            want_nis ? (unsigned char *)PyArray_DATA(outs[5]) + n * b : NULL};
        code = dq_fuse(zu, sb, id ? id + n * b : NULL, (size_t)n, &p, work, &f, &per, &bad_i);
        if (code) { bad_b = b; bad_name = "covariances"; break; }
        memcpy((double *)PyArray_DATA(outs[0]) + 8 * b, f.mean, sizeof f.mean);
        memcpy((double *)PyArray_DATA(outs[1]) + 36 * b, f.covariance, sizeof f.covariance);
        ((npy_int64 *)PyArray_DATA(outs[6]))[b] = f.status;
        ((npy_int64 *)PyArray_DATA(outs[7]))[b] = f.iterations;
        ((double *)PyArray_DATA(outs[8]))[b] = f.chi2;
    }
    NPY_END_THREADS;
    if (code != DQ_OK) {
        char where[256], what[256];
        npy_intp shape[NPY_MAXDIMS + 1];
        for (int k = 0; k < lead; k++) shape[k] = zs[k];
        shape[lead] = n;
        if (code == DQ_E_NO_INLIERS) {
            format_index(where, sizeof where, "inliers", lead, shape, bad_b);
            PyErr_Format(PyExc_ValueError, "%s: selects no measurement", where);
        } else if (code == DQ_E_SINGULAR || code == DQ_E_OVERFLOW) {
            format_index(where, sizeof where, "covariances", lead, shape, bad_b);
            PyErr_Format(PyExc_ValueError, "%s: %s", where,
                         code == DQ_E_SINGULAR ? "the information is not positive definite"
                                               : "the result is not finite (input too large)");
        } else {
            format_index(where, sizeof where, bad_name, lead + 1, shape, bad_b * n + (npy_intp)bad_i);
            if (code == DQ_E_NOT_SPD)
                snprintf(what, sizeof what, "not positive definite");
            else
                problem_text(code, zd + 8 * (n * bad_b + (npy_intp)bad_i), 8, what, sizeof what);
            PyErr_Format(PyExc_ValueError, "%s: %s", where, what);
        }
        goto done;
    }
    result = steal_tuple(outs, 9);
done:
    free(work);
    free(zu);
    Py_XDECREF(Z);
    Py_XDECREF(S);
    Py_XDECREF(M);
    for (int j = 0; j < 9; j++) Py_XDECREF(outs[j]);
    return result;
}

/* An array of `type` and exactly `shape` (nd <= 3), or NULL with a ValueError naming it. */
static PyArrayObject *exact_array(PyObject *o, int type, const char *name, int nd,
                                  const npy_intp *shape)
{
    PyArrayObject *a = (PyArrayObject *)PyArray_FROM_OTF(o, type, NPY_ARRAY_IN_ARRAY);
    if (!a) return NULL;
    if (PyArray_NDIM(a) != nd || !PyArray_CompareLists(PyArray_DIMS(a), shape, nd)) {
        char want[80], got[160];
        format_shape(want, sizeof want, nd, shape);
        format_shape(got, sizeof got, PyArray_NDIM(a), PyArray_DIMS(a));
        PyErr_Format(PyExc_ValueError, "%s: expected shape %s, got %s", name, want, got);
        Py_DECREF(a);
        return NULL;
    }
    return a;
}

/* motion_fit(poses (n, 8), covariances (n, 6, 6), inliers (n,) bool or None, start (8,) or
 * None, stamps (n,), latencies (n,), slots (n,) int, priors (k,), prior_information (k,),
 * twist, twist_information (6, 6) or None, tested (n,) bool, True or None, tol, max_iter,
 * jacobians) -> (mean, twist, ell, H, chi2, status, iterations, dt, residuals, cost, G, nis,
 * tested, P): the constant-twist fit of fusion.h's dq_motion_fit, one problem a call. start
 * None: dq_motion_nearest's inlier (a twist is estimated). tested True: every measurement but
 * an inlier whose leaving out would leave the state undetermined (dq_motion_determined). G is
 * None unless jacobians, nis and tested None without tested; P = H^-1 (dq_spd_inverse). */
static PyObject *py_motion_fit(PyObject *self, PyObject *args)
{
    PyObject *o[12];
    int twist = 0, want_g = 0;
    dq_fuse_params p = {1e-12, 100};
    if (!PyArg_ParseTuple(args, "OOOOOOOOOpOO|dip:motion_fit", &o[0], &o[1], &o[2], &o[3], &o[4],
                          &o[5], &o[6], &o[7], &o[8], &twist, &o[10], &o[11], &p.tol,
                          &p.max_iter, &want_g))
        return NULL;
    if (check_iteration(p.tol, p.max_iter) < 0) return NULL;
    const int pick_start = o[3] == Py_None, find_tested = o[11] == Py_True;
    if (pick_start && !twist) {
        PyErr_SetString(PyExc_ValueError, "start: needed when no twist is estimated");
        return NULL;
    }
    PyArrayObject *a[12] = {NULL}, *outs[14] = {NULL};
    dq_taken *taken = NULL;
    PyObject *result = NULL;
    double *work = NULL, *zu = NULL;
    a[0] = (PyArrayObject *)PyArray_FROM_OTF(o[0], NPY_DOUBLE, NPY_ARRAY_IN_ARRAY);
    if (!a[0]) goto done;
    if (PyArray_NDIM(a[0]) != 2 || PyArray_DIMS(a[0])[1] != 8 || PyArray_DIMS(a[0])[0] == 0) {
        PyErr_SetString(PyExc_ValueError, "poses: expected shape (n, 8), n >= 1");
        goto done;
    }
    npy_intp n = PyArray_DIMS(a[0])[0];
    a[7] = (PyArrayObject *)PyArray_FROM_OTF(o[7], NPY_DOUBLE, NPY_ARRAY_IN_ARRAY);
    if (!a[7]) goto done;
    if (PyArray_NDIM(a[7]) != 1) {
        PyErr_SetString(PyExc_ValueError, "priors: expected shape (k,)");
        goto done;
    }
    npy_intp k = PyArray_DIMS(a[7])[0];
    {
        static const char *names[12] = {"poses", "covariances", "inliers", "start", "stamps",
                                        "latencies", "slots", "priors", "prior_information",
                                        "twist", "twist_information", "tested"};
        /* poses and priors are converted above, twist is a flag (-1: none of these) */
        const int types[12] = {-1, NPY_DOUBLE, NPY_BOOL, NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE,
                               NPY_INT64, -1, NPY_DOUBLE, -1, NPY_DOUBLE, NPY_BOOL};
        const int nds[12] = {0, 3, 1, 1, 1, 1, 1, 0, 1, 0, 2, 1};
        const npy_intp shapes[12][3] = {{0}, {n, 6, 6}, {n}, {8}, {n}, {n}, {n}, {0}, {k},
                                        {0}, {6, 6}, {n}};
        for (int j = 1; j < 12; j++) {
            if (types[j] < 0 || ((j == 2 || j == 3 || j == 10 || j == 11) && o[j] == Py_None) ||
                (j == 11 && find_tested))
                continue;
            if (!(a[j] = exact_array(o[j], types[j], names[j], nds[j], shapes[j]))) goto done;
        }
    }
    const double *zd = PyArray_DATA(a[0]), *sd = PyArray_DATA(a[1]);
    dq_motion_model m = {PyArray_DATA(a[4]), PyArray_DATA(a[5]), PyArray_DATA(a[6]), (size_t)k,
                         PyArray_DATA(a[7]), PyArray_DATA(a[8]), twist,
                         a[10] ? PyArray_DATA(a[10]) : NULL};
    for (npy_intp i = 0; i < n; i++)
        if (m.slot[i] < -1 || m.slot[i] >= k) {
            PyErr_Format(PyExc_ValueError, "slots[%ld]: %lld is not -1 or a latency index < %ld",
                         (long)i, (long long)m.slot[i], (long)k);
            goto done;
        }
    npy_intp dim = (npy_intp)dq_motion_dim(&m);
    {
        /* mean, twist, ell, H, chi2, status, iterations, dt, residuals, cost, G, nis, tested,
         * P */
        const int types[14] = {NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE,
                               NPY_INT64, NPY_INT64, NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE,
                               NPY_DOUBLE, NPY_DOUBLE, NPY_BOOL, NPY_DOUBLE};
        const int nds[14] = {1, 1, 1, 2, 0, 0, 0, 1, 2, 1, 3, 1, 1, 2};
        const npy_intp shapes[14][3] = {{8}, {6}, {k}, {dim, dim}, {0}, {0}, {0}, {n}, {n, 6},
                                        {n}, {n, 6, dim}, {n}, {n}, {dim, dim}};
        const int nis = a[11] || find_tested;
        for (int j = 0; j < 14; j++) {
            if ((j == 10 && !want_g) || ((j == 11 || j == 12) && !nis)) continue;
            if (!(outs[j] = (PyArrayObject *)PyArray_SimpleNew(nds[j], shapes[j], types[j])))
                goto done;
        }
    }
    /* (dq_spd_inverse's workspace fits in the fit's, spent by then) */
    work = (double *)malloc(sizeof(double) * dq_motion_workspace((size_t)n, &m));
    zu = (double *)malloc(sizeof(double) * 8 * (size_t)n);
    if (find_tested) taken = (dq_taken *)malloc(sizeof *taken * (size_t)n);
    if (!work || !zu || (find_tested && !taken)) {
        PyErr_NoMemory();
        goto done;
    }
    int code = DQ_OK;
    size_t bad = 0;
    const char *bad_name = "poses";
    dq_motion_fitted f;
    f.ell = PyArray_DATA(outs[2]);
    f.H = PyArray_DATA(outs[3]);
    dq_motion_outputs per = {PyArray_DATA(outs[7]), PyArray_DATA(outs[8]), PyArray_DATA(outs[9]),
                             outs[10] ? PyArray_DATA(outs[10]) : NULL,
                             outs[11] ? PyArray_DATA(outs[11]) : NULL};
    double start[8];
    const unsigned char *inl = a[2] ? PyArray_DATA(a[2]) : NULL;
    unsigned char *tested = outs[12] ? PyArray_DATA(outs[12]) : NULL;
    NPY_BEGIN_THREADS_DEF;
    NPY_BEGIN_THREADS;
    for (npy_intp i = 0; i < n && code == DQ_OK; i++) {
        if ((code = dq_unit(zd + 8 * i, zu + 8 * i))) bad = (size_t)i;
        else if (!dq_finite_n(sd + 36 * i, 36)) {
            code = DQ_E_NONFINITE; bad = (size_t)i; bad_name = "covariances";
        }
    }
    if (code == DQ_OK && pick_start) {
        size_t j = dq_motion_nearest(&m, inl, (size_t)n);
        if (j == (size_t)n) code = DQ_E_NO_INLIERS;
        else memcpy(start, zu + 8 * j, sizeof start);
    } else if (code == DQ_OK && (code = dq_unit(PyArray_DATA(a[3]), start))) {
        bad_name = "start";
    }
    if (code == DQ_OK && tested) {
        if (find_tested) {
            dq_motion_determined(&m, inl, (size_t)n, taken, tested);
            for (npy_intp i = 0; i < n; i++) tested[i] = tested[i] || (inl && !inl[i]);
        } else {
            memcpy(tested, PyArray_DATA(a[11]), (size_t)n);
        }
    }
    if (code == DQ_OK) {
        code = dq_motion_fit(zu, sd, inl, (size_t)n, &m, start, tested, &p, work, &f, &per,
                             &bad);
        bad_name = "covariances";
    }
    if (code == DQ_OK &&
        !dq_spd_inverse(f.H, (int)dim, work, PyArray_DATA(outs[13])))
        code = DQ_E_SINGULAR;
    NPY_END_THREADS;
    if (code != DQ_OK) {
        char what[256];
        if (code == DQ_E_NO_INLIERS)
            PyErr_SetString(PyExc_ValueError, "inliers: selects no measurement");
        else if (code == DQ_E_SINGULAR)
            PyErr_SetString(PyExc_ValueError, "covariances: the information is not positive definite");
        else if (code == DQ_E_OVERFLOW)
            PyErr_SetString(PyExc_ValueError, "covariances: the result is not finite (input too large)");
        else if (strcmp(bad_name, "start") == 0) {
            problem_text(code, PyArray_DATA(a[3]), 8, what, sizeof what);
            PyErr_Format(PyExc_ValueError, "start: %s", what);
        } else {
            if (code == DQ_E_NOT_SPD)
                snprintf(what, sizeof what, "not positive definite");
            else
                problem_text(code, zd + 8 * bad, 8, what, sizeof what);
            PyErr_Format(PyExc_ValueError, "%s[%zu]: %s", bad_name, bad, what);
        }
        goto done;
    }
    memcpy(PyArray_DATA(outs[0]), f.mean, sizeof f.mean);
    memcpy(PyArray_DATA(outs[1]), f.twist, sizeof f.twist);
    *(double *)PyArray_DATA(outs[4]) = f.chi2;
    *(npy_int64 *)PyArray_DATA(outs[5]) = f.status;
    *(npy_int64 *)PyArray_DATA(outs[6]) = f.iterations;
    result = steal_tuple(outs, 14);
done:
    free(work);
    free(zu);
    free(taken);
    for (int j = 0; j < 12; j++) Py_XDECREF(a[j]);
    for (int j = 0; j < 14; j++) Py_XDECREF(outs[j]);
    return result;
}

/* motion_determined(stamps (n,), latencies (n,), inliers (n,) bool, two_instants) -> (n,) bool:
 * fusion.h's dq_motion_determined; two_instants: a twist without a prior is estimated. */
static PyObject *py_motion_determined(PyObject *self, PyObject *args)
{
    PyObject *o[3];
    int two = 0;
    if (!PyArg_ParseTuple(args, "OOOp:motion_determined", &o[0], &o[1], &o[2], &two)) return NULL;
    PyArrayObject *a[3] = {NULL}, *out = NULL;
    PyObject *result = NULL;
    dq_taken *work = NULL;
    if (!(a[0] = (PyArrayObject *)PyArray_FROM_OTF(o[0], NPY_DOUBLE, NPY_ARRAY_IN_ARRAY)))
        goto done;
    if (PyArray_NDIM(a[0]) != 1) {
        PyErr_SetString(PyExc_ValueError, "stamps: expected shape (n,)");
        goto done;
    }
    npy_intp n = PyArray_DIMS(a[0])[0];
    if (!(a[1] = exact_array(o[1], NPY_DOUBLE, "latencies", 1, &n)) ||
        !(a[2] = exact_array(o[2], NPY_BOOL, "inliers", 1, &n)) ||
        !(out = (PyArrayObject *)PyArray_SimpleNew(1, &n, NPY_BOOL)))
        goto done;
    if (!(work = (dq_taken *)malloc(sizeof *work * (size_t)(n ? n : 1)))) {
        PyErr_NoMemory();
        goto done;
    }
    static const double no_prior[36]; /* any non-NULL: "the twist has a prior" */
    dq_motion_model m = {PyArray_DATA(a[0]), PyArray_DATA(a[1]), NULL, 0, NULL, NULL, 1,
                         two ? NULL : no_prior};
    dq_motion_determined(&m, PyArray_DATA(a[2]), (size_t)n, work, PyArray_DATA(out));
    result = (PyObject *)out;
    out = NULL;
done:
    free(work);
    for (int j = 0; j < 3; j++) Py_XDECREF(a[j]);
    Py_XDECREF(out);
    return result;
}

/* pair_distances(poses (n, 8), covariances (n, 6, 6), candidates (m,) int) -> (m, n): fusion.h's
 * dq_pair_distances, the GIL released. */
static PyObject *py_pair_distances(PyObject *self, PyObject *args)
{
    PyObject *o[3];
    if (!PyArg_ParseTuple(args, "OOO:pair_distances", &o[0], &o[1], &o[2])) return NULL;
    PyArrayObject *a[3] = {NULL}, *out = NULL;
    PyObject *result = NULL;
    if (!(a[0] = (PyArrayObject *)PyArray_FROM_OTF(o[0], NPY_DOUBLE, NPY_ARRAY_IN_ARRAY)))
        goto done;
    if (PyArray_NDIM(a[0]) != 2 || PyArray_DIMS(a[0])[1] != 8) {
        PyErr_SetString(PyExc_ValueError, "poses: expected shape (n, 8)");
        goto done;
    }
    npy_intp n = PyArray_DIMS(a[0])[0], s3[3] = {n, 6, 6};
    if (!(a[1] = exact_array(o[1], NPY_DOUBLE, "covariances", 3, s3)) ||
        !(a[2] = (PyArrayObject *)PyArray_FROM_OTF(o[2], NPY_LONGLONG, NPY_ARRAY_IN_ARRAY)))
        goto done;
    if (PyArray_NDIM(a[2]) != 1) {
        PyErr_SetString(PyExc_ValueError, "candidates: expected shape (m,)");
        goto done;
    }
    npy_intp m = PyArray_DIMS(a[2])[0], s2[2] = {m, n};
    const long long *cand = PyArray_DATA(a[2]);
    for (npy_intp k = 0; k < m; k++)
        if (cand[k] < 0 || cand[k] >= n) {
            PyErr_Format(PyExc_ValueError, "candidates[%zd]: not a measurement", (Py_ssize_t)k);
            goto done;
        }
    if (!(out = (PyArrayObject *)PyArray_SimpleNew(2, s2, NPY_DOUBLE))) goto done;
    size_t bad = 0;
    int code;
    Py_BEGIN_ALLOW_THREADS
    code = dq_pair_distances(PyArray_DATA(a[0]), PyArray_DATA(a[1]), (size_t)n, cand, (size_t)m,
                             PyArray_DATA(out), &bad);
    Py_END_ALLOW_THREADS
    if (code != DQ_OK) {
        PyErr_Format(PyExc_ValueError, "covariances[%zu]: not positive definite", bad);
        goto done;
    }
    result = (PyObject *)out;
    out = NULL;
done:
    for (int j = 0; j < 3; j++) Py_XDECREF(a[j]);
    Py_XDECREF(out);
    return result;
}

/* traj_plan(waypoints (K, 8), mode, radius (K,), times (K,), limits (6,), sigma0)
 * -> (code, bad, plan, duration, segments (K-1, 3) [start, duration, binding]): dq_traj_plan on
 * waypoints service/trajectory.py has checked. plan is the opaque segment table traj_eval reads;
 * code != 0 leaves the message (and the index bad) to the caller. */
static PyObject *py_traj_plan(PyObject *self, PyObject *args)
{
    PyObject *o[4];
    int mode;
    double sigma0;
    if (!PyArg_ParseTuple(args, "OiOOOd:traj_plan", &o[0], &mode, &o[1], &o[2], &o[3], &sigma0))
        return NULL;
    PyArrayObject *a[4] = {NULL};
    PyObject *result = NULL, *plan = NULL;
    PyArrayObject *info = NULL;
    a[0] = (PyArrayObject *)PyArray_FROM_OTF(o[0], NPY_DOUBLE, NPY_ARRAY_IN_ARRAY);
    if (!a[0]) goto done;
    if (PyArray_NDIM(a[0]) != 2 || PyArray_DIMS(a[0])[1] != 8 || PyArray_DIMS(a[0])[0] < 2) {
        PyErr_SetString(PyExc_ValueError, "waypoints: expected shape (K, 8), K >= 2");
        goto done;
    }
    npy_intp K = PyArray_DIMS(a[0])[0], n = K - 1, six = 6;
    {
        static const char *names[3] = {"radius", "times", "limits"};
        for (int j = 1; j < 4; j++)
            if (!(a[j] = exact_array(o[j], NPY_DOUBLE, names[j - 1], 1, j < 3 ? &K : &six))) goto done;
    }
    plan = PyBytes_FromStringAndSize(NULL, (Py_ssize_t)(n * sizeof(dq_traj_seg)));
    npy_intp dims[2] = {n, 3};
    info = (PyArrayObject *)PyArray_ZEROS(2, dims, NPY_DOUBLE, 0);
    if (!plan || !info) goto done;
    const double *L6 = PyArray_DATA(a[3]);
    dq_traj_limits lim = {{L6[0], L6[1]}, {L6[2], L6[3]}, {L6[4], L6[5]}};
    dq_traj_seg *seg = (dq_traj_seg *)PyBytes_AS_STRING(plan);
    double duration = 0.0;
    size_t bad = 0;
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = dq_traj_plan(PyArray_DATA(a[0]), (size_t)K, mode, PyArray_DATA(a[1]), PyArray_DATA(a[2]),
                      &lim, sigma0, seg, &duration, &bad);
    Py_END_ALLOW_THREADS
    if (rc == DQ_TRAJ_E_MEMORY) { PyErr_NoMemory(); goto done; }
    double *row = PyArray_DATA(info);
    for (npy_intp k = 0; !rc && k < n; k++, row += 3) {
        row[0] = seg[k].start;
        row[1] = seg[k].law.t_at[5];
        row[2] = seg[k].bind;
    }
    result = Py_BuildValue("inOdO", rc, (Py_ssize_t)bad, plan, duration, (PyObject *)info);
done:
    for (int j = 0; j < 4; j++) Py_XDECREF(a[j]);
    Py_XDECREF(plan);
    Py_XDECREF(info);
    return result;
}

/* traj_eval(plan, mode, duration, times (N,)) -> (poses (N, 8), linear (N, 3), angular (N, 3)). */
static PyObject *py_traj_eval(PyObject *self, PyObject *args)
{
    PyObject *plan, *to;
    int mode;
    double duration;
    if (!PyArg_ParseTuple(args, "SidO:traj_eval", &plan, &mode, &duration, &to)) return NULL;
    Py_ssize_t bytes = PyBytes_GET_SIZE(plan);
    if (bytes == 0 || bytes % (Py_ssize_t)sizeof(dq_traj_seg)) {
        PyErr_SetString(PyExc_ValueError, "plan: not a segment table of traj_plan");
        return NULL;
    }
    PyArrayObject *t = (PyArrayObject *)PyArray_FROM_OTF(to, NPY_DOUBLE, NPY_ARRAY_IN_ARRAY);
    if (!t) return NULL;
    if (PyArray_NDIM(t) != 1) {
        PyErr_SetString(PyExc_ValueError, "times: expected shape (N,)");
        Py_DECREF(t);
        return NULL;
    }
    npy_intp N = PyArray_DIMS(t)[0], d8[2] = {N, 8}, d3[2] = {N, 3};
    PyArrayObject *outs[3] = {(PyArrayObject *)PyArray_EMPTY(2, d8, NPY_DOUBLE, 0),
                              (PyArrayObject *)PyArray_EMPTY(2, d3, NPY_DOUBLE, 0),
                              (PyArrayObject *)PyArray_EMPTY(2, d3, NPY_DOUBLE, 0)};
    PyObject *result = NULL;
    if (outs[0] && outs[1] && outs[2]) {
        const dq_traj_seg *seg = (const dq_traj_seg *)PyBytes_AS_STRING(plan);
        size_t nseg = (size_t)bytes / sizeof(dq_traj_seg);
        NPY_BEGIN_THREADS_DEF;
        if (N >= GIL_RELEASE_MIN) NPY_BEGIN_THREADS;
        dq_traj_eval(seg, nseg, mode, duration, PyArray_DATA(t), (size_t)N, PyArray_DATA(outs[0]),
                     PyArray_DATA(outs[1]), PyArray_DATA(outs[2]));
        NPY_END_THREADS;
        result = steal_tuple(outs, 3);
    }
    Py_DECREF(t);
    for (int j = 0; j < 3; j++) Py_XDECREF(outs[j]);
    return result;
}

static PyMethodDef methods[] = {
    {"mul", py_mul, METH_VARARGS, "mul(a, b): dual-quaternion product a b."},
    {"conj", py_conj, METH_O, "conj(a): quaternion conjugate of both parts (the inverse of a pose)."},
    {"normalize", py_normalize, METH_O, "normalize(a): divide by the dual-number norm."},
    {"log", py_log, METH_O, "log(a) -> [...,6]."},
    {"exp", py_exp, METH_O, "exp(x[...,6]) -> [...,8]."},
    {"power", py_power, METH_VARARGS, "power(a, tau) = exp(tau log a)."},
    {"sclerp", py_sclerp, METH_VARARGS, "sclerp(a, b, tau)."},
    {"from_matrix", py_from_matrix, METH_O, "from_matrix(T[...,4,4]) -> [...,8]."},
    {"to_matrix", py_to_matrix, METH_O, "to_matrix(a) -> [...,4,4]."},
    {"from_pose", py_from_pose, METH_VARARGS, "from_pose(q[...,4], t[...,3]) -> [...,8]."},
    {"to_pose", py_to_pose, METH_O, "to_pose(a) -> (q[...,4], t[...,3])."},
    {"transform", py_transform, METH_VARARGS, "transform(a, p[...,3]) -> [...,3]."},
    {"screw", py_screw, METH_O, "screw(a) -> (theta, d, [l | m])."},
    {"blend", py_blend, METH_VARARGS, "blend(dqs, weights, method, tol, max_iter)."},
    {"fuse", py_fuse, METH_VARARGS,
     "fuse(poses, covariances, inliers, tol, max_iter, nis) -> (mean, covariance, residuals, "
     "distances, nis, tested, status, iterations, chi2)."},
    {"motion_fit", py_motion_fit, METH_VARARGS, "motion_fit(...): the constant-twist fit (fusion.h)."},
    {"motion_determined", py_motion_determined, METH_VARARGS,
     "motion_determined(stamps, latencies, inliers, two_instants): does the state stay determined "
     "without each measurement (fusion.h)."},
    {"pair_distances", py_pair_distances, METH_VARARGS,
     "pair_distances(poses, covariances, candidates) -> (m, n) squared Mahalanobis distances of "
     "the consensus (fusion.h)."},
    {"traj_plan", py_traj_plan, METH_VARARGS,
     "traj_plan(waypoints, mode, radius, times, limits, sigma0) -> (code, bad, plan, duration, segments)."},
    {"traj_eval", py_traj_eval, METH_VARARGS, "traj_eval(plan, mode, duration, times) -> (poses, linear, angular)."},
    {"lin", py_lin, METH_VARARGS, "lin(dqs, weights): the raw matrix blend -> [...,4,4]."},
    {"blend_request_from_wire", py_blend_request_from_wire, METH_O,
     "blend_request_from_wire(bytes) -> (poses, weights, method, tolerance, max_iterations) or None."},
    {"fuse_stream_from_wire", py_fuse_stream_from_wire, METH_VARARGS,
     "fuse_stream_from_wire(bytes, sym_tol) -> (poses, covariances, times, codes, bodies, "
     "sources, spans) or None."},
    {"measurements_wire", py_measurements_wire, METH_VARARGS,
     "measurements_wire(q, t, covariances, weights, times, sources, bodies) -> bytes: repeated "
     "FuseStreamRequest.measurements."},
    {"blend_batch_wire", py_blend_batch_wire, METH_VARARGS,
     "blend_batch_wire(bytes, max_requests, max_total_poses, max_poses, default_tol, "
     "default_max_iter, max_iter_limit) -> (bytes, n) or None."},
    {"blend_wire", py_blend_wire, METH_VARARGS,
     "blend_wire(bytes, max_poses, default_tol, default_max_iter, max_iter_limit) -> bytes or None."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef moddef = {
    PyModuleDef_HEAD_INIT, "_dqcore",
    "C core of dqpose: dual-quaternion algebra and blending. Use dqpose.dq instead.", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__dqcore(void)
{
    import_array();
    PyObject *m = PyModule_Create(&moddef);
    if (!m) return NULL;
    /* METHODS: {"DIB": 1, ...}, the C enum as it is, for the test against service/dq.py */
    PyObject *codes = PyDict_New();
    if (!codes || PyModule_AddObject(m, "METHODS", codes) < 0) {
        Py_XDECREF(codes);
        Py_DECREF(m);
        return NULL;
    }
#define ADD_METHOD_(name, value)                                                  \
    do {                                                                          \
        PyObject *v_ = PyLong_FromLong(DQ_##name);                                \
        if (!v_ || PyDict_SetItemString(codes, #name, v_) < 0) {                  \
            Py_XDECREF(v_);                                                       \
            Py_DECREF(m);                                                         \
            return NULL;                                                          \
        }                                                                         \
        Py_DECREF(v_);                                                            \
    } while (0);
    DQ_METHODS(ADD_METHOD_)
#undef ADD_METHOD_
    PyModule_AddObject(m, "UNIT_TOL", PyFloat_FromDouble(DQ_UNIT_TOL));
    /* fuse_stream_from_wire's codes up to this one are measurements_to_arrays's, the rest the
     * Tracker's (wire.h) */
    PyModule_AddIntConstant(m, "MEASUREMENT_CONVERT_LAST", DQ_MEAS_CONVERT_LAST);
    PyModule_AddObject(m, "MIN_VARIANCE", PyFloat_FromDouble(DQ_MIN_VARIANCE));
    PyModule_AddObject(m, "MAX_VARIANCE", PyFloat_FromDouble(DQ_MAX_VARIANCE));
    return m;
}
