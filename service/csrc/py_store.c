/*
 * py_store.c — _dqcore.StoreIndex, the Python type of store.h's per-body index, which
 * service/fusion/store.py's Store keeps beside its columns: rows pushed as they are appended,
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

/* live(taken, newest, window, cap, n, recent=None): which of rows 0 .. n - 1 a compaction keeps
 * (bool); newest[b] for every body b the index holds rows of. With recent: instead, each body
 * code's (oldest, near) over those rows (store.h's dq_store_spans). */
static PyObject *index_live(StoreIndex *self, PyObject *args)
{
    PyObject *to, *no, *ro = Py_None;
    double window;
    long cap;
    Py_ssize_t n;
    if (!PyArg_ParseTuple(args, "OOdln|O", &to, &no, &window, &cap, &n, &ro)) return NULL;
    PyArrayObject *taken = vector(to, NPY_FLOAT64, "taken");
    PyArrayObject *newest = taken ? vector(no, NPY_FLOAT64, "newest") : NULL;
    PyObject *out = NULL;
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
    if (ro == Py_None) {
        npy_intp dim = n;
        out = PyArray_SimpleNew(1, &dim, NPY_BOOL);
        if (out)
            dq_store_live(&x, PyArray_DATA(taken), PyArray_DATA(newest), window, cap,
                          (size_t)n, PyArray_DATA((PyArrayObject *)out), NULL);
        goto done;
    }
    double recent = PyFloat_AsDouble(ro);
    if (recent == -1.0 && PyErr_Occurred()) goto done;
    npy_intp dim = (npy_intp)x.count;
    PyObject *oldest = PyArray_SimpleNew(1, &dim, NPY_FLOAT64);
    PyObject *near = oldest ? PyArray_SimpleNew(1, &dim, NPY_INT64) : NULL;
    if (near) {
        dq_store_spans sp = {recent, PyArray_DATA((PyArrayObject *)oldest),
                             PyArray_DATA((PyArrayObject *)near)};
        dq_store_live(&x, PyArray_DATA(taken), PyArray_DATA(newest), window, cap, (size_t)n,
                      NULL, &sp);
        out = Py_BuildValue("(NN)", oldest, near);
    } else {
        Py_XDECREF(oldest);
    }
done:
    Py_XDECREF(taken);
    Py_XDECREF(newest);
    return out;
}

static PyObject *index_reset(StoreIndex *self, PyObject *unused)
{
    dq_store_reset(&self->x);
    return Py_NewRef(Py_None);
}

/* Column `name` of the store's attributes `d` (its __dict__): an ndarray of `type`,
 * C-contiguous and writeable, of shape (rows, inner...) (inner: 0, 8 or 36 doubles a row, 36 as
 * 6x6), rows the first column's (*rows 0: any, then set); a borrowed pointer to its data, NULL
 * with the ValueError. */
static void *column(PyObject *d, const char *name, int type, int inner, size_t *rows)
{
    PyObject *a = PyDict_GetItemString(d, name);        /* borrowed: the store keeps it */
    PyArrayObject *arr = (PyArrayObject *)a;
    int nd = inner == 0 ? 1 : inner == 8 ? 2 : 3;
    if (!a || !PyArray_Check(a) || PyArray_TYPE(arr) != type || PyArray_NDIM(arr) != nd
        || !PyArray_ISCARRAY(arr) || (nd == 2 && PyArray_DIM(arr, 1) != 8)
        || (nd == 3 && (PyArray_DIM(arr, 1) != 6 || PyArray_DIM(arr, 2) != 6))
        || (*rows && (size_t)PyArray_DIM(arr, 0) != *rows)) {
        PyErr_Format(PyExc_ValueError, "store.%s: expected a writeable contiguous column of "
                                       "the store's rows", name);
        return NULL;
    }
    *rows = (size_t)PyArray_DIM(arr, 0);
    return PyArray_DATA(arr);
}

/* The store's columns (n: store.n; wcovs only when it has them), read from its __dict__ (no
 * attribute look-up through its type, no AttributeError made for an absent wcovs); NULL
 * pointers with the ValueError. */
