/*
 * py_dq.c — the Python functions of the dual-quaternion algebra (dq.h) and the blends (blend.h):
 * one kernel per function, run element-wise over broadcast arrays by run_kernel (py_args.h).
 * service/dq.py is their Python interface.
 */
#include "py_args.h"

#include <string.h>

#include "blend.h"
#include "dq.h"
#include "py_functions.h"

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

static const in_spec S_DQ_A = {"a", 1, {8, 0}, 0};
static const in_spec S_DQ_B = {"b", 1, {8, 0}, 0};
static const out_spec O_DQ = {1, {8, 0}};

static PyObject *call1(kernel_fn k, PyObject *x, in_spec s, out_spec o)
{
    PyObject *objs[1] = {x};
    return run_kernel(k, NULL, 1, objs, &s, 1, &o, 0);
}

PyObject *py_mul(PyObject *self, PyObject *args)
{
    PyObject *objs[2];
    if (!PyArg_ParseTuple(args, "OO:mul", &objs[0], &objs[1])) return NULL;
    in_spec is[2] = {S_DQ_A, S_DQ_B};
    return run_kernel(k_mul, NULL, 2, objs, is, 1, &O_DQ, 0);
}

PyObject *py_conj(PyObject *self, PyObject *x) { return call1(k_conj, x, S_DQ_A, O_DQ); }
PyObject *py_normalize(PyObject *self, PyObject *x) { return call1(k_normalize, x, S_DQ_A, O_DQ); }
PyObject *py_log(PyObject *self, PyObject *x)
{
    out_spec o = {1, {6, 0}};
    return call1(k_log, x, S_DQ_A, o);
}
PyObject *py_exp(PyObject *self, PyObject *x)
{
    in_spec s = {"x", 1, {6, 0}, 0};
    return call1(k_exp, x, s, O_DQ);
}
PyObject *py_from_matrix(PyObject *self, PyObject *x)
{
    in_spec s = {"T", 2, {4, 4}, 0};
    return call1(k_from_matrix, x, s, O_DQ);
}
PyObject *py_to_matrix(PyObject *self, PyObject *x)
{
    out_spec o = {2, {4, 4}};
    return call1(k_to_matrix, x, S_DQ_A, o);
}

PyObject *py_power(PyObject *self, PyObject *args)
{
    PyObject *objs[2];
    if (!PyArg_ParseTuple(args, "OO:power", &objs[0], &objs[1])) return NULL;
    in_spec is[2] = {S_DQ_A, {"tau", 0, {0, 0}, 0}};
    return run_kernel(k_power, NULL, 2, objs, is, 1, &O_DQ, 0);
}

/* Independent pairs of one shape (a, b (..., 8), tau (...)): interpolated by the vectorised
 * dq_sclerp_pairs_checked straight from the arrays, without the per-element kernel call.
 * Returns NULL without an exception when the fast path does not apply or an element is invalid;
 * the general path then runs (and names the bad element). */
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
    if (!out) {
        PyErr_Clear();
        return NULL;
    }
    const double *a = PyArray_DATA(A), *b = PyArray_DATA(B), *t = PyArray_DATA(T);
    int rc;
    NPY_BEGIN_THREADS_DEF;
    NPY_BEGIN_THREADS;
    rc = dq_sclerp_pairs_checked(a, b, t, (size_t)n, PyArray_DATA(out));
    NPY_END_THREADS;
    if (rc != DQ_OK) {
        Py_DECREF(out);
        return NULL;
    }
    return (PyObject *)out;
}

PyObject *py_sclerp(PyObject *self, PyObject *args)
{
    PyObject *objs[3];
    if (!PyArg_ParseTuple(args, "OOO:sclerp", &objs[0], &objs[1], &objs[2])) return NULL;
    PyObject *fast = sclerp_pairs_fast(objs);
    if (fast) return fast;
    in_spec is[3] = {S_DQ_A, S_DQ_B, {"tau", 0, {0, 0}, 0}};
    sclerp_ctx c;
    memset(&c, 0, sizeof c);
    return run_kernel(k_sclerp, &c, 3, objs, is, 1, &O_DQ, 0);
}

PyObject *py_from_pose(PyObject *self, PyObject *args)
{
    PyObject *objs[2];
    if (!PyArg_ParseTuple(args, "OO:from_pose", &objs[0], &objs[1])) return NULL;
    in_spec is[2] = {{"q", 1, {4, 0}, 0}, {"t", 1, {3, 0}, 0}};
    return run_kernel(k_from_pose, NULL, 2, objs, is, 1, &O_DQ, 0);
}

PyObject *py_to_pose(PyObject *self, PyObject *x)
{
    PyObject *objs[1] = {x};
    in_spec is[1] = {S_DQ_A};
    out_spec os[2] = {{1, {4, 0}}, {1, {3, 0}}};
    return run_kernel(k_to_pose, NULL, 1, objs, is, 2, os, 0);
}

PyObject *py_transform(PyObject *self, PyObject *args)
{
    PyObject *objs[2];
    if (!PyArg_ParseTuple(args, "OO:transform", &objs[0], &objs[1])) return NULL;
    in_spec is[2] = {S_DQ_A, {"p", 1, {3, 0}, 0}};
    out_spec o = {1, {3, 0}};
    return run_kernel(k_transform, NULL, 2, objs, is, 1, &o, 0);
}

PyObject *py_screw(PyObject *self, PyObject *x)
{
    PyObject *objs[1] = {x};
    in_spec is[1] = {S_DQ_A};
    /* theta, d, and [l | m] packed as 6 values; the Python side splits them. */
    out_spec os[3] = {{0, {0, 0}}, {0, {0, 0}}, {1, {6, 0}}};
    return run_kernel(k_screw, NULL, 1, objs, is, 3, os, 0);
}

static const in_spec S_SET[2] = {{"dqs", 2, {-1, 8}, 0}, {"weights", 1, {-1, 0}, 1}};

/* blend(dqs, weights, method, tol, max_iter) -> out, or (out, iterations, residual) for DIB */
PyObject *py_blend(PyObject *self, PyObject *args)
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
        return run_kernel(k_blend, &p, 2, objs, S_SET, 3, os, 9);
    }
    return run_kernel(k_blend, &p, 2, objs, S_SET, 1, &O_DQ, 9);
}

/* lin(dqs, weights) -> the raw matrix blend (..., 4, 4) */
PyObject *py_lin(PyObject *self, PyObject *args)
{
    PyObject *objs[2];
    if (!PyArg_ParseTuple(args, "OO:lin", &objs[0], &objs[1])) return NULL;
    out_spec o = {2, {4, 4}};
    return run_kernel(k_lin, NULL, 2, objs, S_SET, 1, &o, 9);
}
