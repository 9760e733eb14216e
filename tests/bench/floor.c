/*
 * floor.c — the "floor": the same math written the straightforward way, one pose at a time,
 * with atan2/sqrt/sin/cos per pose and nothing precomputed or cached. It shares no code with
 * service/csrc, so the benchmark can also check that both agree.
 */
#include <math.h>
#include <stddef.h>

static void qmul(const double *a, const double *b, double *c)
{
    c[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3];
    c[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2];
    c[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1];
    c[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0];
}

static void dmul(const double *a, const double *b, double *o)
{
    double d1[4], d2[4];
    qmul(a, b, o);
    qmul(a, b + 4, d1);
    qmul(a + 4, b, d2);
    for (int i = 0; i < 4; i++) o[4 + i] = d1[i] + d2[i];
}

static void dconj(const double *a, double *o)
{
    o[0] = a[0]; o[4] = a[4];
    for (int i = 1; i < 4; i++) { o[i] = -a[i]; o[4 + i] = -a[4 + i]; }
}

/* Screw form of a unit dual quaternion: real (cos p, sin p l), dual (-h sin p, sin p m + h cos p l),
 * p = theta/2, h = d/2. Returns the 6-vector log = (p l, h l + p m). */
static void floor_log(const double *q, double *x)
{
    double s = q[0] < 0.0 ? -1.0 : 1.0;
    double w = s * q[0], wd = s * q[4];
    double v[3] = {s * q[1], s * q[2], s * q[3]}, u[3] = {s * q[5], s * q[6], s * q[7]};
    double n = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    if (n < 1e-12) {
        for (int i = 0; i < 3; i++) { x[i] = 0.0; x[3 + i] = u[i]; }
        return;
    }
    double p = atan2(n, w);
    double h = -wd / n;
    for (int i = 0; i < 3; i++) {
        double l = v[i] / n;
        double m = (u[i] - h * w * l) / n;
        x[i] = p * l;
        x[3 + i] = h * l + p * m;
    }
}

static void floor_exp(const double *x, double *q)
{
    double p = sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2]);
    if (p < 1e-12) {
        q[0] = 1.0; q[1] = q[2] = q[3] = 0.0; q[4] = 0.0;
        for (int i = 0; i < 3; i++) q[5 + i] = x[3 + i];
        return;
    }
    double l[3] = {x[0] / p, x[1] / p, x[2] / p};
    double h = l[0] * x[3] + l[1] * x[4] + l[2] * x[5];
    double sp = sin(p), cp = cos(p);
    q[0] = cp;
    q[4] = -h * sp;
    for (int i = 0; i < 3; i++) {
        double m = (x[3 + i] - h * l[i]) / p;
        q[1 + i] = sp * l[i];
        q[5 + i] = sp * m + h * cp * l[i];
    }
}

void floor_sclerp(const double *a, const double *b, double tau, double *out)
{
    double bb[8], ac[8], rel[8], x[6], e[8];
    double dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3];
    for (int i = 0; i < 8; i++) bb[i] = dot < 0.0 ? -b[i] : b[i];
    dconj(a, ac);
    dmul(ac, bb, rel);
    floor_log(rel, x);
    for (int i = 0; i < 6; i++) x[i] *= tau;
    floor_exp(x, e);
    dmul(a, e, out);
}

/* Independent pairs: floor_sclerp of each (the C harness's floor, and the plain C loop bench_core
 * times beside ScLERP pairs from Python). */
void floor_sclerp_each(const double *a, const double *b, const double *tau, size_t n, double *out)
{
    for (size_t i = 0; i < n; i++) floor_sclerp(a + 8 * i, b + 8 * i, tau[i], out + 8 * i);
}

static void floor_normalize(double *q)
{
    double n = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    double rd = (q[0] * q[4] + q[1] * q[5] + q[2] * q[6] + q[3] * q[7]) / (n * n);
    for (int i = 0; i < 4; i++) {
        q[4 + i] = (q[4 + i] - rd * q[i]) / n;
        q[i] /= n;
    }
}

void floor_dlb(const double *q, const double *w, size_t n, double *out)
{
    size_t k = 0;
    for (size_t i = 1; i < n; i++) if (w[i] > w[k]) k = i;
    for (int j = 0; j < 8; j++) out[j] = 0.0;
    for (size_t i = 0; i < n; i++) {
        const double *qi = q + 8 * i, *pv = q + 8 * k;
        double dot = pv[0] * qi[0] + pv[1] * qi[1] + pv[2] * qi[2] + pv[3] * qi[3];
        double wi = dot < 0.0 ? -w[i] : w[i];
        for (int j = 0; j < 8; j++) out[j] += wi * qi[j];
    }
    floor_normalize(out);
}

int floor_dib(const double *q, const double *w, size_t n, double tol, int max_iter, double *out)
{
    double b[8], bc[8], rel[8], l[6], x[6], e[8];
    floor_dlb(q, w, n, b);
    int k;
    for (k = 0; k < max_iter; k++) {
        for (int j = 0; j < 6; j++) x[j] = 0.0;
        dconj(b, bc);
        for (size_t i = 0; i < n; i++) {
            dmul(bc, q + 8 * i, rel);
            floor_log(rel, l);
            for (int j = 0; j < 6; j++) x[j] += w[i] * l[j];
        }
        double r = 0.0;
        for (int j = 0; j < 6; j++) r += x[j] * x[j];
        if (sqrt(r) < tol) break;
        floor_exp(x, e);
        dmul(b, e, rel);
        floor_normalize(rel);
        for (int j = 0; j < 8; j++) b[j] = rel[j];
    }
    for (int j = 0; j < 8; j++) out[j] = b[j];
    return k;
}