static int columns(PyObject *store, dq_store_cols *c)
{
    size_t cap = 0;
    memset(c, 0, sizeof *c);
    PyObject *d = PyObject_GenericGetDict(store, NULL);
    if (!d) return -1;
    int rc = -1;
    if (!(c->ids = column(d, "ids", NPY_INT64, 0, &cap))
        || !(c->body = column(d, "body", NPY_INT64, 0, &cap))
        || !(c->codes = column(d, "codes", NPY_INT64, 0, &cap))
        || !(c->times = column(d, "times", NPY_FLOAT64, 0, &cap))
        || !(c->taken = column(d, "taken", NPY_FLOAT64, 0, &cap))
        || !(c->poses = column(d, "poses", NPY_FLOAT64, 8, &cap))
        || !(c->covs = column(d, "covs", NPY_FLOAT64, 36, &cap))
        || !(c->wposes = column(d, "wposes", NPY_FLOAT64, 8, &cap)))
        goto done;
    if (PyDict_GetItemString(d, "wcovs")
        && !(c->wcovs = column(d, "wcovs", NPY_FLOAT64, 36, &cap)))
        goto done;
    c->capacity = cap;
    PyObject *n = PyDict_GetItemString(d, "n");
    Py_ssize_t v = n && PyLong_Check(n) ? PyLong_AsSsize_t(n) : -1;
    if (v < 0 || (size_t)v > cap) {
        if (!PyErr_Occurred()) PyErr_SetString(PyExc_ValueError, "store.n: out of range");
        goto done;
    }
    c->n = (size_t)v;
    rc = 0;
done:
    Py_DECREF(d);
    return rc;
}

static int set_n(PyObject *store, size_t n)
{
    PyObject *v = PyLong_FromSize_t(n);
    int rc = v ? PyObject_SetAttrString(store, "n", v) : -1;
    Py_XDECREF(v);
    return rc;
}

/* A writeable C-contiguous ndarray of `type` and `nd` dimensions, else NULL with the error. */
static PyArrayObject *writeable(PyObject *o, int type, int nd, const char *name)
{
    if (!PyArray_Check(o) || PyArray_TYPE((PyArrayObject *)o) != type
        || PyArray_NDIM((PyArrayObject *)o) != nd || !PyArray_ISCARRAY((PyArrayObject *)o)) {
        PyErr_Format(PyExc_ValueError, "%s: expected a writeable contiguous %d-d array", name,
                     nd);
        return NULL;
    }
    return (PyArrayObject *)o;
}

/* A C-contiguous array of `type`, (n, inner...) as column() (inner 8 or 36), a new reference. */
static PyArrayObject *rows_of_shape(PyObject *o, int type, int inner, npy_intp n,
                                    const char *name)
{
    int nd = inner == 0 ? 1 : inner == 8 ? 2 : 3;
    PyArrayObject *a = (PyArrayObject *)PyArray_FROMANY(o, type, nd, nd, NPY_ARRAY_CARRAY_RO);
    if (a && PyArray_DIM(a, 0) == n && (nd < 2 || PyArray_DIM(a, 1) == (inner == 8 ? 8 : 6))
        && (nd < 3 || PyArray_DIM(a, 2) == 6))
        return a;
    Py_XDECREF(a);
    PyErr_Format(PyExc_ValueError, "%s: expected %zd rows", name, (Py_ssize_t)n);
    return NULL;
}

/* The codes of names[k] in `codes` (a dict of str -> int) for the rows with ok[k] (0 for the
 * others) into out[]: 1, 0 when a name is not in it, -1 with the error. */
static int coded(PyObject *names, PyObject *codes, const npy_bool *ok, npy_intp n,
                 int64_t *out, const char *what)
{
    PyObject *seq = PySequence_Fast(names, what);
    if (!seq) return -1;
    int rc = 1;
    if (PySequence_Fast_GET_SIZE(seq) != n || !PyDict_Check(codes)) {
        PyErr_Format(PyExc_ValueError, "%s: expected a name a row and a dict of codes", what);
        rc = -1;
    }
    PyObject **items = PySequence_Fast_ITEMS(seq);
    for (npy_intp k = 0; k < n && rc == 1; k++) {
        out[k] = 0;
        if (!ok[k]) continue;
        PyObject *c = PyDict_GetItemWithError(codes, items[k]);
        if (!c) {
            rc = PyErr_Occurred() ? -1 : 0;
            break;
        }
        out[k] = PyLong_AsLongLong(c);
        if (out[k] == -1 && PyErr_Occurred()) rc = -1;
    }
    Py_DECREF(seq);
    return rc;
}

