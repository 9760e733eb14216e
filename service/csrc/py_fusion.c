/*
 * py_fusion.c — the Python functions of the fusion (fusion.h: fuse, pair_distances, check_rows) and of the
 * constant-twist fit (motion.h: motion_fit, motion_determined), on arrays service/fusion/ has
 * prepared. Poses are checked unit and covariances finite here, the GIL released meanwhile.
 */
#include "py_args.h"

#include <stdlib.h>
#include <string.h>

#include "dq.h"
#include "fusion.h"
#include "linalg6.h"
#include "motion.h"
#include "py_functions.h"

/* ---- fuse ----------------------------------------------------------------------------------- */

/* fuse's poses (..., n, 8), covariances (..., n, 6, 6) and inliers (..., n) bool or None,
 * converted and their shapes checked (*M stays NULL for None): 0, or -1 with a ValueError. */
static int fuse_arrays(PyObject *zo, PyObject *so, PyObject *io, PyArrayObject **Z,
                       PyArrayObject **S, PyArrayObject **M)
{
    *Z = (PyArrayObject *)PyArray_FROM_OTF(zo, NPY_DOUBLE, NPY_ARRAY_IN_ARRAY);
    if (!*Z) return -1;
    *S = (PyArrayObject *)PyArray_FROM_OTF(so, NPY_DOUBLE, NPY_ARRAY_IN_ARRAY);
    if (!*S) return -1;
    int nd = PyArray_NDIM(*Z);
    npy_intp *zs = PyArray_DIMS(*Z), *ss = PyArray_DIMS(*S);
    char sh[160];
    if (nd < 2 || zs[nd - 1] != 8) {
        format_shape(sh, sizeof sh, nd, zs);
        PyErr_Format(PyExc_ValueError, "poses: expected shape (..., n, 8), got %s", sh);
        return -1;
    }
    int lead = nd - 2;
    if (PyArray_NDIM(*S) != nd + 1 || !PyArray_CompareLists(ss, zs, lead + 1) || ss[nd - 1] != 6 ||
        ss[nd] != 6) {
        format_shape(sh, sizeof sh, PyArray_NDIM(*S), ss);
        PyErr_Format(PyExc_ValueError,
                     "covariances: expected shape (..., n, 6, 6) matching poses, got %s", sh);
        return -1;
    }
    if (io != Py_None) {
        *M = (PyArrayObject *)PyArray_FROM_OTF(io, NPY_BOOL, NPY_ARRAY_IN_ARRAY);
        if (!*M) return -1;
        if (PyArray_NDIM(*M) != lead + 1 || !PyArray_CompareLists(PyArray_DIMS(*M), zs, lead + 1)) {
            format_shape(sh, sizeof sh, PyArray_NDIM(*M), PyArray_DIMS(*M));
            PyErr_Format(PyExc_ValueError, "inliers: expected shape (..., n) matching poses, got %s",
                         sh);
            return -1;
        }
    }
    if (zs[lead] == 0) {
        PyErr_SetString(PyExc_ValueError, "poses: no measurements");
        return -1;
    }
    return 0;
}

/* fuse's outputs with the leading shape zs[0 .. lead): mean, covariance, residuals, distances,
 * nis, tested, status, iterations, chi2 (nis and tested NULL without want_nis). 0, or -1. */
static int fuse_outputs(int lead, const npy_intp *zs, npy_intp n, int want_nis,
                        PyArrayObject **outs)
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
        if (!outs[j]) return -1;
    }
    return 0;
}

/* The first failure of a batch: its code, problem b, measurement i and argument. */
typedef struct {
    int code;
    npy_intp b;
    size_t i;
    const char *name;
} fuse_failure;

/* dq_fuse over each of the batch's problems (each checked first: poses unit, covariances
 * finite), the GIL released for a batch, into outs; stops at the first failure. */
