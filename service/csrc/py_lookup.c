/*
 * py_lookup.c — _dqcore.lookup, lookup.h's Lookup on a store's columns and its sources' table
 * (service/lookup.py prepares them), the GIL released for the fits. Rows and codes are checked
 * against the arrays here; the columns are the store's, checked when they came in.
 */
#include "py_args.h"

#include <math.h>
#include <string.h>

#include "dq.h"
#include "lookup.h"
#include "py_functions.h"

enum { A_IDS, A_POSES, A_COVS, A_TIMES, A_CODES, A_LAT, A_LATW, A_E, A_EINFO, A_UNC, A_ROWS_A,
       A_ROWS_B, A_TWIST, A_WARM_A, A_WARM_B, A_L, A_EHAT, A_REC_A, A_REC_B, A_REC_AB,
       A_COUNT };

static const char *const names[A_COUNT] = {
    "ids", "poses", "covariances", "times", "codes", "latency", "latency_information", "extrinsics",
    "extrinsic_information", "uncertain", "rows_a", "rows_b", "twist_information", "warm_a",
    "warm_b", "latencies", "extrinsic_starts", "record_a", "record_b", "record_ab"};

/* Trailing shapes (-1: the leading dimension, any; -2: ncodes); None allowed where optional. */
static const int types[A_COUNT] = {NPY_INT64, NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE, NPY_INT64,
                                   NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE, NPY_BOOL,
                                   NPY_INT64, NPY_INT64, NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE,
                                   NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE};
static const int nds[A_COUNT] = {1, 2, 3, 1, 1, 1, 1, 2, 3, 1, 1, 1, 2, 1, 1, 1, 2, 1, 1, 1};
static const npy_intp shapes[A_COUNT][3] = {
    {-1}, {-1, 8}, {-1, 6, 6}, {-1}, {-1}, {-2}, {-2}, {-2, 8}, {-2, 6, 6}, {-2}, {-1}, {-1},
    {6, 6}, {15}, {15}, {-2}, {-2, 8}, {-1}, {-1}, {-1}};
static const int optional[A_COUNT] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 0, 0,
                                      1, 1, 1};

static int lookup_arrays(PyObject **o, PyArrayObject **a)
{
    npy_intp nc = -1;
    for (int j = 0; j < A_COUNT; j++) {
        if (optional[j] && o[j] == Py_None) continue;
        a[j] = (PyArrayObject *)PyArray_FROM_OTF(o[j], types[j], NPY_ARRAY_IN_ARRAY);
        if (!a[j]) return -1;
        int ok = PyArray_NDIM(a[j]) == nds[j];
        for (int d = 0; ok && d < nds[j]; d++) {
            const npy_intp want = shapes[j][d], got = PyArray_DIMS(a[j])[d];
            if (want == -2 && nc < 0) nc = got;
            ok = want == -1 || got == (want == -2 ? nc : want);
        }
        if (!ok) {
            PyErr_Format(PyExc_ValueError, "%s: not of the shape the store's columns give",
                         names[j]);
            return -1;
        }
    }
    const npy_intp rows = PyArray_DIMS(a[A_TIMES])[0];
    if (PyArray_DIMS(a[A_POSES])[0] < rows || PyArray_DIMS(a[A_COVS])[0] < rows ||
        PyArray_DIMS(a[A_CODES])[0] < rows || PyArray_DIMS(a[A_IDS])[0] < rows) {
        PyErr_SetString(PyExc_ValueError, "poses: fewer rows than times");
        return -1;
    }
    const npy_int64 *codes = PyArray_DATA(a[A_CODES]);
    for (int side = A_ROWS_A; side <= A_ROWS_B; side++) {
        if (!a[side]) continue;
        const npy_int64 *r = PyArray_DATA(a[side]);
        for (npy_intp i = 0; i < PyArray_DIMS(a[side])[0]; i++)
            if (r[i] < 0 || r[i] >= rows || codes[r[i]] < 0 || codes[r[i]] >= nc) {
                PyErr_Format(PyExc_ValueError, "%s[%zd]: %lld is not a row of the store",
                             names[side], (Py_ssize_t)i, (long long)r[i]);
                return -1;
            }
    }
    return 0;
}

