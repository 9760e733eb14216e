/*
 * py_store.c — _dqcore.StoreIndex, the Python type of store.h's per-body index, which
 * service/fusion/store.py's _Store keeps beside its columns: rows pushed as they are appended,
 * a body's rows taken since a time, the rows a compaction keeps.
 */
#include "py_args.h"

#include <string.h>

#include "py_functions.h"
#include "store.h"

typedef struct {
    PyObject_HEAD
    dq_store_index x;
} StoreIndex;

static void index_dealloc(StoreIndex *self)
{
    dq_store_free(&self->x);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject *index_new(PyTypeObject *type, PyObject *args, PyObject *kw)
{
    StoreIndex *self = (StoreIndex *)type->tp_alloc(type, 0);
    if (self) memset(&self->x, 0, sizeof self->x);
    return (PyObject *)self;
}

/* A 1-d contiguous array of `type` (a new reference), or NULL with the ValueError. */
static PyArrayObject *vector(PyObject *o, int type, const char *name)
{
    PyArrayObject *a = (PyArrayObject *)PyArray_FROMANY(o, type, 1, 1, NPY_ARRAY_CARRAY_RO);
    if (!a) {
        PyErr_Format(PyExc_ValueError, "%s: expected a 1-d array", name);
        return NULL;
    }
    return a;
}

/* push(first, body, taken): rows first, first + 1, ... of bodies body[k] (int64), taken at
 * taken[k], appended to their bodies' indices. */
static PyObject *index_push(StoreIndex *self, PyObject *args)
{
    Py_ssize_t first;
    PyObject *bo, *to;
    if (!PyArg_ParseTuple(args, "nOO", &first, &bo, &to)) return NULL;
    PyArrayObject *body = vector(bo, NPY_INT64, "body");
    PyArrayObject *taken = body ? vector(to, NPY_FLOAT64, "taken") : NULL;
    PyObject *out = NULL;
    if (!taken) goto done;
    npy_intp m = PyArray_DIM(body, 0);
    if (PyArray_DIM(taken, 0) != m) {
        PyErr_SetString(PyExc_ValueError, "taken: expected one time a row");
        goto done;
    }
    const int64_t *b = PyArray_DATA(body);
    const double *t = PyArray_DATA(taken);
    for (npy_intp k = 0; k < m; k++) {
        if (b[k] < 0) {
            PyErr_SetString(PyExc_ValueError, "body: codes are >= 0");
            goto done;
        }
        if (dq_store_push(&self->x, b[k], (int64_t)first + k, t[k]) < 0) {
            PyErr_NoMemory();
            goto done;
        }
    }
    out = Py_NewRef(Py_None);
done:
    Py_XDECREF(body);
    Py_XDECREF(taken);
    return out;
}

/* Body b's rows from the first whose running maximum reaches lo, those taken at lo or later
 * when `taken` is given, the last `cap` of them when cap >= 0: a new intp array. */
static PyObject *rows_of(StoreIndex *self, long long b, double lo, PyObject *to, long cap)
{
    const int64_t *rows;
    size_t n = dq_store_after(&self->x, b, lo, &rows);
    PyArrayObject *taken = NULL;
    if (to != Py_None && !(taken = vector(to, NPY_FLOAT64, "taken"))) return NULL;
    const double *t = taken ? PyArray_DATA(taken) : NULL;
    npy_intp len = taken ? PyArray_DIM(taken, 0) : 0, m = 0, skip = 0;
    for (size_t i = 0; i < n; i++)
        m += !t || (rows[i] < len && t[rows[i]] >= lo);
    if (cap >= 0 && m > cap) {
        skip = m - cap;         /* the first ones of the rows taken */
        m = cap;
    }
    PyArrayObject *out = (PyArrayObject *)PyArray_SimpleNew(1, &m, NPY_INTP);
    if (out) {
        npy_intp *o = PyArray_DATA(out), j = 0;
        for (size_t i = 0; i < n && j < m; i++) {
            if (t && !(rows[i] < len && t[rows[i]] >= lo)) continue;
            if (skip) {
                skip--;
                continue;
            }
            o[j++] = (npy_intp)rows[i];
        }
    }
    Py_XDECREF(taken);
    return (PyObject *)out;
}

/* after(b, lo): body b's rows from the first whose running maximum of taken reaches lo. */
static PyObject *index_after(StoreIndex *self, PyObject *args)
{
    long long b;
    double lo;
    if (!PyArg_ParseTuple(args, "Ld", &b, &lo)) return NULL;
    return rows_of(self, b, lo, Py_None, -1);
}

/* since(b, lo, taken, cap=-1): those of them taken at lo or later (the last cap). */
static PyObject *index_since(StoreIndex *self, PyObject *args)
{
    long long b;
    double lo;
    PyObject *taken;
    long cap = -1;
    if (!PyArg_ParseTuple(args, "LdO|l", &b, &lo, &taken, &cap)) return NULL;
    return rows_of(self, b, lo, taken, cap);
}

static PyObject *index_count(StoreIndex *self, PyObject *arg)
{
    long long b = PyLong_AsLongLong(arg);
    if (b == -1 && PyErr_Occurred()) return NULL;
    return PyLong_FromSize_t(dq_store_count(&self->x, b));
}

/* live(taken, newest, window, cap, n): which of rows 0 .. n - 1 a compaction keeps (bool);
 * newest[b] for every body b the index holds rows of. */
static PyObject *index_live(StoreIndex *self, PyObject *args)
{
    PyObject *to, *no;
    double window;
    long cap;
    Py_ssize_t n;
    if (!PyArg_ParseTuple(args, "OOdln", &to, &no, &window, &cap, &n)) return NULL;
    PyArrayObject *taken = vector(to, NPY_FLOAT64, "taken");
    PyArrayObject *newest = taken ? vector(no, NPY_FLOAT64, "newest") : NULL;
    PyArrayObject *out = NULL;
    if (!newest) goto done;
    dq_store_index x = self->x;
    if ((size_t)PyArray_DIM(newest, 0) < x.count) x.count = (size_t)PyArray_DIM(newest, 0);
    for (size_t k = x.count; k < self->x.count; k++) {
        if (self->x.bodies[k].used) {
            PyErr_SetString(PyExc_ValueError, "newest: a body of the index has none");
            goto done;
        }
    }
    if (n < 0 || PyArray_DIM(taken, 0) < n) {
        PyErr_SetString(PyExc_ValueError, "taken: fewer rows than n");
        goto done;
    }
    npy_intp dim = n;
    out = (PyArrayObject *)PyArray_SimpleNew(1, &dim, NPY_BOOL);
    if (out)
        dq_store_live(&x, PyArray_DATA(taken), PyArray_DATA(newest), window, cap, (size_t)n,
                      PyArray_DATA(out));
done:
    Py_XDECREF(taken);
    Py_XDECREF(newest);
    return (PyObject *)out;
}

static PyObject *index_reset(StoreIndex *self, PyObject *unused)
{
    dq_store_reset(&self->x);
    return Py_NewRef(Py_None);
}

/* plain(newest, body, times, taken, window, max_time, jump) -> bool: store.h's dq_store_plain;
 * newest (float64, C-contiguous, writeable) updated in place (spent when False). */
PyObject *py_store_plain(PyObject *self, PyObject *args)
{
    PyObject *no, *bo, *mo, *to;
    double window, max_time, jump;
    if (!PyArg_ParseTuple(args, "OOOOddd", &no, &bo, &mo, &to, &window, &max_time, &jump))
        return NULL;
    if (!PyArray_Check(no) || PyArray_TYPE((PyArrayObject *)no) != NPY_FLOAT64 ||
        PyArray_NDIM((PyArrayObject *)no) != 1 ||
        !PyArray_ISCARRAY((PyArrayObject *)no)) {
        PyErr_SetString(PyExc_ValueError, "newest: expected a writeable contiguous float64 "
                                          "vector");
        return NULL;
    }
    PyArrayObject *newest = (PyArrayObject *)no;
    PyArrayObject *body = vector(bo, NPY_INT64, "body");
    PyArrayObject *times = body ? vector(mo, NPY_FLOAT64, "times") : NULL;
    PyArrayObject *taken = times ? vector(to, NPY_FLOAT64, "taken") : NULL;
    PyObject *out = NULL;
    if (!taken) goto done;
    npy_intp n = PyArray_DIM(body, 0);
    if (PyArray_DIM(times, 0) != n || PyArray_DIM(taken, 0) != n) {
        PyErr_SetString(PyExc_ValueError, "times, taken: expected one a row");
        goto done;
    }
    int plain = dq_store_plain(PyArray_DATA(newest), (size_t)PyArray_DIM(newest, 0),
                               PyArray_DATA(body), PyArray_DATA(times), PyArray_DATA(taken),
                               (size_t)n, window, max_time, jump);
    if (plain < 0)
        PyErr_NoMemory();
    else
        out = PyBool_FromLong(plain);
done:
    Py_XDECREF(body);
    Py_XDECREF(times);
    Py_XDECREF(taken);
    return out;
}

static PyMethodDef index_methods[] = {
    {"push", (PyCFunction)index_push, METH_VARARGS,
     "push(first, body, taken): rows first, first + 1, ... of bodies body[k] appended."},
    {"after", (PyCFunction)index_after, METH_VARARGS,
     "after(b, lo): body b's rows from the first whose running maximum of taken reaches lo."},
    {"since", (PyCFunction)index_since, METH_VARARGS,
     "since(b, lo, taken, cap=-1): body b's rows taken at lo or later (the last cap)."},
    {"count", (PyCFunction)index_count, METH_O, "count(b): body b's rows in the index."},
    {"live", (PyCFunction)index_live, METH_VARARGS,
     "live(taken, newest, window, cap, n): the rows within their body's window (the last cap "
     "of them; cap < 0: all), as bools."},
    {"reset", (PyCFunction)index_reset, METH_NOARGS, "reset(): every body's index emptied."},
    {NULL, NULL, 0, NULL},
};

PyTypeObject dq_store_index_type = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "dqpose._dqcore.StoreIndex",
    .tp_basicsize = sizeof(StoreIndex),
    .tp_dealloc = (destructor)index_dealloc,
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Each body's rows in arrival order with the running maximum of their taken times "
              "(store.h).",
    .tp_methods = index_methods,
    .tp_new = index_new,
};