static void fuse_batch(const double *zd, const double *sd, const unsigned char *id, npy_intp batch,
                       npy_intp n, const dq_fuse_params *p, int want_nis, double *work,
                       double *zu, PyArrayObject **outs, fuse_failure *bad)
{
    int code = DQ_OK;
    NPY_BEGIN_THREADS_DEF;
    if (batch * n >= GIL_RELEASE_MIN) NPY_BEGIN_THREADS;
    for (npy_intp b = 0; b < batch && code == DQ_OK; b++) {
        const double *zb = zd + 8 * n * b, *sb = sd + 36 * n * b;
        for (npy_intp i = 0; i < n && code == DQ_OK; i++) {
            code = dq_unit(zb + 8 * i, zu + 8 * i);
            if (code) { bad->i = (size_t)i; bad->name = "poses"; }
            else if (!dq_finite_n(sb + 36 * i, 36)) {
                code = DQ_E_NONFINITE; bad->i = (size_t)i; bad->name = "covariances";
            }
        }
        if (code) { bad->b = b; break; }
        dq_fused f;
        dq_fuse_outputs per = {
            (double *)PyArray_DATA(outs[2]) + 6 * n * b, (double *)PyArray_DATA(outs[3]) + n * b,
            want_nis ? (double *)PyArray_DATA(outs[4]) + n * b : NULL,
            want_nis ? (unsigned char *)PyArray_DATA(outs[5]) + n * b : NULL};
        code = dq_fuse(zu, sb, id ? id + n * b : NULL, (size_t)n, p, work, &f, &per, &bad->i);
        if (code) { bad->b = b; bad->name = "covariances"; break; }
        memcpy((double *)PyArray_DATA(outs[0]) + 8 * b, f.mean, sizeof f.mean);
        memcpy((double *)PyArray_DATA(outs[1]) + 36 * b, f.covariance, sizeof f.covariance);
        ((npy_int64 *)PyArray_DATA(outs[6]))[b] = f.status;
        ((npy_int64 *)PyArray_DATA(outs[7]))[b] = f.iterations;
        ((double *)PyArray_DATA(outs[8]))[b] = f.chi2;
    }
    NPY_END_THREADS;
    bad->code = code;
}

/* The ValueError of a batch's failure, indexed within the batch's leading shape. */
static void fuse_error(const fuse_failure *bad, int lead, const npy_intp *zs, npy_intp n,
                       const double *zd)
{
    char inliers[256], covariances[256], where[256];
    npy_intp shape[NPY_MAXDIMS + 1];
    for (int k = 0; k < lead; k++) shape[k] = zs[k];
    shape[lead] = n;
    format_index(inliers, sizeof inliers, "inliers", lead, shape, bad->b);
    format_index(covariances, sizeof covariances, "covariances", lead, shape, bad->b);
    format_index(where, sizeof where, bad->name, lead + 1, shape, bad->b * n + (npy_intp)bad->i);
    fit_error(bad->code, inliers, covariances, where, zd + 8 * (n * bad->b + (npy_intp)bad->i));
}

/* fuse(poses (..., n, 8), covariances (..., n, 6, 6), inliers (..., n) bool or None, tol,
 * max_iter, nis) -> (mean, covariance, residuals, distances, nis, tested, status, iterations,
 * chi2), each with the leading shape; nis and tested are None when nis is false. The leading
 * shapes of the arguments must be equal (a batch of independent problems, no broadcasting). */
