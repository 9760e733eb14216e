/*
 * py_args.c — the element-wise driver and the error texts of py_args.h.
 */
#include "py_args.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "dq.h"
#include "fusion.h"

typedef struct {
    PyArrayObject *arr;
    const double *data;
    npy_intp core_size;
    int lead_nd;
    npy_intp lead[NPY_MAXDIMS];
    npy_intp stride[NPY_MAXDIMS]; /* in elements of core_size, 0 where broadcast */
} arg;

void format_shape(char *buf, size_t len, int nd, const npy_intp *shape)
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

void problem_text(int code, const double *v, int kind, char *buf, size_t len)
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

void fit_error(int code, const char *inliers, const char *covariances, const char *where,
               const double *pose)
{
    char what[256];
    if (code == DQ_E_NO_INLIERS)
        PyErr_Format(PyExc_ValueError, "%s: selects no measurement", inliers);
    else if (code == DQ_E_SINGULAR)
        PyErr_Format(PyExc_ValueError, "%s: the information is not positive definite",
                     covariances);
    else if (code == DQ_E_OVERFLOW)
        PyErr_Format(PyExc_ValueError, "%s: the result is not finite (input too large)",
                     covariances);
    else if (code == DQ_E_NOT_SPD)
        PyErr_Format(PyExc_ValueError, "%s: not positive definite", where);
    else {
        /* without a pose only its own codes can be told (problem_text reads the pose) */
        problem_text(pose || code == DQ_E_NONFINITE ? code : -1, pose, 8, what, sizeof what);
        PyErr_Format(PyExc_ValueError, "%s: %s", where, what);
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

void format_index(char *buf, size_t len, const char *name, int nd, const npy_intp *shape,
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

/* The broadcast of the present inputs' leading dimensions (right-aligned, as NumPy does): its
 * shape, and each input's strides over it. 0, or -1 with a ValueError. */
typedef struct {
    int nd;
    npy_intp lead[NPY_MAXDIMS];
    npy_intp total;
} broadcast;

static int broadcast_args(arg *a, const int *present, int nin, const in_spec *is, broadcast *b)
{
    b->nd = 0;
    for (int i = 0; i < nin; i++)
        if (present[i] && a[i].lead_nd > b->nd) b->nd = a[i].lead_nd;
    for (int k = 0; k < b->nd; k++) b->lead[k] = 1;
    for (int i = 0; i < nin; i++) {
        if (!present[i]) continue;
        int off = b->nd - a[i].lead_nd;
        for (int k = 0; k < a[i].lead_nd; k++) {
            npy_intp d = a[i].lead[k];
            if (d == 1) continue;
            if (b->lead[off + k] == 1) {
                b->lead[off + k] = d;
            } else if (b->lead[off + k] != d) {
                char s1[160], s2[160];
                format_shape(s1, sizeof s1, a[i].lead_nd, a[i].lead);
                format_shape(s2, sizeof s2, b->nd, b->lead);
                PyErr_Format(PyExc_ValueError,
                             "shape mismatch: %s has leading shape %s, which does not broadcast "
                             "with %s",
                             is[i].name, s1, s2);
                return -1;
            }
        }
    }
    b->total = 1;
    for (int k = 0; k < b->nd; k++) b->total *= b->lead[k];
    for (int i = 0; i < nin; i++) {
        if (!present[i]) continue;
        int off = b->nd - a[i].lead_nd;
        npy_intp st = 1;
        for (int k = b->nd - 1; k >= 0; k--) {
            int ak = k - off;
            if (ak < 0 || a[i].lead[ak] == 1) {
                a[i].stride[k] = 0;
            } else {
                a[i].stride[k] = st;
                st *= a[i].lead[ak];
            }
        }
    }
    return 0;
}

/* The outputs, the broadcast shape followed by each one's core (n for a free core size), and
 * the doubles of one element of each. 0, or -1 with the exception set. */
static int new_outputs(const out_spec *os, int nout, const broadcast *b, npy_intp n,
                       PyArrayObject **outs, npy_intp *out_core)
{
    for (int j = 0; j < nout; j++) {
        npy_intp dims[NPY_MAXDIMS + 2];
        for (int k = 0; k < b->nd; k++) dims[k] = b->lead[k];
        for (int k = 0; k < os[j].ncore; k++) dims[b->nd + k] = os[j].core[k] < 0 ? n : os[j].core[k];
        outs[j] = (PyArrayObject *)PyArray_SimpleNew(b->nd + os[j].ncore, dims, NPY_DOUBLE);
        if (!outs[j]) return -1;
    }
    for (int j = 0; j < nout; j++) {
        out_core[j] = 1;
        for (int k = 0; k < os[j].ncore; k++) out_core[j] *= os[j].core[k] < 0 ? n : os[j].core[k];
    }
    return 0;
}

/* The kernel over every element of the broadcast, the GIL released for a batch: DQ_OK, or the
 * first failure's code with *bad_off the failing input's element offset (e->bad_arg says which
 * input). */
static int each_element(kernel_fn kern, elem *e, const arg *a, const int *present, int nin,
                        const broadcast *b, PyArrayObject **outs, const npy_intp *out_core,
                        int nout, npy_intp *bad_off)
{
    int code = DQ_OK;
    npy_intp idx[NPY_MAXDIMS];
    npy_intp off[MAX_IN];
    for (int k = 0; k < b->nd; k++) idx[k] = 0;
    for (int i = 0; i < nin; i++) off[i] = 0;

    NPY_BEGIN_THREADS_DEF;
    if (b->total >= GIL_RELEASE_MIN) NPY_BEGIN_THREADS;
    for (npy_intp t = 0; t < b->total; t++) {
        for (int i = 0; i < nin; i++) e->in[i] = present[i] ? a[i].data + off[i] * a[i].core_size : NULL;
        for (int j = 0; j < nout; j++) e->out[j] = (double *)PyArray_DATA(outs[j]) + t * out_core[j];
        code = kern(e);
        if (code != DQ_OK) {
            *bad_off = off[e->bad_arg];
            break;
        }
        /* odometer over the broadcast index */
        for (int k = b->nd - 1; k >= 0; k--) {
            idx[k]++;
            for (int i = 0; i < nin; i++) off[i] += a[i].stride[k];
            if (idx[k] < b->lead[k]) break;
            for (int i = 0; i < nin; i++) off[i] -= a[i].stride[k] * b->lead[k];
            idx[k] = 0;
        }
    }
    NPY_END_THREADS;
    return code;
}

/* The ValueError of a kernel's failure: the argument, its index (its own leading index, then the
 * sub-element of the set) and the problem. */
static void element_error(int code, const elem *e, const arg *a, const in_spec *is, npy_intp n,
                          npy_intp bad_off)
{
    if (code == DQ_E_SET_SIZE) { /* every set has the same size: no index to name */
        PyErr_Format(PyExc_ValueError, "%s: sclerp blends exactly 2 poses, got %zd", is[0].name,
                     (Py_ssize_t)n);
        return;
    }
    int bi = e->bad_arg;
    const in_spec *s = &is[bi];
    int nd = a[bi].lead_nd;
    npy_intp shape[NPY_MAXDIMS + 1];
    for (int k = 0; k < nd; k++) shape[k] = a[bi].lead[k];
    npy_intp flat = bad_off;
    npy_intp sub_size = a[bi].core_size;
    int has_sub = s->ncore >= 1 && s->core[0] < 0;
    if (has_sub) {
        shape[nd++] = n;
        flat = flat * n + e->bad_sub;
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
}

PyObject *run_kernel(kernel_fn kern, void *ctx, int nin, PyObject **objs, const in_spec *is,
                     int nout, const out_spec *os, size_t scratch_per_n)
{
    arg a[MAX_IN];
    PyArrayObject *outs[MAX_OUT] = {NULL, NULL, NULL};
    int present[MAX_IN];
    npy_intp n = -1, out_core[MAX_OUT], bad_off = 0;
    PyObject *result = NULL;
    double *scratch = NULL;
    broadcast b;
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
    if (broadcast_args(a, present, nin, is, &b) < 0) goto done;
    if (new_outputs(os, nout, &b, n, outs, out_core) < 0) goto done;
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
    int code = each_element(kern, &e, a, present, nin, &b, outs, out_core, nout, &bad_off);
    if (code != DQ_OK) {
        element_error(code, &e, a, is, n, bad_off);
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

int check_iteration(double tol, int max_iter)
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

PyArrayObject *exact_array(PyObject *o, int type, const char *name, int nd, const npy_intp *shape)
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

PyObject *steal_tuple(PyArrayObject **outs, int n)
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
