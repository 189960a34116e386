/* The argument check in front of the ahead-of-time kernels (phrt_usd/kernels.py).

   A kernel built ahead of time by numba's pycc unboxes an array argument without
   looking at its dtype or rank (numba checks only the item size), so a call with an
   int32 array where int64 was compiled would read past the buffer. kernels._Guarded
   calls fits() first and sends any call that does not fit to the JIT kernel.

   fits(args, spec) -> bool
     args : the call's arguments (a tuple)
     spec : bytes, SPEC_BYTES per argument: kind (SCALAR, NONE or ARRAY), then for an
            ARRAY its numpy type number, its rank and 1 when it must be C-contiguous.
   An ARRAY argument fits when it is an np.ndarray (not a subclass) whose dtype is
   equivalent to the type number in native byte order (numpy's dtype equality), of
   that rank, and C-contiguous when required; a NONE argument is None; a SCALAR is
   anything but None or an np.ndarray (the wrapper converts it or raises).

   One C call instead of Python code per argument: a trace round makes ~10 kernel calls
   of up to 29 arguments, and checking them in Python was ~30 us of its fixed cost. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#define NPY_NO_DEPRECATED_API NPY_1_7_API_VERSION
#include <numpy/arrayobject.h>

enum { SCALAR = 0, NONE = 1, ARRAY = 2, SPEC_BYTES = 4 };

static int argument_fits(PyObject *value, const unsigned char *spec)
{
    switch (spec[0]) {
    case SCALAR:
        return value != Py_None && Py_TYPE(value) != &PyArray_Type;
    case NONE:
        return value == Py_None;
    case ARRAY: {
        if (Py_TYPE(value) != &PyArray_Type)
            return 0;
        PyArrayObject *array = (PyArrayObject *)value;
        return PyArray_EquivTypenums(PyArray_TYPE(array), spec[1])
               && PyArray_ISNOTSWAPPED(array)
               && PyArray_NDIM(array) == spec[2]
               && (!spec[3] || PyArray_IS_C_CONTIGUOUS(array));
    }
    default:
        return 0;
    }
}

static PyObject *fits(PyObject *module, PyObject *const *argv, Py_ssize_t nargs)
{
    if (nargs != 2 || !PyTuple_Check(argv[0]) || !PyBytes_Check(argv[1])) {
        PyErr_SetString(PyExc_TypeError, "fits(args: tuple, spec: bytes)");
        return NULL;
    }
    PyObject *args = argv[0];
    Py_ssize_t count = PyTuple_GET_SIZE(args);
    if (PyBytes_GET_SIZE(argv[1]) != SPEC_BYTES * count)
        Py_RETURN_FALSE;
    const unsigned char *spec = (const unsigned char *)PyBytes_AS_STRING(argv[1]);
    for (Py_ssize_t i = 0; i < count; i++) {
        if (!argument_fits(PyTuple_GET_ITEM(args, i), spec + SPEC_BYTES * i))
            Py_RETURN_FALSE;
    }
    Py_RETURN_TRUE;
}

static PyMethodDef methods[] = {
    {"fits", (PyCFunction)(void (*)(void))fits, METH_FASTCALL,
     "fits(args, spec): whether a call's arguments are those a build was made for."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module_def = {
    PyModuleDef_HEAD_INIT, "phrt_kernel_guard", NULL, -1, methods,
};

PyMODINIT_FUNC PyInit_phrt_kernel_guard(void)
{
    import_array();
    return PyModule_Create(&module_def);
}