PyObject *py_fuse(PyObject *self, PyObject *args)
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
    if (fuse_arrays(zo, so, io, &Z, &S, &M) < 0) goto done;
    npy_intp *zs = PyArray_DIMS(Z);
    int lead = PyArray_NDIM(Z) - 2;
    npy_intp n = zs[lead], batch = 1;
    for (int k = 0; k < lead; k++) batch *= zs[k];
    if (fuse_outputs(lead, zs, n, want_nis, outs) < 0) goto done;
    work = (double *)malloc(sizeof(double) * dq_fuse_workspace((size_t)n));
    zu = (double *)malloc(sizeof(double) * 8 * (size_t)n);
    if (!work || !zu) {
        PyErr_NoMemory();
        goto done;
    }
    const double *zd = PyArray_DATA(Z);
    fuse_failure bad = {DQ_OK, 0, 0, "poses"};
    fuse_batch(zd, PyArray_DATA(S), M ? (const unsigned char *)PyArray_DATA(M) : NULL, batch, n,
               &p, want_nis, work, zu, outs, &bad);
    if (bad.code != DQ_OK) {
        fuse_error(&bad, lead, zs, n, zd);
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

/* ---- the constant-twist fit ----------------------------------------------------------------- */

/* motion_fit's array arguments o[0..12) into a[] (twist, o[9], is a flag), their shapes checked
 * against n poses and k priors: 0, or -1 with a ValueError. */
static int motion_arrays(PyObject **o, PyArrayObject **a, int find_tested, npy_intp *n_out,
                         npy_intp *k_out)
{
    a[0] = (PyArrayObject *)PyArray_FROM_OTF(o[0], NPY_DOUBLE, NPY_ARRAY_IN_ARRAY);
    if (!a[0]) return -1;
    if (PyArray_NDIM(a[0]) != 2 || PyArray_DIMS(a[0])[1] != 8 || PyArray_DIMS(a[0])[0] == 0) {
        PyErr_SetString(PyExc_ValueError, "poses: expected shape (n, 8), n >= 1");
        return -1;
    }
    npy_intp n = PyArray_DIMS(a[0])[0];
    a[7] = (PyArrayObject *)PyArray_FROM_OTF(o[7], NPY_DOUBLE, NPY_ARRAY_IN_ARRAY);
    if (!a[7]) return -1;
    if (PyArray_NDIM(a[7]) != 1) {
        PyErr_SetString(PyExc_ValueError, "priors: expected shape (k,)");
        return -1;
    }
    npy_intp k = PyArray_DIMS(a[7])[0];
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
        if (!(a[j] = exact_array(o[j], types[j], names[j], nds[j], shapes[j]))) return -1;
    }
    *n_out = n;
    *k_out = k;
    return 0;
}

/* motion_fit's outputs: mean, twist, ell, H, chi2, status, iterations, dt, residuals, cost, G,
 * nis, tested, P (G NULL without want_g, nis and tested without nis). 0, or -1. */
static int motion_outputs(PyArrayObject **outs, npy_intp n, npy_intp k, npy_intp dim, int want_g,
                          int nis)
{
    const int types[14] = {NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE,
                           NPY_INT64, NPY_INT64, NPY_DOUBLE, NPY_DOUBLE, NPY_DOUBLE,
                           NPY_DOUBLE, NPY_DOUBLE, NPY_BOOL, NPY_DOUBLE};
    const int nds[14] = {1, 1, 1, 2, 0, 0, 0, 1, 2, 1, 3, 1, 1, 2};
    const npy_intp shapes[14][3] = {{8}, {6}, {k}, {dim, dim}, {0}, {0}, {0}, {n}, {n, 6},
                                    {n}, {n, 6, dim}, {n}, {n}, {dim, dim}};
    for (int j = 0; j < 14; j++) {
        if ((j == 10 && !want_g) || ((j == 11 || j == 12) && !nis)) continue;
        if (!(outs[j] = (PyArrayObject *)PyArray_SimpleNew(nds[j], shapes[j], types[j])))
            return -1;
    }
    return 0;
}

/* What one motion_fit call computes with, besides the model. */
typedef struct {
    PyArrayObject **a, **outs;
    npy_intp n;
    int pick_start, find_tested;
    const dq_fuse_params *p;
    double *work, *zu;
    dq_taken *taken;
} motion_call;

/* The fit (motion.h's dq_motion_run) with the GIL released, on the call's arrays. Returns a
 * DQ_E* code with *bad and *bad_name the measurement and argument it concerns. */
