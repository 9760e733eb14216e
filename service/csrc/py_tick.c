/*
 * py_tick.c — _dqcore.FitOptions (tick.h's dq_tick_options, made once per configuration and
 * source table) and _dqcore.tick (one tick's FusedPose bytes from the store's columns, the GIL
 * released), for service/world.py's World.tick_bytes.
 */
#include "py_args.h"

#include <math.h>
#include <string.h>

#include "py_functions.h"
#include "tick.h"

/* A tick of at most this many rows keeps the GIL (tens of us): released, the thread that took
 * it meanwhile (a server's event loop) holds it until its switch interval (5 ms) or its next
 * wait, and the step's lock is held all that time. */
#define TICK_RELEASE_ROWS 64

typedef struct {
    PyObject_HEAD
    dq_tick_options o;
    double *numbers;    /* latency, sigma, prior_w (m each), E (8 m), E_info (36 m) */
    unsigned char *flags; /* estimated, exact (m each) */
    dq_str *names;
    PyObject *name_refs; /* the tuple of str the names point into */
    double twist_w[36], twist_cov[36];
} FitOptions;

static void options_dealloc(FitOptions *self)
{
    PyMem_Free(self->numbers);
    PyMem_Free(self->flags);
    PyMem_Free(self->names);
    Py_XDECREF(self->name_refs);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* a 1-d float64 array of m values copied into dst, or -1 with a ValueError */
static int copy_vector(PyObject *o, npy_intp m, int type, void *dst, size_t size,
                       const char *name)
{
    PyArrayObject *a = (PyArrayObject *)PyArray_FROMANY(o, type, 1, 1, NPY_ARRAY_CARRAY_RO);
    if (!a || PyArray_DIM(a, 0) != m) {
        Py_XDECREF(a);
        PyErr_Format(PyExc_ValueError, "%s: expected %ld values", name, (long)m);
        return -1;
    }
    memcpy(dst, PyArray_DATA(a), size * (size_t)m);
    Py_DECREF(a);
    return 0;
}

/* FitOptions(latency, sigma, prior_w, estimated, exact, names, E, E_info, max_skew,
 * max_extrapolation, twist_w, twist_cov, probability, tol, max_iter): per source code its
 * configured latency, its latency prior's sigma (NaN: exact) and information, whether estimated,
 * whether its extrinsic is exact, its name, its extrinsic and that one's information (read where
 * not exact); the options (None: unbounded, no twist prior: both or neither). */
static int options_init(FitOptions *self, PyObject *args, PyObject *kw)
{
    PyObject *lat, *sig, *pw, *est, *exact, *names, *eo, *eio, *skew, *extra, *tw, *tc;
    double probability, tol;
    int max_iter;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOOddi:FitOptions", &lat, &sig, &pw, &est, &exact,
                          &names, &eo, &eio, &skew, &extra, &tw, &tc, &probability, &tol,
                          &max_iter))
        return -1;
    PyObject *tuple = PySequence_Tuple(names);
    if (!tuple) return -1;
    npy_intp m = PyTuple_GET_SIZE(tuple);
    Py_XSETREF(self->name_refs, tuple);
    PyMem_Free(self->numbers);
    PyMem_Free(self->flags);
    PyMem_Free(self->names);
    self->numbers = PyMem_Calloc(47 * (size_t)m + 1, sizeof(double));
    self->flags = PyMem_Calloc(2 * (size_t)m + 1, 1);
    self->names = PyMem_Calloc((size_t)m + 1, sizeof(dq_str));
    if (!self->numbers || !self->flags || !self->names) {
        PyErr_NoMemory();
        return -1;
    }
    dq_tick_options *o = &self->o;
    memset(o, 0, sizeof *o);
    o->m = (size_t)m;
    double *x = self->numbers;
    if (copy_vector(lat, m, NPY_DOUBLE, x, sizeof(double), "latency") ||
        copy_vector(sig, m, NPY_DOUBLE, x + m, sizeof(double), "sigma") ||
        copy_vector(pw, m, NPY_DOUBLE, x + 2 * m, sizeof(double), "prior_w") ||
        copy_vector(est, m, NPY_BOOL, self->flags, 1, "estimated") ||
        copy_vector(exact, m, NPY_BOOL, self->flags + m, 1, "exact") ||
        copy_vector(eo, 8 * m, NPY_DOUBLE, x + 3 * m, sizeof(double), "E") ||
        copy_vector(eio, 36 * m, NPY_DOUBLE, x + 11 * m, sizeof(double), "E_info"))
        return -1;
    o->E = x + 3 * m;
    o->E_info = x + 11 * m;
    o->latency = x;
    o->sigma = x + m;
    o->prior_w = x + 2 * m;
    o->estimated = self->flags;
    o->exact = self->flags + m;
    for (npy_intp c = 0; c < m; c++) {
        Py_ssize_t len;
        const char *s = PyUnicode_AsUTF8AndSize(PyTuple_GET_ITEM(tuple, c), &len);
        if (!s) return -1;
        self->names[c].s = s;
        self->names[c].n = (size_t)len;
    }
    o->names = self->names;
    if ((o->has_skew = skew != Py_None) && (o->max_skew = PyFloat_AsDouble(skew)) == -1.0 &&
        PyErr_Occurred())
        return -1;
    if ((o->has_extrapolation = extra != Py_None) &&
        (o->max_extrapolation = PyFloat_AsDouble(extra)) == -1.0 && PyErr_Occurred())
        return -1;
    if (tw != Py_None) {
        if (copy_vector(tw, 36, NPY_DOUBLE, self->twist_w, sizeof(double), "twist_w") < 0 ||
            copy_vector(tc, 36, NPY_DOUBLE, self->twist_cov, sizeof(double), "twist_cov") < 0)
            return -1;
        o->twist_w = self->twist_w;
        o->twist_cov = self->twist_cov;
    }
    o->probability = probability;
    o->p.tol = tol;
    o->p.max_iter = max_iter;
    return 0;
}

