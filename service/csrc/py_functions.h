/*
 * py_functions.h — the Python functions of _dqcore, for module.c's method table; each py_*.c
 * defines those of one part of the core.
 */
#ifndef DQPOSE_PY_FUNCTIONS_H
#define DQPOSE_PY_FUNCTIONS_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>

/* py_dq.c: the dual-quaternion algebra and the blends */
PyObject *py_mul(PyObject *self, PyObject *args);
PyObject *py_conj(PyObject *self, PyObject *x);
PyObject *py_normalize(PyObject *self, PyObject *x);
PyObject *py_log(PyObject *self, PyObject *x);
PyObject *py_exp(PyObject *self, PyObject *x);
PyObject *py_from_matrix(PyObject *self, PyObject *x);
PyObject *py_to_matrix(PyObject *self, PyObject *x);
PyObject *py_power(PyObject *self, PyObject *args);
PyObject *py_sclerp(PyObject *self, PyObject *args);
PyObject *py_from_pose(PyObject *self, PyObject *args);
PyObject *py_to_pose(PyObject *self, PyObject *x);
PyObject *py_transform(PyObject *self, PyObject *args);
PyObject *py_screw(PyObject *self, PyObject *x);
PyObject *py_blend(PyObject *self, PyObject *args);
PyObject *py_lin(PyObject *self, PyObject *args);

/* py_wire.c: the wire codecs */
PyObject *py_blend_request_from_wire(PyObject *self, PyObject *arg);
PyObject *py_blend_wire(PyObject *self, PyObject *args);
PyObject *py_blend_batch_wire(PyObject *self, PyObject *args);
PyObject *py_fuse_stream_from_wire(PyObject *self, PyObject *args);
PyObject *py_publish_head(PyObject *self, PyObject *arg);
PyObject *py_measurements_wire(PyObject *self, PyObject *args);
PyObject *py_fused_pose_wire(PyObject *self, PyObject *args);
PyObject *py_frame_entries(PyObject *self, PyObject *args);

/* py_fusion.c: the fusion and the constant-twist fit */
PyObject *py_fuse(PyObject *self, PyObject *args);
PyObject *py_motion_fit(PyObject *self, PyObject *args);
PyObject *py_motion_determined(PyObject *self, PyObject *args);
PyObject *py_pair_distances(PyObject *self, PyObject *args);
PyObject *py_check_rows(PyObject *self, PyObject *args);

/* py_joint.c: the joint fit with uncertain extrinsics */
PyObject *py_joint_fit(PyObject *self, PyObject *args);
PyObject *py_lookup(PyObject *self, PyObject *args);
PyObject *py_relative_pose_bytes(PyObject *self, PyObject *args);

/* py_se3.c: the SE(3) Jacobians */
PyObject *py_se3_jl_inv(PyObject *self, PyObject *x);
PyObject *py_se3_jr(PyObject *self, PyObject *x);

/* _dqcore.StoreIndex (py_store.c) */
extern PyTypeObject dq_store_index_type;

/* _dqcore.FitOptions and tick (py_tick.c) */
extern PyTypeObject dq_fit_options_type;
PyObject *py_tick(PyObject *self, PyObject *args);

/* py_trajectory.c: the trajectory planner */
PyObject *py_traj_plan(PyObject *self, PyObject *args);
PyObject *py_traj_eval(PyObject *self, PyObject *args);

#endif