static int motion_run(const motion_call *c, const dq_motion_model *m, dq_motion_fitted *f,
                      size_t *bad, const char **bad_name)
{
    PyArrayObject **a = c->a, **outs = c->outs;
    f->ell = PyArray_DATA(outs[2]);
    f->H = PyArray_DATA(outs[3]);
    dq_motion_outputs per = {PyArray_DATA(outs[7]), PyArray_DATA(outs[8]), PyArray_DATA(outs[9]),
                             outs[10] ? PyArray_DATA(outs[10]) : NULL,
                             outs[11] ? PyArray_DATA(outs[11]) : NULL};
    dq_motion_run_args r = {PyArray_DATA(a[0]), PyArray_DATA(a[1]),
                            a[2] ? PyArray_DATA(a[2]) : NULL,
                            c->pick_start ? NULL : PyArray_DATA(a[3]), (size_t)c->n,
                            c->find_tested || !a[11] ? NULL : PyArray_DATA(a[11]),
                            c->find_tested, outs[12] ? PyArray_DATA(outs[12]) : NULL, c->p,
                            c->work, c->zu, PyArray_DATA(outs[13]), c->taken};
    int code;
    NPY_BEGIN_THREADS_DEF;
    NPY_BEGIN_THREADS;
    code = dq_motion_run(&r, m, f, &per, bad, bad_name);
    NPY_END_THREADS;
    return code;
}

/* The ValueError of motion_run's failure. */
static void motion_error(int code, const char *bad_name, size_t bad, PyArrayObject **a)
{
    char where[64];
    const double *pose = (const double *)PyArray_DATA(a[0]) + 8 * bad;
    if (strcmp(bad_name, "start") == 0) {
        snprintf(where, sizeof where, "start");
        pose = PyArray_DATA(a[3]);
    } else {
        snprintf(where, sizeof where, "%s[%zu]", bad_name, bad);
    }
    fit_error(code, "inliers", "covariances", where, pose);
}

/* motion_fit(poses (n, 8), covariances (n, 6, 6), inliers (n,) bool or None, start (8,) or
 * None, stamps (n,), latencies (n,), slots (n,) int, priors (k,), prior_information (k,),
 * twist, twist_information (6, 6) or None, tested (n,) bool, True or None, tol, max_iter,
 * jacobians) -> (mean, twist, ell, H, chi2, status, iterations, dt, residuals, cost, G, nis,
 * tested, P): the constant-twist fit of motion.h's dq_motion_fit, one problem a call. start
 * None: dq_motion_nearest's inlier (a twist is estimated). tested True: every measurement but
 * an inlier whose leaving out would leave the state undetermined (dq_motion_determined). G is
 * None unless jacobians, nis and tested None without tested; P = H^-1 (dq_spd_inverse). */
