/* What the two lockstep loop types share beyond _lockstep.h: the helpers their run() calls
 * per call or on a rare path (not per message), the keyword-only constructor, and their
 * part of the module ambhil.bridge.protocol._wire (the LOOP_* constants, the two types). */
#include "_lockstep.h"

static const struct { const char *name; int value; } LOOP_CODES[] = {
    {"LOOP_DONE", LOOP_DONE},   {"LOOP_SLOW", LOOP_SLOW},     {"LOOP_FLUSH", LOOP_FLUSH},
    {"LOOP_CHECK", LOOP_CHECK}, {"LOOP_RAISED", LOOP_RAISED}, {"LOOP_NONFINITE", LOOP_NONFINITE}};

PyObject *s_step_index, *s_status, *s_payload, *s_to_bytes;

/* recv().payload.to_bytes() */
PyObject *recv_bytes(PyObject *recv)
{
    PyObject *smp = PyObject_CallNoArgs(recv);
    if (smp == NULL)
        return NULL;
    PyObject *pl = PyObject_GetAttr(smp, s_payload);
    Py_DECREF(smp);
    if (pl == NULL)
        return NULL;
    PyObject *data = PyObject_CallMethodNoArgs(pl, s_to_bytes);
    Py_DECREF(pl);
    if (data != NULL && !PyBytes_Check(data)) {
        PyErr_SetString(PyExc_TypeError, "payload.to_bytes() did not return bytes");
        Py_CLEAR(data);
    }
    return data;
}


/* The pending exception as an object if it is an Exception (the caller turns it into a
 * fault naming the step), else NULL with it still set (KeyboardInterrupt, SystemExit). */
PyObject *take_exception(void)
{
    if (!PyErr_ExceptionMatches(PyExc_Exception))
        return NULL;
    PyObject *t, *v, *tb;
    PyErr_Fetch(&t, &v, &tb);
    PyErr_NormalizeException(&t, &v, &tb);
    if (tb != NULL && v != NULL)
        PyException_SetTraceback(v, tb);
    Py_XDECREF(t);
    Py_XDECREF(tb);
    return v;
}

int get_buffers(PyObject *const *objs, Py_buffer *b, int nb, const int *writable)
{
    for (int i = 0; i < nb; i++) {
        if (PyObject_GetBuffer(objs[i], &b[i], writable[i] ? PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS
                                                            : PyBUF_C_CONTIGUOUS) < 0) {
            for (int j = 0; j < i; j++)
                PyBuffer_Release(&b[j]);
            return -1;
        }
    }
    return 0;
}

/* A peer id (16 bytes, the all-zero key) or a seal (48 bytes: id + topic key, _wire.h) */
int check_id(PyObject *o, const char *type, const char *field)
{
    if (PyBytes_Check(o) && seal_size_ok(PyBytes_GET_SIZE(o)))
        return 0;
    PyErr_Format(PyExc_TypeError, "%s.%s must be a 16-byte peer id or a 48-byte seal (id + key)",
                 type, field);
    return -1;
}

int check_list(PyObject *o, const char *type, const char *field)
{
    if (PyList_Check(o))
        return 0;
    PyErr_Format(PyExc_TypeError, "%s.%s must be a list", type, field);
    return -1;
}

int unset(const char *type, const char *field)
{
    PyErr_Format(PyExc_TypeError, "%s.run(): field %s is not set", type, field);
    return -1;
}

/* What the two types share: the keyword-only constructor (each keyword sets the field of
 * that name, an unknown name is an AttributeError) and the field tables' entries. */
int kw_init(PyObject *self, PyObject *args, PyObject *kw)
{
    if (PyTuple_GET_SIZE(args) != 0) {
        PyErr_Format(PyExc_TypeError, "%s() takes keyword arguments only (the field names)",
                     Py_TYPE(self)->tp_name);
        return -1;
    }
    PyObject *key, *value;
    Py_ssize_t pos = 0;
    while (kw != NULL && PyDict_Next(kw, &pos, &key, &value))
        if (PyObject_SetAttr(self, key, value) < 0)
            return -1;
    return 0;
}

int lockstep_ready(void)
{
    s_step_index = PyUnicode_InternFromString("step_index");
    s_status = PyUnicode_InternFromString("status");
    s_payload = PyUnicode_InternFromString("payload");
    s_to_bytes = PyUnicode_InternFromString("to_bytes");
    if (!s_step_index || !s_status || !s_payload || !s_to_bytes)
        return -1;
    if (PyType_Ready(&PlantLockstepType) < 0 || PyType_Ready(&ControllerLockstepType) < 0)
        return -1;
    return 0;
}

int lockstep_add(PyObject *m)
{
    for (size_t i = 0; i < sizeof LOOP_CODES / sizeof LOOP_CODES[0]; i++)
        if (PyModule_AddIntConstant(m, LOOP_CODES[i].name, LOOP_CODES[i].value) < 0)
            return -1;
    if (PyModule_AddType(m, &PlantLockstepType) < 0
        || PyModule_AddType(m, &ControllerLockstepType) < 0)
        return -1;
    return 0;
}
