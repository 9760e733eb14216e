/*
 * py_wire.c — the Python functions of the wire codecs (wire.h): request bytes to arrays, the
 * served Blend and BlendBatch from bytes to bytes, StreamFuse's requests decoded and checked, and
 * the client's measurements encoded. Each returns None outside the decoder's plain case, and the
 * caller (service/rpc) then takes its protobuf path, which names the problem.
 */
#include "py_args.h"

#include <string.h>

#include "dq.h"
#include "fused_wire.h"
#include "pbwrite.h"
#include "wire.h"
#include "py_functions.h"

/* blend_request_from_wire(bytes) -> (poses (n, 7) [qw qx qy qz x y z], weights (m,), method,
 * tolerance, max_iterations), or None when the bytes are not a BlendRequest this decoder
 * understands (the caller then uses the protobuf parser, which says what is wrong). */
PyObject *py_blend_request_from_wire(PyObject *self, PyObject *arg)
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
PyObject *py_blend_wire(PyObject *self, PyObject *args)
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
PyObject *py_blend_batch_wire(PyObject *self, PyObject *args)
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

/* fuse_stream_from_wire(bytes, sym_tol, publish=0) -> (poses (n, 8), covariances (n, 6, 6),
 * times (n,), codes (n,) uint8, bodies, sources (tuples of str), spans (n, 2): each
 * measurement's offset and length in the bytes), or None outside the plain case (see
 * dq_wire_fuse_stream); publish: the bytes are a PublishRequest's. */
