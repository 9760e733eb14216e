/*
 * py_joint.c — the Python function of the joint fit with uncertain extrinsics (joint.h:
 * joint_fit), on arrays service/fusion/extrinsics.py has prepared. Poses, starts and extrinsics
 * are checked unit and the matrices finite here, the GIL released meanwhile.
 */
#include "py_args.h"

#include <stdlib.h>
#include <string.h>

#include "dq.h"
#include "joint.h"
#include "py_functions.h"

enum { A_POSES, A_COV, A_INLIERS, A_COUNTS, A_STAMPS, A_LATENCIES, A_LSLOTS, A_ESLOTS,
       A_STARTS, A_TWISTS, A_TFLAGS, A_TINFO, A_TPRIORS, A_LSTARTS, A_PRIORS, A_PINFO,
       A_EXT, A_EINFO, A_COUNT };

static const char *const joint_names[A_COUNT] = {
    "poses", "covariances", "inliers", "counts", "stamps", "latencies", "latency_slots",
    "extrinsic_slots", "starts", "twists", "twist_flags", "twist_information", "twist_priors",
    "latency_starts", "priors", "prior_information", "extrinsics", "extrinsic_information"};

/* The arguments o[] as arrays a[] of their types, their shapes checked against N measurements,
 * K parts, k latencies and m extrinsics (the first dimension of poses, counts, priors and
 * extrinsics); a slot outside its range named. 0, or -1 with a ValueError. */
static int joint_arrays(PyObject **o, PyArrayObject **a, npy_intp *dims)
{
    /* N, K, k, m from the arrays that define them */
    static const int defines[4] = {A_POSES, A_COUNTS, A_PRIORS, A_EXT};
    static const int first_nd[4] = {2, 1, 1, 2};
    static const char *const first_shape[4] = {"(N, 8)", "(K,)", "(k,)", "(m, 8)"};
    for (int d = 0; d < 4; d++) {
        const int j = defines[d];
        a[j] = (PyArrayObject *)PyArray_FROM_OTF(o[j], j == A_COUNTS ? NPY_INT64 : NPY_DOUBLE,
                                                 NPY_ARRAY_IN_ARRAY);
        if (!a[j]) return -1;
        if (PyArray_NDIM(a[j]) != first_nd[d] || (first_nd[d] == 2 && PyArray_DIMS(a[j])[1] != 8)) {
            PyErr_Format(PyExc_ValueError, "%s: expected shape %s", joint_names[j],
                         first_shape[d]);
            return -1;
        }
        dims[d] = PyArray_DIMS(a[j])[0];
    }
    const npy_intp N = dims[0], K = dims[1], k = dims[2], m = dims[3];
    /* -1: converted above */
    const int types[A_COUNT] = {-1, NPY_DOUBLE, NPY_BOOL, -1, NPY_DOUBLE, NPY_DOUBLE, NPY_INT64,
                                NPY_INT64, NPY_DOUBLE, NPY_DOUBLE, NPY_BOOL, NPY_DOUBLE,
                                NPY_BOOL, NPY_DOUBLE, -1, NPY_DOUBLE, -1, NPY_DOUBLE};
    const int nds[A_COUNT] = {0, 3, 1, 0, 1, 1, 1, 1, 2, 2, 1, 3, 1, 1, 0, 1, 0, 3};
    const npy_intp shapes[A_COUNT][3] = {{0}, {N, 6, 6}, {N}, {0}, {N}, {N}, {N}, {N}, {K, 8},
                                         {K, 6}, {K}, {K, 6, 6}, {K}, {k}, {0}, {k}, {0},
                                         {m, 6, 6}};
    for (int j = 0; j < A_COUNT; j++) {
        if (types[j] < 0 || (j == A_INLIERS && o[j] == Py_None)) continue;
        if (!(a[j] = exact_array(o[j], types[j], joint_names[j], nds[j], shapes[j]))) return -1;
    }
    const npy_int64 *counts = PyArray_DATA(a[A_COUNTS]);
    npy_int64 total = 0;
    for (npy_intp j = 0; j < K; j++) {
        if (counts[j] < 0) {
            PyErr_Format(PyExc_ValueError, "counts[%zd]: %lld is negative", (Py_ssize_t)j,
                         (long long)counts[j]);
            return -1;
        }
        total += counts[j];
    }
    if (total != N) {
        PyErr_Format(PyExc_ValueError, "counts: they sum to %lld, not the %zd poses",
                     (long long)total, (Py_ssize_t)N);
        return -1;
    }
    const int slots[2] = {A_LSLOTS, A_ESLOTS};
    const npy_intp limit[2] = {k, m};
    for (int s = 0; s < 2; s++) {
        const npy_int64 *v = PyArray_DATA(a[slots[s]]);
        for (npy_intp i = 0; i < N; i++)
            if (v[i] < -1 || v[i] >= limit[s]) {
                PyErr_Format(PyExc_ValueError, "%s[%zd]: %lld is not -1 or an index < %zd",
                             joint_names[slots[s]], (Py_ssize_t)i, (long long)v[i],
                             (Py_ssize_t)limit[s]);
                return -1;
            }
    }
    return 0;
}