PyObject *py_motion_fit(PyObject *self, PyObject *args)
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
    npy_intp n = 0, k = 0;
    if (motion_arrays(o, a, find_tested, &n, &k) < 0) goto done;
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
    if (motion_outputs(outs, n, k, dim, want_g, a[11] || find_tested) < 0) goto done;
    work = (double *)malloc(sizeof(double) * dq_motion_workspace((size_t)n, &m));
    zu = (double *)malloc(sizeof(double) * 8 * (size_t)n);
    if (find_tested) taken = (dq_taken *)malloc(sizeof *taken * (size_t)n);
    if (!work || !zu || (find_tested && !taken)) {
        PyErr_NoMemory();
        goto done;
    }
    size_t bad = 0;
    const char *bad_name = "poses";
    dq_motion_fitted f;
    motion_call c = {a, outs, n, pick_start, find_tested, &p, work, zu, taken};
    int code = motion_run(&c, &m, &f, &bad, &bad_name);
    if (code != DQ_OK) {
        motion_error(code, bad_name, bad, a);
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
 * motion.h's dq_motion_determined; two_instants: a twist without a prior is estimated. */
PyObject *py_motion_determined(PyObject *self, PyObject *args)
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

/* poses (n, 8) and covariances (n, 6, 6) as float64 arrays into a[0], a[1] (new references,
 * NULL on an error, which is set); n their count. */
static int poses_and_covariances(PyObject *poses, PyObject *covariances, PyArrayObject **a,
                                 npy_intp *n)
{
    if (!(a[0] = (PyArrayObject *)PyArray_FROM_OTF(poses, NPY_DOUBLE, NPY_ARRAY_IN_ARRAY)))
        return 0;
    if (PyArray_NDIM(a[0]) != 2 || PyArray_DIMS(a[0])[1] != 8) {
        PyErr_SetString(PyExc_ValueError, "poses: expected shape (n, 8)");
        return 0;
    }
    *n = PyArray_DIMS(a[0])[0];
    npy_intp s3[3] = {*n, 6, 6};
    return (a[1] = exact_array(covariances, NPY_DOUBLE, "covariances", 3, s3)) != NULL;
}

/* pair_distances(poses (n, 8), covariances (n, 6, 6), candidates (m,) int) -> (m, n): fusion.h's
 * dq_pair_distances, the GIL released. */
PyObject *py_pair_distances(PyObject *self, PyObject *args)
{
    PyObject *o[3];
    if (!PyArg_ParseTuple(args, "OOO:pair_distances", &o[0], &o[1], &o[2])) return NULL;
    PyArrayObject *a[3] = {NULL}, *out = NULL;
    PyObject *result = NULL;
    npy_intp n = 0;
    if (!poses_and_covariances(o[0], o[1], a, &n) ||
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

/* check_rows(poses (n, 8), covariances (n, 6, 6), sym_tol) -> (ok (n,) bool, symmetrised
 * (n, 6, 6)): a stream's rows checked by the Tracker's rules in one pass, the GIL released.
 * ok[i]: pose i is a unit rigid motion (dq_unit, the rule of dq.to_matrix) and covariance i
 * passes fusion.h's dq_covariance_check (finite, symmetric within sym_tol, variances within
 * bounds, positive definite beyond doubt), symmetrised[i] then 0.5 (S + S^T) (NumPy's bits).
 * A row not ok (a problem, or a covariance too near the edge to be sure) is for the caller's
 * own check to name; its symmetrised entry is a copy of the covariance given. */
PyObject *py_check_rows(PyObject *self, PyObject *args)
{
    PyObject *o[2];
    double sym_tol;
    if (!PyArg_ParseTuple(args, "OOd:check_rows", &o[0], &o[1], &sym_tol)) return NULL;
    PyArrayObject *a[2] = {NULL}, *ok = NULL, *sym = NULL;
    PyObject *result = NULL;
    npy_intp n = 0;
    if (!poses_and_covariances(o[0], o[1], a, &n)) goto done;
    npy_intp s3[3] = {n, 6, 6};
    if (!(ok = (PyArrayObject *)PyArray_SimpleNew(1, &n, NPY_BOOL)) ||
        !(sym = (PyArrayObject *)PyArray_SimpleNew(3, s3, NPY_DOUBLE)))
        goto done;
    const double *z = PyArray_DATA(a[0]), *S = PyArray_DATA(a[1]);
    double *out = PyArray_DATA(sym);
    unsigned char *good = PyArray_DATA(ok);
    Py_BEGIN_ALLOW_THREADS
    for (npy_intp i = 0; i < n; i++) {
        double unit[8];
        good[i] = dq_unit(z + 8 * i, unit) == DQ_OK &&
                  dq_covariance_check(S + 36 * i, sym_tol, out + 36 * i) == DQ_OK;
        if (!good[i]) memcpy(out + 36 * i, S + 36 * i, 36 * sizeof(double));
    }
    Py_END_ALLOW_THREADS
    result = PyTuple_Pack(2, (PyObject *)ok, (PyObject *)sym);
done:
    for (int j = 0; j < 2; j++) Py_XDECREF(a[j]);
    Py_XDECREF(ok);
    Py_XDECREF(sym);
    return result;
}
