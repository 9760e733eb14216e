/*
 * py_se3.c — the Python functions of se3.h: the SE(3) Jacobians Jl^-1(xi) and Jr(xi) of twists
 * (..., 6), element by element, for service/lie.py (which checks its arguments first).
 */
#include "py_args.h"

#include <math.h>

#include "dq.h"
#include "py_functions.h"
#include "se3.h"

/* se3.h's functions take the squared sine and the cosine of half the rotation angle. */
static void half_angle(const double *xi, double *s2, double *ch)
{
    double t = sqrt(xi[0] * xi[0] + xi[1] * xi[1] + xi[2] * xi[2]);
    double sh = sin(0.5 * t);
    *s2 = sh * sh;
    *ch = cos(0.5 * t);
}

static int k_jl_inv(elem *e)
{
    if (!dq_finite_n(e->in[0], 6)) { e->bad_arg = 0; return DQ_E_NONFINITE; }
    double s2, ch;
    half_angle(e->in[0], &s2, &ch);
    dq_jl_inv(e->in[0], s2, ch, e->out[0]);
    return DQ_OK;
}

static int k_jr(elem *e)
{
    if (!dq_finite_n(e->in[0], 6)) { e->bad_arg = 0; return DQ_E_NONFINITE; }
    double s2, ch;
    half_angle(e->in[0], &s2, &ch);
    dq_jr_scaled(e->in[0], s2, ch, 1.0, e->out[0], 6);
    return DQ_OK;
}

static PyObject *jacobian(kernel_fn k, PyObject *x)
{
    in_spec s = {"xi", 1, {6, 0}, 0};
    out_spec o = {2, {6, 6}};
    PyObject *objs[1] = {x};
    return run_kernel(k, NULL, 1, objs, &s, 1, &o, 0);
}

PyObject *py_se3_jl_inv(PyObject *self, PyObject *x) { return jacobian(k_jl_inv, x); }
PyObject *py_se3_jr(PyObject *self, PyObject *x) { return jacobian(k_jr, x); }