/* The names of bodies[k] (codes body[k] < bodies) of the rows with use[k], once each, in order:
 * a new tuple; *seen the scratch it allocates (the caller frees it). */
static PyObject *touched_bodies(PyObject *names, const int64_t *body, const npy_bool *use,
                                npy_intp n, size_t bodies, unsigned char **seen)
{
    *seen = calloc(bodies + 1, 1);
    PyObject *seq = *seen ? PySequence_Fast(names, "bodies") : NULL;
    if (!seq) return *seen ? NULL : PyErr_NoMemory();
    PyObject *list = PyList_New(0);
    for (npy_intp k = 0; list && k < n; k++) {
        if (!use[k] || (*seen)[body[k]]) continue;
        (*seen)[body[k]] = 1;
        if (PyList_Append(list, PySequence_Fast_GET_ITEM(seq, k)) < 0) Py_CLEAR(list);
    }
    Py_DECREF(seq);
    PyObject *out = list ? PyList_AsTuple(list) : NULL;
    Py_XDECREF(list);
    return out;
}

/* The ingest rules' bound, all-or-none and origin (None: anonymous); -1 with an exception. */
static int rules_of(dq_store_rules *r, Py_ssize_t max_rows, int all_or_none, PyObject *origin)
{
    r->bounded = max_rows >= 0;
    r->max_rows = r->bounded ? (size_t)max_rows : 0;
    r->all_or_none = all_or_none;
    r->anon = origin == Py_None;
    if (!r->anon) {
        r->origin = PyLong_AsLongLong(origin);
        if (r->origin == -1 && PyErr_Occurred()) return -1;
    }
    return 0;
}

/* Whether dq_store_ingest's rc is an error (then set as the Python exception). */
static int ingest_failed(int rc)
{
    if (rc == -1)
        PyErr_NoMemory();
    else if (rc == -2)
        PyErr_SetString(PyExc_ValueError, "rows: a code out of range, or the store's columns "
                                          "too short for them");
    else if (rc == -3)
        PyErr_SetString(PyExc_ValueError, "poses: a pose is not a rigid motion");
    return rc < 0;
}

/* The refusals as a list of (row, code, a, b), or NULL (an exception set). */
static PyObject *refusal_list(const dq_store_refusal *refused, size_t nout)
{
    PyObject *list = PyList_New((Py_ssize_t)nout);
    for (size_t i = 0; list && i < nout; i++) {
        PyObject *t = Py_BuildValue("(nidd)", (Py_ssize_t)refused[i].row, refused[i].code,
                                    refused[i].a, refused[i].b);
        if (!t) {
            Py_CLEAR(list);
            break;
        }
        PyList_SET_ITEM(list, (Py_ssize_t)i, t);
    }
    return list;
}

/* The rows offered (ok's, else all) and each row's id (first + k when consecutive). */
static void rows_used(PyArrayObject *ok, int consecutive, long long first, PyArrayObject *ids,
                      npy_intp n, npy_bool *use, int64_t *id)
{
    if (ok)
        memcpy(use, PyArray_DATA(ok), (size_t)n);
    else
        memset(use, 1, (size_t)n);
    for (npy_intp k = 0; k < n; k++)
        id[k] = consecutive ? (int64_t)(first + k) : ((const int64_t *)PyArray_DATA(ids))[k];
}

/* ingest(store, newest, by_source, latency, bodies, body_codes, sources, source_codes, ids,
 * times, poses, covs, ok, wposes, wcovs, window, cap, max_time, jump, max_rows, origin,
 * all_or_none) -> (refusals, fresh, touched) | None: store.h's dq_store_ingest over the store's
 * columns (store.n updated), newest and by_source (body x source) updated in place; ok (bool, or
 * None: every row) the rows offered, out: taken in; ids an int64 array or the first of
 * consecutive ids; the rows' bodies and sources are names coded by the dicts (None, nothing
 * done, when a row with ok names one they do not hold); refusals [(k, code, a, b)]; touched the
 * bodies of the rows taken in, once each, in order; max_rows < 0: unbounded (max_time, jump
 * unused); origin None: a stream's rows. */