PyObject *py_fuse_stream_from_wire(PyObject *self, PyObject *args)
{
    Py_buffer view;
    double sym_tol;
    int publish = 0;
    if (!PyArg_ParseTuple(args, "y*d|p:fuse_stream_from_wire", &view, &sym_tol, &publish))
        return NULL;
    const uint8_t *buf = (const uint8_t *)view.buf;
    PyObject *result = NULL, *bodies = NULL, *sources = NULL;
    PyArrayObject *poses = NULL, *covs = NULL, *times = NULL, *codes = NULL, *spans = NULL;
    uint32_t *sp = NULL;
    dq_fuse_stream r;
    memset(&r, 0, sizeof r);
    r.publish = publish;
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

/* publish_head(bytes) -> (producer, sequence, count) of a World PublishRequest read as protobuf
 * reads them (the last producer and sequence given, the measurements counted, none decoded),
 * or None outside the plain case (a field the decoder does not take, bytes it does not read, a
 * producer that is not ASCII): then protobuf reads it. */
PyObject *py_publish_head(PyObject *self, PyObject *arg)
{
    Py_buffer view;
    if (PyObject_GetBuffer(arg, &view, PyBUF_SIMPLE) < 0) return NULL;
    const uint8_t *buf = (const uint8_t *)view.buf;
    dq_fuse_stream r;
    memset(&r, 0, sizeof r);
    r.publish = 1;
    PyObject *out = NULL;
    int plain = !dq_wire_fuse_count(buf, (size_t)view.len, &r);
    for (size_t i = 0; plain && i < r.producer_len; i++)
        plain = buf[r.producer + i] < 0x80;
    if (!plain) {
        out = Py_NewRef(Py_None);
    } else {
        PyObject *producer = PyUnicode_DecodeASCII((const char *)buf + r.producer,
                                                   (Py_ssize_t)r.producer_len, NULL);
        if (producer)
            out = Py_BuildValue("(NKn)", producer, (unsigned long long)r.sequence,
                                (Py_ssize_t)r.n);
    }
    PyBuffer_Release(&view);
    return out;
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
 * times (n,) or None, sources or None, bodies or None, field=3) -> bytes: the measurements as
 * repeated FuseStreamRequest.measurements (dq_wire_measurement), or as the repeated field
 * ``field`` of another message (1: PublishRequest's). The caller has checked the shapes; a name
 * that is not a str is a ValueError naming it. */
PyObject *py_measurements_wire(PyObject *self, PyObject *args)
{
    PyObject *oq, *ot, *ocov, *ow, *otimes, *osrc, *obody;
    int field = 3;
    if (!PyArg_ParseTuple(args, "OOOOOOO|i:measurements_wire", &oq, &ot, &ocov, &ow, &otimes,
                          &osrc, &obody, &field))
        return NULL;
    if (field < 1 || field > 15) {
        PyErr_SetString(PyExc_ValueError, "field: expected 1..15 (a one-byte tag)");
        return NULL;
    }
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
        size_t at = len;
        len += dq_wire_measurement(buf + len, a, (size_t)na, b, (size_t)nb, ptm ? ptm[i] : 0.0,
                                   pq + 4 * i, pt + 3 * i, pc ? pc + 36 * i : NULL,
                                   pw ? pw[i] : 0.0);
        buf[at] = (uint8_t)(field << 3 | 2); /* each entry starts with its one-byte tag */
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

/* ---- a FusedPose written (fused_wire.h) ------------------------------------------------------- */

/* the n elements of obj as a C-contiguous array of type (NPY_DOUBLE, NPY_UINT32, ...), named
 * for an error; None with n 0 is an empty array */
static PyArrayObject *column(PyObject *obj, int type, npy_intp *n, npy_intp want, const char *name)
{
    PyArrayObject *a = (PyArrayObject *)PyArray_FROM_OTF(obj, type, NPY_ARRAY_IN_ARRAY |
                                                                    NPY_ARRAY_FORCECAST);
    if (!a) return NULL;
    if (want >= 0 && PyArray_SIZE(a) != want) {
        PyErr_Format(PyExc_ValueError, "%s: expected %zd values, got %zd", name, (Py_ssize_t)want,
                     (Py_ssize_t)PyArray_SIZE(a));
        Py_DECREF(a);
        return NULL;
    }
    if (n) *n = PyArray_SIZE(a);
    return a;
}

static int utf8(PyObject *s, const char *name, dq_str *out)
{
    if (!PyUnicode_Check(s)) {
        PyErr_Format(PyExc_TypeError, "%s: expected a string, got %s", name, Py_TYPE(s)->tp_name);
        return -1;
    }
    Py_ssize_t n;
    out->s = PyUnicode_AsUTF8AndSize(s, &n);
    out->n = (size_t)n;
    return out->s ? 0 : -1;
}

/* each item of seq (a PySequence_Fast) read by fill into the k-th record of size bytes of a new
 * array *out (the caller frees it); returns the count, or -1 with an exception set */
typedef int (*fill_fn)(PyObject *item, void *out);

static Py_ssize_t records(PyObject *seq, size_t size, fill_fn fill, void **out, const char *name)
{
    Py_ssize_t n = PySequence_Fast_GET_SIZE(seq);
    *out = PyMem_Calloc(n ? (size_t)n : 1, size);
    if (!*out) {
        PyErr_NoMemory();
        return -1;
    }
    for (Py_ssize_t k = 0; k < n; k++)
        if (fill(PySequence_Fast_GET_ITEM(seq, k), (char *)*out + (size_t)k * size)) {
            if (!PyErr_Occurred()) PyErr_Format(PyExc_ValueError, "%s[%zd]: malformed", name, k);
            return -1;
        }
    return n;
}

static int fill_str(PyObject *item, void *out) { return utf8(item, "string", (dq_str *)out); }

static int fill_source(PyObject *item, void *out)
{
    dq_wire_source *s = (dq_wire_source *)out;
    PyObject *name;
    if (!PyArg_ParseTuple(item, "OIIdddI", &name, &s->count, &s->rejected, &s->nis_mean, &s->low,
                          &s->high, &s->verdict))
        return -1;
    return utf8(name, "sources.name", &s->name);
}

static int fill_dropped(PyObject *item, void *out)
{
    dq_wire_dropped *d = (dq_wire_dropped *)out;
    PyObject *source, *reason;
    if (!PyArg_ParseTuple(item, "IOdO", &d->index, &source, &d->age, &reason)) return -1;
    return utf8(source, "dropped.source", &d->source) || utf8(reason, "dropped.reason", &d->reason);
}

static int fill_latency(PyObject *item, void *out)
{
    dq_wire_latency *a = (dq_wire_latency *)out;
    PyObject *source;
    if (!PyArg_ParseTuple(item, "Odddd", &source, &a->configured, &a->prior_sigma, &a->value,
                          &a->sigma))
        return -1;
    return utf8(source, "latencies.source", &a->source);
}

/* fused_pose_wire(body, time, mean (8,), covariance (36), inliers, rejected, reasons,
 * rejected_sources, chi2, dof, iterations, status, distances (n,), nis (n,), tested (n,),
 * residuals (n, 6), sources [(name, count, rejected, nis_mean, low, high, verdict)], request,
 * measurements, dropped [(index, source, age, reason)], twist (6,) or None, twist_covariance (36)
 * or None, extrapolation, latencies [(source, configured, prior_sigma, value, sigma)]) -> the
 * FusedPose's bytes (dq_fused_pose_write); status and verdicts as proto numbers. */
PyObject *py_fused_pose_wire(PyObject *self, PyObject *args)
{
    PyObject *obody, *omean, *ocov, *oinl, *orej, *oreasons, *orsrc, *odist, *onis, *otested,
             *ores, *osrc, *omeas, *odrop, *otwist, *otc, *olat;
    dq_fused_pose f;
    memset(&f, 0, sizeof f);
    if (!PyArg_ParseTuple(args, "OdOOOOOOdIIIOOOOOIOOOOdO:fused_pose_wire", &obody, &f.time,
                          &omean, &ocov, &oinl, &orej, &oreasons, &orsrc, &f.chi2, &f.dof,
                          &f.iterations, &f.status, &odist, &onis, &otested, &ores, &osrc,
                          &f.request, &omeas, &odrop, &otwist, &otc, &f.extrapolation, &olat))
        return NULL;
    PyArrayObject *arr[11] = {NULL};
    PyObject *seq[5] = {NULL};
    void *mem[5] = {NULL};
    PyObject *result = NULL;
    npy_intp n_inl, n_rej, n, n_meas;
    if (utf8(obody, "body", &f.body)) goto done;
    if (!(arr[0] = column(omean, NPY_DOUBLE, NULL, 8, "mean")) ||
        !(arr[1] = column(ocov, NPY_DOUBLE, NULL, 36, "covariance")) ||
        !(arr[2] = column(oinl, NPY_UINT32, &n_inl, -1, "inliers")) ||
        !(arr[3] = column(orej, NPY_UINT32, &n_rej, -1, "rejected")) ||
        !(arr[4] = column(odist, NPY_DOUBLE, &n, -1, "distances")) ||
        !(arr[5] = column(onis, NPY_DOUBLE, NULL, n, "nis")) ||
        !(arr[6] = column(otested, NPY_UINT8, NULL, n, "tested")) ||
        !(arr[7] = column(ores, NPY_DOUBLE, NULL, 6 * n, "residuals")) ||
        !(arr[8] = column(omeas, NPY_UINT64, &n_meas, -1, "measurements")))
        goto done;
    if (otwist != Py_None && (!(arr[9] = column(otwist, NPY_DOUBLE, NULL, 6, "twist")) ||
                              !(arr[10] = column(otc, NPY_DOUBLE, NULL, 36, "twist_covariance"))))
        goto done;
    const char *names[5] = {"reasons", "rejected_sources", "sources", "dropped", "latencies"};
    PyObject *given[5] = {oreasons, orsrc, osrc, odrop, olat};
    for (int k = 0; k < 5; k++)
        if (!(seq[k] = PySequence_Fast(given[k], names[k]))) goto done;
    if (PySequence_Fast_GET_SIZE(seq[0]) != n_rej || PySequence_Fast_GET_SIZE(seq[1]) != n_rej) {
        PyErr_SetString(PyExc_ValueError, "reasons, rejected_sources: expected one a rejection");
        goto done;
    }
    Py_ssize_t got[5];
    size_t sizes[5] = {sizeof(dq_str), sizeof(dq_str), sizeof(dq_wire_source),
                       sizeof(dq_wire_dropped), sizeof(dq_wire_latency)};
    fill_fn fills[5] = {fill_str, fill_str, fill_source, fill_dropped, fill_latency};
    for (int k = 0; k < 5; k++)
        if ((got[k] = records(seq[k], sizes[k], fills[k], &mem[k], names[k])) < 0) goto done;
    double unit[8];
    if (dq_unit(PyArray_DATA(arr[0]), unit)) {
        PyErr_SetString(PyExc_ValueError, "mean: not a unit dual quaternion");
        goto done;
    }
    dq_to_pose(unit, f.quat, f.t);
    f.covariance = PyArray_DATA(arr[1]);
    f.inliers = PyArray_DATA(arr[2]);
    f.n_inliers = (size_t)n_inl;
    f.rejected = PyArray_DATA(arr[3]);
    f.n_rejected = (size_t)n_rej;
    f.reasons = mem[0];
    f.rejected_sources = mem[1];
    f.distances = PyArray_DATA(arr[4]);
    f.nis = PyArray_DATA(arr[5]);
    f.tested = PyArray_DATA(arr[6]);
    f.residuals = PyArray_DATA(arr[7]);
    f.n = (size_t)n;
    f.sources = mem[2];
    f.n_sources = (size_t)got[2];
    f.measurements = PyArray_DATA(arr[8]);
    f.n_measurements = (size_t)n_meas;
    f.dropped = mem[3];
    f.n_dropped = (size_t)got[3];
    f.twist = arr[9] ? PyArray_DATA(arr[9]) : NULL;
    f.twist_covariance = arr[10] ? PyArray_DATA(arr[10]) : NULL;
    f.latencies = mem[4];
    f.n_latencies = (size_t)got[4];
    result = PyBytes_FromStringAndSize(NULL, (Py_ssize_t)dq_fused_pose_bound(&f));
    if (!result) goto done;
    size_t len = dq_fused_pose_write(&f, (uint8_t *)PyBytes_AS_STRING(result));
    _PyBytes_Resize(&result, (Py_ssize_t)len);
done:
    for (int k = 0; k < 11; k++) Py_XDECREF(arr[k]);
    for (int k = 0; k < 5; k++) {
        Py_XDECREF(seq[k]);
        PyMem_Free(mem[k]);
    }
    return result;
}

/* frame_entries(heads, spans, tails): a FrameList's entries (field 1, one FrameInfo each): entry
 * k is heads[k] (its name, parent and kind, written already), spans[k] as FrameInfo's fields 4,
 * 5 and 6 (oldest, newest, rate_hz; +0.0 left out), then tails[k] (its sources). */
PyObject *py_frame_entries(PyObject *self, PyObject *args)
{
    PyObject *heads, *so, *tails;
    if (!PyArg_ParseTuple(args, "O!OO!", &PyList_Type, &heads, &so, &PyList_Type, &tails))
        return NULL;
    const Py_ssize_t n = PyList_GET_SIZE(heads);
    if (PyList_GET_SIZE(tails) != n)
        return PyErr_Format(PyExc_ValueError, "tails: expected %zd, got %zd", n,
                            PyList_GET_SIZE(tails));
    PyObject *spans = double_rows(so, n, 3, "spans");
    if (!spans) return NULL;
    const double *d = PyArray_DATA((PyArrayObject *)spans);
    size_t size = 0;
    for (Py_ssize_t k = 0; k < n; k++) {
        PyObject *h = PyList_GET_ITEM(heads, k), *t = PyList_GET_ITEM(tails, k);
        if (!PyBytes_Check(h) || !PyBytes_Check(t)) {
            Py_DECREF(spans);
            return PyErr_Format(PyExc_TypeError, "heads, tails: expected bytes at %zd", k);
        }
        /* tag, a length of at most 10 bytes, three doubles of 9 bytes */
        size += 11 + 27 + (size_t)PyBytes_GET_SIZE(h) + (size_t)PyBytes_GET_SIZE(t);
    }
    PyObject *out = PyBytes_FromStringAndSize(NULL, (Py_ssize_t)size);
    if (!out) {
        Py_DECREF(spans);
        return NULL;
    }
    uint8_t *p = (uint8_t *)PyBytes_AS_STRING(out), *start = p;
    for (Py_ssize_t k = 0; k < n; k++) {
        PyObject *h = PyList_GET_ITEM(heads, k), *t = PyList_GET_ITEM(tails, k);
        uint8_t body[27], *q = body;
        for (int f = 0; f < 3; f++) q = put_double(q, 4 + f, d[3 * k + f]);
        const size_t hn = (size_t)PyBytes_GET_SIZE(h), tn = (size_t)PyBytes_GET_SIZE(t);
        const size_t bn = (size_t)(q - body);
        p = put_tag(p, 1, WT_LEN);
        p = put_varint(p, hn + bn + tn);
        memcpy(p, PyBytes_AS_STRING(h), hn);
        memcpy(p + hn, body, bn);
        memcpy(p + hn + bn, PyBytes_AS_STRING(t), tn);
        p += hn + bn + tn;
    }
    Py_DECREF(spans);
    if (_PyBytes_Resize(&out, (Py_ssize_t)(p - start)) < 0) return NULL;
    return out;
}