/* Outputs: X, V, L, Ehat, H, P, g, dt, residuals, cost, G, nis, tested (G NULL without
 * want_g, nis and tested without want_nis). 0, or -1. */
enum { O_X, O_V, O_L, O_E, O_H, O_P, O_G, O_DT, O_R, O_COST, O_JAC, O_NIS, O_TESTED, O_COUNT };

static int joint_outputs(PyArrayObject **outs, const npy_intp *dims, npy_intp D, int want_g,
                         int want_nis)
{
    const npy_intp N = dims[0], K = dims[1], k = dims[2], m = dims[3];
    const int nds[O_COUNT] = {2, 2, 1, 2, 2, 2, 1, 1, 2, 1, 3, 1, 1};
    const npy_intp shapes[O_COUNT][3] = {{K, 8}, {K, 6}, {k}, {m, 8}, {D, D}, {D, D}, {D},
                                         {N}, {N, 6}, {N}, {N, 6, D}, {N}, {N}};
    for (int j = 0; j < O_COUNT; j++) {
        if ((j == O_JAC && !want_g) || ((j == O_NIS || j == O_TESTED) && !want_nis)) continue;
        outs[j] = (PyArrayObject *)PyArray_SimpleNew(nds[j], shapes[j],
                                                     j == O_TESTED ? NPY_BOOL : NPY_DOUBLE);
        if (!outs[j]) return -1;
    }
    return 0;
}

/* The checks and the fit with the GIL released: poses, starts and extrinsics unit (their unit
 * forms into zu, X and ext), the matrices finite, then dq_joint_fit. A DQ_E* code with *bad
 * and *bad_name the entry and argument it concerns. */
static int joint_run(PyArrayObject **a, const npy_intp *dims, dq_joint_model *jm, double *zu,
                     double *ext, const dq_fuse_params *p, double *work, dq_taken *taken,
                     dq_joint_state *st, const dq_joint_outputs *per, size_t *bad,
                     const char **bad_name)
{
    const int units[3] = {A_POSES, A_STARTS, A_EXT};
    double *unit_out[3] = {zu, st->X, ext};
    const int finite[4] = {A_COV, A_TINFO, A_PINFO, A_EINFO};
    const size_t fsize[4] = {36, 36, 1, 36};
    int code = DQ_OK;
    NPY_BEGIN_THREADS_DEF;
    NPY_BEGIN_THREADS;
    for (int u = 0; u < 3 && code == DQ_OK; u++) {
        const double *v = PyArray_DATA(a[units[u]]);
        for (npy_intp i = 0; i < PyArray_DIMS(a[units[u]])[0] && code == DQ_OK; i++)
            if ((code = dq_unit(v + 8 * i, unit_out[u] + 8 * i))) {
                *bad = (size_t)i;
                *bad_name = joint_names[units[u]];
            }
    }
    for (int f = 0; f < 4 && code == DQ_OK; f++) {
        const double *v = PyArray_DATA(a[finite[f]]);
        for (npy_intp i = 0; i < PyArray_DIMS(a[finite[f]])[0] && code == DQ_OK; i++)
            if (!dq_finite_n(v + fsize[f] * i, fsize[f])) {
                code = DQ_E_NONFINITE;
                *bad = (size_t)i;
                *bad_name = joint_names[finite[f]];
            }
    }
    if (code == DQ_OK) {
        jm->E = ext;
        code = dq_joint_fit(zu, PyArray_DATA(a[A_COV]), a[A_INLIERS] ? PyArray_DATA(a[A_INLIERS])
                                                                      : NULL,
                            (size_t)dims[0], jm, p, work, taken, st, per, bad);
        *bad_name = "covariances";
    }
    NPY_END_THREADS;
    return code;
}