static void body_in(PyArrayObject *rows, PyArrayObject *warm, dq_lookup_body *b)
{
    memset(b, 0, sizeof *b);
    if (!rows) return;
    b->rows = PyArray_DATA(rows);
    b->n = (size_t)PyArray_DIMS(rows)[0];
    if (warm) {
        const double *w = PyArray_DATA(warm);
        b->warm = dq_finite_n(w, 15);
        b->t0 = w[0];
        memcpy(b->X, w + 1, 8 * sizeof(double));
        memcpy(b->V, w + 9, 6 * sizeof(double));
    }
}

static PyObject *body_out(const dq_lookup_body *b)
{
    if (!b->n) Py_RETURN_NONE;
    npy_intp n = 15;
    PyArrayObject *w = (PyArrayObject *)PyArray_SimpleNew(1, &n, NPY_DOUBLE);
    if (!w) return NULL;
    double *d = PyArray_DATA(w);
    d[0] = b->t0;
    memcpy(d + 1, b->X, 8 * sizeof(double));
    memcpy(d + 9, b->V, 6 * sizeof(double));
    return (PyObject *)w;
}

static PyObject *record_out(double *r, size_t n)
{
    if (!r) Py_RETURN_NONE;
    npy_intp dim = (npy_intp)n;
    PyArrayObject *o = (PyArrayObject *)PyArray_SimpleNew(1, &dim, NPY_DOUBLE);
    if (o) memcpy(PyArray_DATA(o), r, sizeof(double) * n);
    return (PyObject *)o;
}

/* lookup(ids, poses, covariances, times, codes, latency, latency_information, extrinsics,
 * extrinsic_information, uncertain, rows_a, rows_b, twist_information, warm_a, warm_b,
 * latencies, extrinsic_starts, record_a, record_b, record_ab, at, max_extrapolation, tol,
 * max_iter) -> None (another path's Lookup) or (pose, covariance, warm_a, warm_b, latencies,
 * extrinsic_starts, record_a, record_b, record_ab, shared): lookup.h's dq_lookup of
 * T_a^-1 T_b, a the target's rows (None: the world frame), b the source's. warm_*: [t0, X (8),
 * V (6)] or None; latencies and extrinsic_starts by source code (NaN: none), copied and returned
 * with the fitted ones; record_*: the fits' records (lookup.h; None: none, or not fitted). */
