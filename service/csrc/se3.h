/*
 * se3.h — the SE(3) Jacobians the fusion linearises with, in pure C99.
 *
 * xi = [w v] is a twist, rotation first (fusion.h's convention), Exp(xi) = dq_exp(xi / 2);
 * matrices are 6 x 6 row-major. Jl^-1 and Jr are Barfoot's closed forms (the formulas of
 * service/lie.py), from their Taylor series below a rotation angle of 0.5. Each takes s2 and ch,
 * the squared sine and the cosine of half the rotation angle, from the quaternion the rotation
 * came from (dq_se3_residual gives them), so no trigonometric call is needed.
 */
#ifndef DQPOSE_SE3_H
#define DQPOSE_SE3_H

/* Jl^-1(xi) = [[Ji, 0], [-Ji Q Ji, Ji]] with Ji = I - w^/2 + D w^2. */
void dq_jl_inv(const double *xi, double s2, double ch, double *J);

/* s Jr(xi) = s Jl(-xi), written into the 6 x 6 block at the top left of the ld-strided J. */
void dq_jr_scaled(const double *xi, double s2, double ch, double s, double *J, int ld);

/* r = Log(xc z) (xc the inverse of the estimate, z a unit pose), and sc = [s2, ch] of its
 * rotation. */
void dq_se3_residual(const double *xc, const double *z, double *r, double *sc);

/* Ad(q) = [[R, 0], [t^ R, R]] of the unit pose q (service/lie.py's adjoint): a right
 * perturbation carried through q, q Exp(xi) = Exp(Ad(q) xi) q. */
void dq_adjoint(const double *q, double *Ad);

/* out = X Exp(delta), normalised (a Gauss-Newton step's retraction): 0, or nonzero when the
 * result is not finite (dq_normalize's code). */
int dq_retract(const double *X, const double *delta, double *out);

/* DQ_LANES (linalg6.h) of dq_jl_inv, dq_jr_scaled (ld 6) and dq_adjoint side by side, entry k of
 * lane l at [DQ_LANES k + l] (xi, s, q in; J, Ad out), each lane's bits those of the function on
 * its own; dq_jl_inv_lanes and dq_jr_scaled_lanes return 0, writing nothing, when a lane's
 * rotation is beyond their series (then the scalar ones serve). */
#include "vecmath.h"
#if DQ_V4
int dq_jl_inv_lanes(const double *xi, double *J);
int dq_jr_scaled_lanes(const double *xi, const double *s, double *J);
void dq_adjoint_lanes(const double *q, double *Ad);
#endif

#endif