static PyObject *options_sources(FitOptions *self, void *closure)
{
    return PyLong_FromSize_t(self->o.m);
}

static PyGetSetDef options_getset[] = {
    {"sources", (getter)options_sources, NULL, "source codes the options know", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

PyTypeObject dq_fit_options_type = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "dqpose._dqcore.FitOptions",
    .tp_basicsize = sizeof(FitOptions),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "A tick's fit options and source table (tick.h's dq_tick_options).",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)options_init,
    .tp_dealloc = (destructor)options_dealloc,
    .tp_getset = options_getset,
};

/* a column as a C-contiguous array of type and at least rows x width values (width 0: 1-d) */
static PyArrayObject *column(PyObject *o, int type, npy_intp rows, npy_intp width,
                             const char *name)
{
    PyArrayObject *a = (PyArrayObject *)PyArray_FROMANY(o, type, 1, 3, NPY_ARRAY_CARRAY_RO);
    if (!a) return NULL;
    if (PyArray_DIM(a, 0) < rows || (PyArray_SIZE(a) != PyArray_DIM(a, 0) * (width ? width : 1))) {
        Py_DECREF(a);
        PyErr_Format(PyExc_ValueError, "%s: expected %ld rows of %ld values", name, (long)rows,
                     (long)(width ? width : 1));
        return NULL;
    }
    return a;
}

/* an array of n float64 values in all (any shape), or NULL with the ValueError */
static PyArrayObject *values(PyObject *o, npy_intp n, const char *name)
{
    PyArrayObject *a = (PyArrayObject *)PyArray_FROMANY(o, NPY_DOUBLE, 1, 2, NPY_ARRAY_CARRAY_RO);
    if (a && PyArray_SIZE(a) == n) return a;
    Py_XDECREF(a);
    PyErr_Format(PyExc_ValueError, "%s: expected %ld values", name, (long)n);
    return NULL;
}

/* tick(options, poses, covs, times, codes, ids, rows, time, body, request, bounds[, pose, cov])
 * -> bytes or None: the FusedPose bytes of the fit of the store's rows `rows` (poses (N, 8) and
 * covs (N, 6, 6) in the world frame, times, codes, ids: the store's columns) at `time` (NaN:
 * their newest taken) of `body` as request `request`'s answer, with `pose` (8,) and `cov`
 * (6, 6) instead of the fit's when given; None: the Python path makes it.
 * bounds (2, c): the verdict's chi2 interval (low, high) by count, c > len(rows). */