PyObject *py_lookup(PyObject *self, PyObject *args)
{
    PyObject *o[A_COUNT];
    double at, max_extrapolation;
    dq_fuse_params p = {1e-12, 100};
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOOOOOOOOOOdddi:lookup", &o[0], &o[1], &o[2], &o[3],
                          &o[4], &o[5], &o[6], &o[7], &o[8], &o[9], &o[10], &o[11], &o[12],
                          &o[13], &o[14], &o[15], &o[16], &o[17], &o[18], &o[19], &at,
                          &max_extrapolation, &p.tol, &p.max_iter))
        return NULL;
    if (check_iteration(p.tol, p.max_iter) < 0) return NULL;
    PyArrayObject *a[A_COUNT] = {NULL}, *L = NULL, *Ehat = NULL, *pose = NULL, *cov = NULL;
    PyObject *result = NULL;
    dq_lookup_args la;
    memset(&la, 0, sizeof la);
    if (lookup_arrays(o, a) < 0) goto done;
    L = (PyArrayObject *)PyArray_NewCopy(a[A_L], NPY_CORDER);
    Ehat = (PyArrayObject *)PyArray_NewCopy(a[A_EHAT], NPY_CORDER);
    npy_intp d8 = 8, d66[2] = {6, 6};
    pose = (PyArrayObject *)PyArray_SimpleNew(1, &d8, NPY_DOUBLE);
    cov = (PyArrayObject *)PyArray_SimpleNew(2, d66, NPY_DOUBLE);
    if (!L || !Ehat || !pose || !cov) goto done;
    const dq_lookup_store s = {(size_t)PyArray_DIMS(a[A_TIMES])[0], PyArray_DATA(a[A_IDS]),
                               PyArray_DATA(a[A_POSES]), PyArray_DATA(a[A_COVS]),
                               PyArray_DATA(a[A_TIMES]), PyArray_DATA(a[A_CODES]),
                               (size_t)PyArray_DIMS(a[A_LAT])[0], PyArray_DATA(a[A_LAT]),
                               PyArray_DATA(a[A_LATW]), PyArray_DATA(a[A_E]),
                               PyArray_DATA(a[A_EINFO]), PyArray_DATA(a[A_UNC])};
    dq_lookup_body body[2];
    body_in(a[A_ROWS_A], a[A_WARM_A], &body[0]);
    body_in(a[A_ROWS_B], a[A_WARM_B], &body[1]);
    la.at = at;
    la.twist_w = a[A_TWIST] ? PyArray_DATA(a[A_TWIST]) : NULL;
    la.max_extrapolation = max_extrapolation;
    la.p = p;
    la.L = PyArray_DATA(L);
    la.Ehat = PyArray_DATA(Ehat);
    for (int r = 0; r < 3; r++)
        if (a[A_REC_A + r]) {
            la.rec_in[r] = PyArray_DATA(a[A_REC_A + r]);
            la.rec_in_n[r] = (size_t)PyArray_DIMS(a[A_REC_A + r])[0];
        }
    int shared = 0, rc;
    Py_BEGIN_ALLOW_THREADS
    rc = dq_lookup(&s, body, &la, PyArray_DATA(pose), PyArray_DATA(cov), &shared);
    Py_END_ALLOW_THREADS
    if (rc == DQ_LOOKUP_NOMEM) {
        PyErr_NoMemory();
        goto done;
    }
    if (rc) {
        result = Py_None;
        Py_INCREF(result);
        goto done;
    }
    PyObject *out[5] = {body_out(&body[0]), body_out(&body[1]),
                        record_out(la.rec_out[0], la.rec_out_n[0]),
                        record_out(la.rec_out[1], la.rec_out_n[1]),
                        record_out(la.rec_out[2], la.rec_out_n[2])};
    if (out[0] && out[1] && out[2] && out[3] && out[4])
        result = Py_BuildValue("(OOOOOOOOOO)", pose, cov, out[0], out[1], L, Ehat, out[2],
                               out[3], out[4], shared ? Py_True : Py_False);
    for (int r = 0; r < 5; r++) Py_XDECREF(out[r]);
done:
    for (int r = 0; r < 3; r++) free(la.rec_out[r]);
    for (int j = 0; j < A_COUNT; j++) Py_XDECREF(a[j]);
    Py_XDECREF(L);
    Py_XDECREF(Ehat);
    Py_XDECREF(pose);
    Py_XDECREF(cov);
    return result;
}

/* relative_pose_bytes(pose (8,), covariance (6, 6), time) -> bytes: a RelativePose
 * (lookup.h's dq_relative_pose_write); the pose made unit first (a ValueError when it is not). */
PyObject *py_relative_pose_bytes(PyObject *self, PyObject *args)
{
    PyObject *po, *co;
    double time;
    if (!PyArg_ParseTuple(args, "OOd:relative_pose_bytes", &po, &co, &time)) return NULL;
    static const npy_intp s8[1] = {8}, s66[2] = {6, 6};
    PyArrayObject *pa = exact_array(po, NPY_DOUBLE, "pose", 1, s8), *ca = NULL;
    PyObject *result = NULL;
    if (!pa || !(ca = exact_array(co, NPY_DOUBLE, "covariance", 2, s66))) goto done;
    double u[8];
    if (dq_unit(PyArray_DATA(pa), u)) {
        PyErr_SetString(PyExc_ValueError, "pose: not a unit dual quaternion");
        goto done;
    }
    unsigned char buf[DQ_RELATIVE_POSE_MAX];
    size_t n = dq_relative_pose_write(u, PyArray_DATA(ca), time, buf);
    result = PyBytes_FromStringAndSize((const char *)buf, (Py_ssize_t)n);
done:
    Py_XDECREF(pa);
    Py_XDECREF(ca);
    return result;
}