static PyObject *index_ingest(StoreIndex *self, PyObject *args)
{
    PyObject *store, *no, *so, *lo, *bn, *bc, *sn, *sc, *io, *to, *po, *vo, *oko, *wpo, *wco,
        *origin;
    dq_store_rules r = {0};
    Py_ssize_t max_rows;
    int all_or_none;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOOOOOdlddnOp", &store, &no, &so, &lo, &bn, &bc, &sn,
                          &sc, &io, &to, &po, &vo, &oko, &wpo, &wco, &r.window, &r.cap,
                          &r.max_time, &r.jump, &max_rows, &origin, &all_or_none) ||
        rules_of(&r, max_rows, all_or_none, origin) < 0)
        return NULL;
    dq_store_cols cols;
    if (columns(store, &cols) < 0) return NULL;
    PyArrayObject *newest = writeable(no, NPY_FLOAT64, 1, "newest");
    PyArrayObject *by_source = newest ? writeable(so, NPY_FLOAT64, 2, "by_source") : NULL;
    PyArrayObject *ok = NULL;
    if (!by_source || (oko != Py_None && !(ok = writeable(oko, NPY_BOOL, 1, "ok"))))
        return NULL;
    npy_intp n = PySequence_Size(bn);
    if (n < 0) return NULL;
    if (ok && PyArray_DIM(ok, 0) != n)
        return PyErr_Format(PyExc_ValueError, "ok: expected one a row");
    long long first = 0;
    int consecutive = PyLong_Check(io);
    if (consecutive && (first = PyLong_AsLongLong(io)) == -1 && PyErr_Occurred()) return NULL;
    PyArrayObject *latency = vector(lo, NPY_FLOAT64, "latency");
    PyArrayObject *ids = latency && !consecutive ? rows_of_shape(io, NPY_INT64, 0, n, "ids")
                                                 : NULL;
    PyArrayObject *times = ids || (latency && consecutive)
                           ? rows_of_shape(to, NPY_FLOAT64, 0, n, "times") : NULL;
    PyArrayObject *poses = times ? rows_of_shape(po, NPY_FLOAT64, 8, n, "poses") : NULL;
    PyArrayObject *covs = poses ? rows_of_shape(vo, NPY_FLOAT64, 36, n, "covs") : NULL;
    PyArrayObject *wposes = NULL, *wcovs = NULL;
    PyObject *out = NULL, *list = NULL;
    double *taken = NULL;
    int64_t *body = NULL, *source = NULL, *id = NULL;
    npy_bool *use = NULL;
    unsigned char *seen = NULL;
    dq_store_refusal *refused = NULL;
    if (!covs) goto done;
    body = malloc(3 * ((size_t)n + 1) * sizeof *body);
    use = malloc((size_t)n + 1);
    if (!body || !use) {
        PyErr_NoMemory();
        goto done;
    }
    source = body + n + 1;
    id = source + n + 1;
    rows_used(ok, consecutive, first, ids, n, use, id);
    int known = coded(bn, bc, use, n, body, "bodies");
    if (known == 1) known = coded(sn, sc, use, n, source, "sources");
    if (known < 0) goto done;
    if (!known) {
        out = Py_NewRef(Py_None);
        goto done;
    }
    if ((wpo != Py_None && !(wposes = rows_of_shape(wpo, NPY_FLOAT64, 8, n, "wposes"))) ||
        (wco != Py_None && !(wcovs = rows_of_shape(wco, NPY_FLOAT64, 36, n, "wcovs"))))
        goto done;
    taken = malloc(((size_t)n + 1) * sizeof *taken);
    refused = malloc(((size_t)n + 1) * sizeof *refused);
    if (!taken || !refused) {
        PyErr_NoMemory();
        goto done;
    }
    dq_store_state st = {PyArray_DATA(newest), PyArray_DATA(by_source),
                         (size_t)PyArray_DIM(newest, 0), (size_t)PyArray_DIM(by_source, 1),
                         (size_t)PyArray_DIM(latency, 0), PyArray_DATA(latency)};
    if ((size_t)PyArray_DIM(by_source, 0) < st.bodies) {
        PyErr_SetString(PyExc_ValueError, "by_source: fewer bodies than newest");
        goto done;
    }
    dq_store_rows in = {(size_t)n, body, source, id, PyArray_DATA(times),
                        PyArray_DATA(poses), PyArray_DATA(covs),
                        wposes ? PyArray_DATA(wposes) : NULL,
                        wcovs ? PyArray_DATA(wcovs) : NULL, use, taken};
    size_t nout = 0;
    int fresh = 0, rc = dq_store_ingest(&self->x, &cols, &st, &in, &r, refused, &nout, &fresh);
    if (set_n(store, cols.n) < 0 || ingest_failed(rc)) goto done;
    if (!(list = refusal_list(refused, nout))) goto done;
    if (ok) memcpy(PyArray_DATA(ok), use, (size_t)n);
    PyObject *touched = touched_bodies(bn, body, use, n, st.bodies, &seen);
    if (touched) out = Py_BuildValue("(ONN)", list, PyBool_FromLong(fresh), touched);
