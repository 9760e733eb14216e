/*
 * py_trajectory.c — the Python functions of the trajectory planner and its dense evaluation
 * (trajectory.h), on waypoints service/trajectory.py has checked.
 */
#include "py_args.h"

#include "trajectory.h"
#include "py_functions.h"

/* traj_plan(waypoints (K, 8), mode, radius (K,), times (K,), limits (6,), sigma0)
 * -> (code, bad, plan, duration, segments (K-1, 3) [start, duration, binding]): dq_traj_plan on
 * waypoints service/trajectory.py has checked. plan is the opaque segment table traj_eval reads;
 * code != 0 leaves the message (and the index bad) to the caller. */
PyObject *py_traj_plan(PyObject *self, PyObject *args)
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
        row[1] = dq_traj_seg_duration(&seg[k]);
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
PyObject *py_traj_eval(PyObject *self, PyObject *args)
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
