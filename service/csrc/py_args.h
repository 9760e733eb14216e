/*
 * py_args.h — what the Python bindings (py_*.c) share: NumPy's C API for every file that uses it,
 * the element-wise driver run_kernel (argument specs, float64 conversion, core-shape checks,
 * broadcasting of the leading dimensions, the GIL released for batches) and the ValueError texts
 * that name the argument, its index and the problem.
 *
 * A kernel validates its element and returns a DQ_E* code; the first failure becomes a ValueError
 * naming the argument, the index and the problem. Only module.c and the py_*.c files include
 * this header (and so Python.h); the geometry is in the pure C files.
 */
#ifndef DQPOSE_PY_ARGS_H
#define DQPOSE_PY_ARGS_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>

/* One NumPy API table for the whole extension: module.c imports it (DQ_PY_IMPORT_ARRAY), the
 * other files use it. */
#define PY_ARRAY_UNIQUE_SYMBOL dqpose_ARRAY_API
#ifndef DQ_PY_IMPORT_ARRAY
#define NO_IMPORT_ARRAY
#endif
#include <numpy/arrayobject.h>

#include <stddef.h>

#define MAX_IN 3
#define MAX_OUT 3
/* Below this many elements releasing the GIL costs more than it gives. */
#define GIL_RELEASE_MIN 64

typedef struct {
    const char *name;
    int ncore;          /* trailing dims that belong to one element: 0, 1 or 2 */
    npy_intp core[2];   /* their sizes; -1 = any (the set size n of a blend) */
    int optional;       /* None allowed (weights) */
} in_spec;

typedef struct {
    int ncore;
    npy_intp core[2];   /* -1 = the n of input 0 */
} out_spec;

/* What a kernel gets for one element. */
typedef struct {
    const double *in[MAX_IN];
    double *out[MAX_OUT];
    npy_intp n;        /* set size for blends */
    void *ctx;
    int bad_arg;       /* set by a kernel on failure: which input */
    npy_intp bad_sub;  /* and which sub-element of it (pose in a set, weight index) */
    double *scratch;
} elem;

typedef int (*kernel_fn)(elem *e);

/*
 * Runs `kern` over the broadcast of the inputs. objs[i] may be NULL/None for optional inputs;
 * scratch_per_n doubles per set element are the kernel's scratch. Returns a new reference: the
 * single output, or a tuple when nout > 1; NULL with a ValueError naming the bad argument.
 */
PyObject *run_kernel(kernel_fn kern, void *ctx, int nin, PyObject **objs, const in_spec *is,
                     int nout, const out_spec *os, size_t scratch_per_n);

/* "(2, 3)", "(4,)" */
void format_shape(char *buf, size_t len, int nd, const npy_intp *shape);
/* "name[i, j]" for the element at flat sub-index `flat` of an array whose index space is
 * `shape` */
void format_index(char *buf, size_t len, const char *name, int nd, const npy_intp *shape,
                  npy_intp flat);
/* The problem text for a DQ_E* code, with the details of the offending values v (kind: how many
 * values, 16 for a matrix) where it helps. */
void problem_text(int code, const double *v, int kind, char *buf, size_t len);

/* The ValueError of a fit's failure (fuse, motion_fit, joint_fit): the whole fit's, naming
 * `inliers` (none selected) or `covariances` (the information singular, the result not finite),
 * or one measurement's, `where` its argument and index ("covariances[3]") and `pose` the pose
 * it names (NULL: not a pose). */
void fit_error(int code, const char *inliers, const char *covariances, const char *where,
               const double *pose);

/* The stopping rule of an iteration (DIB, DEC, fusion): 0, or -1 with a ValueError. */
int check_iteration(double tol, int max_iter);

/* An array of `type` and exactly `shape` (nd <= 3), or NULL with a ValueError naming it. */
PyArrayObject *exact_array(PyObject *o, int type, const char *name, int nd, const npy_intp *shape);

/* A tuple of the n outputs (None for a NULL one), taking their references: outs[j] is left
 * NULL so the caller's cleanup does not release them again. NULL when the tuple cannot be made
 * (then outs keeps its references). */
PyObject *steal_tuple(PyArrayObject **outs, int n);

#endif