done:
    Py_XDECREF(list);
    free(taken);
    free(refused);
    free(body);
    free(use);
    free(seen);
    Py_XDECREF(latency);
    Py_XDECREF(ids);
    Py_XDECREF(times);
    Py_XDECREF(poses);
    Py_XDECREF(covs);
    Py_XDECREF(wposes);
    Py_XDECREF(wcovs);
    return out;
}

/* keep(store, live): store.h's dq_store_keep over the store's columns (store.n updated). */
static PyObject *index_keep(StoreIndex *self, PyObject *args)
{
    PyObject *store, *lo;
    if (!PyArg_ParseTuple(args, "OO", &store, &lo)) return NULL;
    dq_store_cols cols;
    if (columns(store, &cols) < 0) return NULL;
    PyArrayObject *live = rows_of_shape(lo, NPY_BOOL, 0, (npy_intp)cols.n, "live");
    if (!live) return NULL;
    int rc = dq_store_keep(&self->x, &cols, PyArray_DATA(live));
    Py_DECREF(live);
    if (set_n(store, cols.n) < 0) return NULL;
    if (rc < 0) return PyErr_NoMemory();
    return Py_NewRef(Py_None);
}

static PyObject *index_version(StoreIndex *self, PyObject *arg)
{
    long long b = PyLong_AsLongLong(arg);
    if (b == -1 && PyErr_Occurred()) return NULL;
    return PyLong_FromLongLong(dq_store_version(&self->x, b));
}

static PyObject *index_forget(StoreIndex *self, PyObject *arg)
{
    long long b = PyLong_AsLongLong(arg);
    if (b == -1 && PyErr_Occurred()) return NULL;
    dq_store_forget(&self->x, b);
    return Py_NewRef(Py_None);
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
     "live(taken, newest, window, cap, n, recent=None): the rows within their body's window "
     "(the last cap of them; cap < 0: all), as bools; with recent, each body code's (oldest, "
     "near) over them instead."},
    {"reset", (PyCFunction)index_reset, METH_NOARGS, "reset(): every body's index emptied."},
    {"ingest", (PyCFunction)index_ingest, METH_VARARGS,
     "ingest(store, newest, by_source, latency, bodies, body_codes, sources, source_codes, ids, "
     "times, poses, covs, ok, wposes, wcovs, window, cap, max_time, jump, max_rows, origin, "
     "all_or_none) -> (refusals, fresh, touched) | None: a request's rows checked and taken "
     "into the store (store.h); None when a name is not coded."},
    {"keep", (PyCFunction)index_keep, METH_VARARGS,
     "keep(store, live): the store's rows with live[r] kept, in order."},
    {"version", (PyCFunction)index_version, METH_O,
     "version(b): requests that brought body b rows (0: none)."},
    {"forget", (PyCFunction)index_forget, METH_O, "forget(b): body b's jump state forgotten."},
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