/* The ValueError of joint_run's failure. */
static void joint_error(int code, const char *bad_name, size_t bad, PyArrayObject **a)
{
    char where[64];
    snprintf(where, sizeof where, "%s[%zu]", bad_name, bad);
    int j = strcmp(bad_name, "starts") == 0 ? A_STARTS
            : strcmp(bad_name, "extrinsics") == 0 ? A_EXT
            : strcmp(bad_name, "poses") == 0 ? A_POSES : -1;
    fit_error(code, "inliers", "covariances", where,
              j < 0 ? NULL : (const double *)PyArray_DATA(a[j]) + 8 * bad);
}

/* joint_fit(poses (N, 8), covariances (N, 6, 6), inliers (N,) bool or None, counts (K,) int,
 * stamps (N,), latencies (N,), latency_slots (N,) int, extrinsic_slots (N,) int, starts (K, 8),
 * twists (K, 6), twist_flags (K,) bool, twist_information (K, 6, 6), twist_priors (K,) bool,
 * latency_starts (k,), priors (k,), prior_information (k,), extrinsics (m, 8),
 * extrinsic_information (m, 6, 6), nis=False, tol=1e-12, max_iter=100, jacobians=False)
 * -> (X, V, L, Ehat, H, P, g, dt, residuals, cost, G, nis, tested, chi2, status, iterations):
 * joint.h's dq_joint_fit, one problem a call. Part j is the next counts[j] measurements, its
 * twist estimated where twist_flags[j], with the prior twist_information[j] where
 * twist_priors[j]. G is None unless jacobians, nis and tested None unless nis. */
