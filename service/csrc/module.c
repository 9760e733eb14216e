/*
 * module.c — the extension module dqpose._dqcore: its method table and its initialisation
 * (NumPy's C API imported, the constants Python reads). The functions are the py_*.c files';
 * only they and this file know CPython and NumPy, the geometry is in the pure C files.
 */
#define DQ_PY_IMPORT_ARRAY
#include "py_args.h"

#include "blend.h"
#include "dq.h"
#include "fusion.h"
#include "gn.h"
#include "py_functions.h"
#include "store.h"
#include "wire.h"

static PyMethodDef methods[] = {
    {"mul", py_mul, METH_VARARGS, "mul(a, b): dual-quaternion product a b."},
    {"conj", py_conj, METH_O, "conj(a): quaternion conjugate of both parts (the inverse of a pose)."},
    {"normalize", py_normalize, METH_O, "normalize(a): divide by the dual-number norm."},
    {"log", py_log, METH_O, "log(a) -> [...,6]."},
    {"exp", py_exp, METH_O, "exp(x[...,6]) -> [...,8]."},
    {"power", py_power, METH_VARARGS, "power(a, tau) = exp(tau log a)."},
    {"sclerp", py_sclerp, METH_VARARGS, "sclerp(a, b, tau)."},
    {"from_matrix", py_from_matrix, METH_O, "from_matrix(T[...,4,4]) -> [...,8]."},
    {"to_matrix", py_to_matrix, METH_O, "to_matrix(a) -> [...,4,4]."},
    {"from_pose", py_from_pose, METH_VARARGS, "from_pose(q[...,4], t[...,3]) -> [...,8]."},
    {"to_pose", py_to_pose, METH_O, "to_pose(a) -> (q[...,4], t[...,3])."},
    {"transform", py_transform, METH_VARARGS, "transform(a, p[...,3]) -> [...,3]."},
    {"screw", py_screw, METH_O, "screw(a) -> (theta, d, [l | m])."},
    {"blend", py_blend, METH_VARARGS, "blend(dqs, weights, method, tol, max_iter)."},
    {"fuse", py_fuse, METH_VARARGS,
     "fuse(poses, covariances, inliers, tol, max_iter, nis) -> (mean, covariance, residuals, "
     "distances, nis, tested, status, iterations, chi2)."},
    {"motion_fit", py_motion_fit, METH_VARARGS, "motion_fit(...): the constant-twist fit (motion.h)."},
    {"motion_determined", py_motion_determined, METH_VARARGS,
     "motion_determined(stamps, latencies, inliers, two_instants): does the state stay determined "
     "without each measurement (motion.h)."},
    {"joint_fit", py_joint_fit, METH_VARARGS,
     "joint_fit(...): several bodies and the uncertain extrinsics' errors fitted jointly "
     "(joint.h)."},
    {"lookup", py_lookup, METH_VARARGS, "lookup(...): a World's Lookup in one call (lookup.h)."},
    {"relative_pose_bytes", py_relative_pose_bytes, METH_VARARGS,
     "relative_pose_bytes(pose, covariance, time) -> a RelativePose's bytes (lookup.h)."},
    {"se3_jl_inv", py_se3_jl_inv, METH_O,
     "se3_jl_inv(xi[...,6]) -> [...,6,6]: the SE(3) left Jacobian's inverse (service/lie.py)."},
    {"se3_jr", py_se3_jr, METH_O,
     "se3_jr(xi[...,6]) -> [...,6,6]: the SE(3) right Jacobian (service/lie.py)."},
    {"check_rows", py_check_rows, METH_VARARGS,
     "check_rows(poses, covariances, sym_tol) -> (ok, symmetrised): a stream's rows by the "
     "Tracker's pose and covariance rules (fusion.h)."},
    {"pair_distances", py_pair_distances, METH_VARARGS,
     "pair_distances(poses, covariances, candidates) -> (m, n) squared Mahalanobis distances of "
     "the consensus (fusion.h)."},
    {"traj_plan", py_traj_plan, METH_VARARGS,
     "traj_plan(waypoints, mode, radius, times, limits, sigma0) -> (code, bad, plan, duration, segments)."},
    {"traj_eval", py_traj_eval, METH_VARARGS, "traj_eval(plan, mode, duration, times) -> (poses, linear, angular)."},
    {"lin", py_lin, METH_VARARGS, "lin(dqs, weights): the raw matrix blend -> [...,4,4]."},
    {"blend_request_from_wire", py_blend_request_from_wire, METH_O,
     "blend_request_from_wire(bytes) -> (poses, weights, method, tolerance, max_iterations) or None."},
    {"publish_head", py_publish_head, METH_O,
     "publish_head(bytes) -> (producer, sequence, count) of a PublishRequest, or None."},
    {"fuse_stream_from_wire", py_fuse_stream_from_wire, METH_VARARGS,
     "fuse_stream_from_wire(bytes, sym_tol, publish=False) -> (poses, covariances, times, "
     "codes, bodies, sources, spans) or None."},
    {"measurements_wire", py_measurements_wire, METH_VARARGS,
     "measurements_wire(q, t, covariances, weights, times, sources, bodies, field=3) -> bytes: "
     "repeated FuseStreamRequest.measurements (field 1: PublishRequest's)."},
    {"fused_pose_wire", py_fused_pose_wire, METH_VARARGS,
     "fused_pose_wire(body, time, mean, covariance, inliers, rejected, reasons, "
     "rejected_sources, chi2, dof, iterations, status, distances, nis, tested, residuals, "
     "sources, request, measurements, dropped, twist, twist_covariance, extrapolation, "
     "latencies) -> FusedPose bytes."},
    {"frame_entries", py_frame_entries, METH_VARARGS,
     "frame_entries(heads, spans, tails) -> a FrameList's entries: heads[k] + FrameInfo fields "
     "4-6 of spans[k] (n x 3) + tails[k], each as field 1."},
    {"blend_batch_wire", py_blend_batch_wire, METH_VARARGS,
     "blend_batch_wire(bytes, max_requests, max_total_poses, max_poses, default_tol, "
     "default_max_iter, max_iter_limit) -> (bytes, n) or None."},
    {"blend_wire", py_blend_wire, METH_VARARGS,
     "blend_wire(bytes, max_poses, default_tol, default_max_iter, max_iter_limit) -> bytes or None."},
    {"tick", py_tick, METH_VARARGS,
     "tick(options, poses, covs, times, codes, ids, rows, time, body, request, bounds) -> bytes "
     "or None: one tick's FusedPose (tick.h)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef moddef = {
    PyModuleDef_HEAD_INIT, "_dqcore",
    "C core of dqpose: dual-quaternion algebra and blending. Use dqpose.dq instead.", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__dqcore(void)
{
    import_array();
    PyObject *m = PyModule_Create(&moddef);
    if (!m) return NULL;
    /* METHODS: {"DIB": 1, ...}, the C enum as it is, for the test against service/dq.py */
    PyObject *codes = PyDict_New();
    if (!codes || PyModule_AddObject(m, "METHODS", codes) < 0) {
        Py_XDECREF(codes);
        Py_DECREF(m);
        return NULL;
    }
#define ADD_METHOD_(name, value)                                                  \
    do {                                                                          \
        PyObject *v_ = PyLong_FromLong(DQ_##name);                                \
        if (!v_ || PyDict_SetItemString(codes, #name, v_) < 0) {                  \
            Py_XDECREF(v_);                                                       \
            Py_DECREF(m);                                                         \
            return NULL;                                                          \
        }                                                                         \
        Py_DECREF(v_);                                                            \
    } while (0);
    DQ_METHODS(ADD_METHOD_)
#undef ADD_METHOD_
    PyModule_AddObject(m, "UNIT_TOL", PyFloat_FromDouble(DQ_UNIT_TOL));
    /* fuse_stream_from_wire's codes up to this one are measurements_to_arrays's, the rest the
     * Tracker's (wire.h) */
    PyModule_AddIntConstant(m, "MEASUREMENT_CONVERT_LAST", DQ_MEAS_CONVERT_LAST);
    PyModule_AddIntConstant(m, "REFUSED_TIME", DQ_REFUSED_TIME);
    PyModule_AddIntConstant(m, "REFUSED_JUMP", DQ_REFUSED_JUMP);
    PyModule_AddIntConstant(m, "REFUSED_FLOOR", DQ_REFUSED_FLOOR);
    PyModule_AddObject(m, "MIN_VARIANCE", PyFloat_FromDouble(DQ_MIN_VARIANCE));
    PyModule_AddObject(m, "MAX_VARIANCE", PyFloat_FromDouble(DQ_MAX_VARIANCE));
    /* the fits' step rule (gn.h), for process_noise.py's NumPy loop */
    PyModule_AddObject(m, "COST_SLACK", PyFloat_FromDouble(DQ_GN_COST_SLACK));
    PyModule_AddIntConstant(m, "MAX_HALVINGS", DQ_GN_MAX_HALVINGS);
    if (PyType_Ready(&dq_store_index_type) < 0
        || PyModule_AddObjectRef(m, "StoreIndex", (PyObject *)&dq_store_index_type) < 0
        || PyType_Ready(&dq_fit_options_type) < 0
        || PyModule_AddObjectRef(m, "FitOptions", (PyObject *)&dq_fit_options_type) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