PyObject *py_tick(PyObject *self, PyObject *args)
{
    PyObject *opts, *o[6], *obody, *obounds, *opose = Py_None, *ocov = Py_None;
    dq_tick_input in;
    memset(&in, 0, sizeof in);
    unsigned int request;
    if (!PyArg_ParseTuple(args, "O!OOOOOOdOIO|OO:tick", &dq_fit_options_type, &opts, &o[0],
                          &o[1], &o[2], &o[3], &o[4], &o[5], &in.time, &obody, &request, &obounds,
                          &opose, &ocov))
        return NULL;
    Py_ssize_t blen;
    in.body.s = PyUnicode_AsUTF8AndSize(obody, &blen);
    if (!in.body.s) return NULL;
    in.body.n = (size_t)blen;
    in.request = request;
    PyArrayObject *a[9] = {NULL};
    PyObject *result = NULL;
    if (!(a[5] = column(o[5], NPY_INT64, 0, 0, "rows"))) goto done;
    npy_intp n = PyArray_DIM(a[5], 0), N = 0;
    if (!(a[0] = column(o[0], NPY_DOUBLE, 0, 8, "poses"))) goto done;
    N = PyArray_DIM(a[0], 0);
    if (!(a[1] = column(o[1], NPY_DOUBLE, N, 36, "covs")) ||
        !(a[2] = column(o[2], NPY_DOUBLE, N, 0, "times")) ||
        !(a[3] = column(o[3], NPY_INT64, N, 0, "codes")) ||
        !(a[4] = column(o[4], NPY_INT64, N, 0, "ids")) ||
        !(a[6] = (PyArrayObject *)PyArray_FROMANY(obounds, NPY_DOUBLE, 2, 2,
                                                   NPY_ARRAY_CARRAY_RO)))
        goto done;
    if (PyArray_DIM(a[6], 0) != 2) {
        PyErr_SetString(PyExc_ValueError, "bounds: expected shape (2, c)");
        goto done;
    }
    if (opose != Py_None && (!(a[7] = values(opose, 8, "pose")) ||
                             !(a[8] = values(ocov, 36, "cov"))))
        goto done;
    in.pose = a[7] ? PyArray_DATA(a[7]) : NULL;
    in.cov = a[8] ? PyArray_DATA(a[8]) : NULL;
    const int64_t *rows = PyArray_DATA(a[5]);
    for (npy_intp i = 0; i < n; i++)
        if (rows[i] < 0 || rows[i] >= N) {
            PyErr_Format(PyExc_ValueError, "rows[%ld]: %lld is not a row", (long)i,
                         (long long)rows[i]);
            goto done;
        }
    in.poses = PyArray_DATA(a[0]);
    in.covs = PyArray_DATA(a[1]);
    in.times = PyArray_DATA(a[2]);
    in.codes = PyArray_DATA(a[3]);
    in.ids = PyArray_DATA(a[4]);
    in.rows = rows;
    in.n = (size_t)n;
    dq_tick_options opt = ((FitOptions *)opts)->o;
    const double *b = PyArray_DATA(a[6]);
    opt.n_bounds = (size_t)PyArray_DIM(a[6], 1);
    opt.low = b;
    opt.high = b + opt.n_bounds;
    uint8_t *bytes = NULL;
    size_t len = 0;
    int code;
    if (n > TICK_RELEASE_ROWS) {
        Py_BEGIN_ALLOW_THREADS
        code = dq_tick(&opt, &in, &bytes, &len);
        Py_END_ALLOW_THREADS
    } else {
        code = dq_tick(&opt, &in, &bytes, &len);
    }
    if (code < 0) {
        PyErr_NoMemory();
    } else if (code == DQ_TICK_PYTHON) {
        result = Py_NewRef(Py_None);
    } else {
        result = PyBytes_FromStringAndSize((const char *)bytes, (Py_ssize_t)len);
        free(bytes);
    }
done:
    for (int k = 0; k < 9; k++) Py_XDECREF(a[k]);
    return result;
}