PyObject *py_joint_fit(PyObject *self, PyObject *args)
{
    PyObject *o[A_COUNT];
    int want_nis = 0, want_g = 0;
    dq_fuse_params p = {1e-12, 100};
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOOOOOOOO|pdip:joint_fit", &o[0], &o[1], &o[2], &o[3],
                          &o[4], &o[5], &o[6], &o[7], &o[8], &o[9], &o[10], &o[11], &o[12],
                          &o[13], &o[14], &o[15], &o[16], &o[17], &want_nis, &p.tol, &p.max_iter,
                          &want_g))
        return NULL;
    if (check_iteration(p.tol, p.max_iter) < 0) return NULL;
    PyArrayObject *a[A_COUNT] = {NULL}, *outs[O_COUNT] = {NULL};
    PyObject *result = NULL;
    double *work = NULL, *zu = NULL, *ext = NULL;
    dq_joint_part *parts = NULL;
    dq_taken *taken = NULL;
    npy_intp dims[4] = {0};
    if (joint_arrays(o, a, dims) < 0) goto done;
    const npy_intp N = dims[0], K = dims[1];
    if (!(parts = (dq_joint_part *)malloc(sizeof *parts * (size_t)(K ? K : 1)))) {
        PyErr_NoMemory();
        goto done;
    }
    const npy_int64 *counts = PyArray_DATA(a[A_COUNTS]);
    const npy_bool *tflags = PyArray_DATA(a[A_TFLAGS]), *tpriors = PyArray_DATA(a[A_TPRIORS]);
    const double *tinfo = PyArray_DATA(a[A_TINFO]);
    for (npy_intp j = 0; j < K; j++)
        parts[j] = (dq_joint_part){(size_t)counts[j], tflags[j] != 0,
                                   tpriors[j] ? tinfo + 36 * j : NULL};
    dq_joint_model jm = {(size_t)K, parts, PyArray_DATA(a[A_STAMPS]),
                         PyArray_DATA(a[A_LATENCIES]), PyArray_DATA(a[A_LSLOTS]),
                         PyArray_DATA(a[A_ESLOTS]), (size_t)dims[2], PyArray_DATA(a[A_PRIORS]),
                         PyArray_DATA(a[A_PINFO]), (size_t)dims[3], NULL,
                         PyArray_DATA(a[A_EINFO])};
    const npy_intp D = (npy_intp)dq_joint_dim(&jm);
    if (joint_outputs(outs, dims, D, want_g, want_nis) < 0) goto done;
    work = (double *)malloc(sizeof(double) * dq_joint_workspace((size_t)N, &jm, want_nis));
    zu = (double *)malloc(sizeof(double) * 8 * (size_t)(N ? N : 1));
    ext = (double *)malloc(sizeof(double) * 8 * (size_t)(dims[3] ? dims[3] : 1));
    taken = (dq_taken *)malloc(sizeof *taken * (size_t)(N ? N : 1));
    if (!work || !zu || !ext || !taken) {
        PyErr_NoMemory();
        goto done;
    }
    memcpy(PyArray_DATA(outs[O_V]), PyArray_DATA(a[A_TWISTS]), sizeof(double) * 6 * (size_t)K);
    memcpy(PyArray_DATA(outs[O_L]), PyArray_DATA(a[A_LSTARTS]), sizeof(double) * (size_t)dims[2]);
    dq_joint_state st = {PyArray_DATA(outs[O_X]), PyArray_DATA(outs[O_V]),
                         PyArray_DATA(outs[O_L]), PyArray_DATA(outs[O_E]),
                         PyArray_DATA(outs[O_H]), PyArray_DATA(outs[O_P]),
                         PyArray_DATA(outs[O_G]), 0.0, 0, 0, 0};
    dq_joint_outputs per = {PyArray_DATA(outs[O_DT]), PyArray_DATA(outs[O_R]),
                            PyArray_DATA(outs[O_COST]),
                            outs[O_JAC] ? PyArray_DATA(outs[O_JAC]) : NULL,
                            outs[O_NIS] ? PyArray_DATA(outs[O_NIS]) : NULL,
                            outs[O_TESTED] ? PyArray_DATA(outs[O_TESTED]) : NULL};
    size_t bad = 0;
    const char *bad_name = "poses";
    int code = joint_run(a, dims, &jm, zu, ext, &p, work, taken, &st, &per, &bad, &bad_name);
    if (code != DQ_OK) {
        joint_error(code, bad_name, bad, a);
        goto done;
    }
    PyObject *chi2 = PyFloat_FromDouble(st.chi2), *status = PyLong_FromLong(st.status),
             *iterations = PyLong_FromLong(st.iterations);
    PyObject *arrays = chi2 && status && iterations ? steal_tuple(outs, O_COUNT) : NULL;
    if (arrays) {
        PyObject *tail = PyTuple_Pack(3, chi2, status, iterations);
        result = tail ? PySequence_Concat(arrays, tail) : NULL;
        Py_XDECREF(tail);
        Py_DECREF(arrays);
    }
    Py_XDECREF(chi2);
    Py_XDECREF(status);
    Py_XDECREF(iterations);
done:
    free(work);
    free(zu);
    free(ext);
    free(parts);
    free(taken);
    for (int j = 0; j < A_COUNT; j++) Py_XDECREF(a[j]);
    for (int j = 0; j < O_COUNT; j++) Py_XDECREF(outs[j]);
    return result;
}
