/* Hot-path codec for the two per-period messages of docs/protocol.md (SensorSample,
 * CurrentCommand): one C call per message instead of a dozen CPython operations.
 *
 * On the lockstep loop both processes share one core, so every Python object created
 * between recv() and put() costs several times its warm CPU time (cold caches after each
 * process switch; docs/hil.md).  This module does the header check, the finiteness check
 * and the vector copy in one call and creates only the result (a small tuple or the
 * bytes to send).  bridge/wire.py holds the pure-Python twin with identical semantics;
 * tests/test_protocol.py checks both against the reference codec.
 *
 * Layout (little-endian, CDR_LE encapsulation 00 01 00 00, protocol version 1):
 *   0 encap[4]  4 version u16  6 pad[6]  12 seq u64  20 step u64  28 sim_time_ns i64
 *   36 times i64[nt]  36+8nt count u32  40+8nt pad[4]  44+8nt values f64[count]
 * nt = 1 for SensorSample (publish_wall_ns), 2 for CurrentCommand (recv, publish).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#define WIRE_VERSION 1
static const unsigned char ENCAP[4] = {0x00, 0x01, 0x00, 0x00};

static inline Py_ssize_t hdr_size(int nt) { return 44 + 8 * (Py_ssize_t)nt; }

static int all_finite(const char *p, Py_ssize_t n)
{
    for (Py_ssize_t i = 0; i < n; i++) {
        double x;
        memcpy(&x, p + 8 * i, 8);
        if (!isfinite(x))
            return 0;
    }
    return 1;
}

/* decode(data, expect_seq, out) -> (seq, step, sim_time_ns, t0[, t1]) or None.
 * None (``out`` untouched) when the message is not a well-formed, finite message for
 * len(out)/8 axes with sequence number expect_seq: the caller's validating slow path
 * then classifies it.  ``out``: writable C-contiguous buffer of float64. */
static PyObject *decode_nt(PyObject *const *args, Py_ssize_t nargs, int nt, const char *name)
{
    if (nargs != 3) {
        PyErr_Format(PyExc_TypeError, "%s() takes 3 arguments (%zd given)", name, nargs);
        return NULL;
    }
    unsigned long long expect = PyLong_AsUnsignedLongLongMask(args[1]);
    if (expect == (unsigned long long)-1 && PyErr_Occurred())
        return NULL;
    Py_buffer in, out;
    if (PyObject_GetBuffer(args[0], &in, PyBUF_SIMPLE) < 0)
        return NULL;
    if (PyObject_GetBuffer(args[2], &out, PyBUF_WRITABLE) < 0) {
        PyBuffer_Release(&in);
        return NULL;
    }
    PyObject *res = NULL;
    const char *p = (const char *)in.buf;
    Py_ssize_t n = out.len / 8, off = hdr_size(nt);
    uint16_t ver;
    uint32_t cnt;
    uint64_t seq, step;
    int64_t sim, t[2];
    if (out.len % 8 != 0) {
        PyErr_Format(PyExc_ValueError, "%s(): output buffer of %zd bytes is not float64", name,
                     out.len);
        goto done;
    }
    if (in.len != off + 8 * n || memcmp(p, ENCAP, 4) != 0)
        goto reject;
    memcpy(&ver, p + 4, 2);
    memcpy(&cnt, p + off - 8, 4);
    memcpy(&seq, p + 12, 8);
    if (ver != WIRE_VERSION || (Py_ssize_t)cnt != n || seq != expect || !all_finite(p + off, n))
        goto reject;
    memcpy(&step, p + 20, 8);
    memcpy(&sim, p + 28, 8);
    memcpy(t, p + 36, 8 * (size_t)nt);
    memcpy(out.buf, p + off, 8 * (size_t)n);
    res = PyTuple_New(3 + nt);
    if (res == NULL)
        goto done;
    PyTuple_SET_ITEM(res, 0, PyLong_FromUnsignedLongLong(seq));
    PyTuple_SET_ITEM(res, 1, PyLong_FromUnsignedLongLong(step));
    PyTuple_SET_ITEM(res, 2, PyLong_FromLongLong(sim));
    for (int i = 0; i < nt; i++)
        PyTuple_SET_ITEM(res, 3 + i, PyLong_FromLongLong(t[i]));
    for (int i = 0; i < 3 + nt; i++) {
        if (PyTuple_GET_ITEM(res, i) == NULL) {
            Py_CLEAR(res);
            goto done;
        }
    }
    goto done;
reject:
    res = Py_NewRef(Py_None);
done:
    PyBuffer_Release(&out);
    PyBuffer_Release(&in);
    return res;
}

/* encode(vec, seq, step, sim_time_ns, t0[, t1]) -> bytes, or None if vec has a
 * non-finite value (nothing non-finite is ever sent).  ``vec``: C-contiguous float64. */
static PyObject *encode_nt(PyObject *const *args, Py_ssize_t nargs, int nt, const char *name)
{
    if (nargs != 4 + nt) {
        PyErr_Format(PyExc_TypeError, "%s() takes %d arguments (%zd given)", name, 4 + nt, nargs);
        return NULL;
    }
    unsigned long long seq = PyLong_AsUnsignedLongLong(args[1]);
    if (seq == (unsigned long long)-1 && PyErr_Occurred())
        return NULL;
    unsigned long long step = PyLong_AsUnsignedLongLong(args[2]);
    if (step == (unsigned long long)-1 && PyErr_Occurred())
        return NULL;
    int64_t v[3];
    for (int i = 0; i < 1 + nt; i++) {
        long long x = PyLong_AsLongLong(args[3 + i]);
        if (x == -1 && PyErr_Occurred())
            return NULL;
        v[i] = (int64_t)x;
    }
    Py_buffer vec;
    if (PyObject_GetBuffer(args[0], &vec, PyBUF_SIMPLE) < 0)
        return NULL;
    PyObject *res = NULL;
    Py_ssize_t n = vec.len / 8, off = hdr_size(nt);
    if (vec.len % 8 != 0 || n == 0 || n > 0xFFFFFFFFLL) {
        PyErr_Format(PyExc_ValueError, "%s(): vector of %zd bytes is not a float64 vector",
                     name, vec.len);
        goto done;
    }
    if (!all_finite((const char *)vec.buf, n)) {
        res = Py_NewRef(Py_None);
        goto done;
    }
    res = PyBytes_FromStringAndSize(NULL, off + 8 * n);
    if (res == NULL)
        goto done;
    char *p = PyBytes_AS_STRING(res);
    uint16_t ver = WIRE_VERSION;
    uint32_t cnt = (uint32_t)n;
    uint64_t s = seq, st = step;
    memcpy(p, ENCAP, 4);
    memcpy(p + 4, &ver, 2);
    memset(p + 6, 0, 6);
    memcpy(p + 12, &s, 8);
    memcpy(p + 20, &st, 8);
    memcpy(p + 28, v, 8 * (size_t)(1 + nt));
    memcpy(p + off - 8, &cnt, 4);
    memset(p + off - 4, 0, 4);
    memcpy(p + off, vec.buf, 8 * (size_t)n);
done:
    PyBuffer_Release(&vec);
    return res;
}

static PyObject *decode_sensor(PyObject *m, PyObject *const *a, Py_ssize_t n)
{
    return decode_nt(a, n, 1, "decode_sensor");
}
static PyObject *decode_current(PyObject *m, PyObject *const *a, Py_ssize_t n)
{
    return decode_nt(a, n, 2, "decode_current");
}
static PyObject *encode_sensor(PyObject *m, PyObject *const *a, Py_ssize_t n)
{
    return encode_nt(a, n, 1, "encode_sensor");
}
static PyObject *encode_current(PyObject *m, PyObject *const *a, Py_ssize_t n)
{
    return encode_nt(a, n, 2, "encode_current");
}

static PyMethodDef methods[] = {
    {"decode_sensor", (PyCFunction)(void (*)(void))decode_sensor, METH_FASTCALL,
     "decode_sensor(data, expect_seq, out) -> (seq, step, sim_time_ns, publish_wall_ns) | None"},
    {"decode_current", (PyCFunction)(void (*)(void))decode_current, METH_FASTCALL,
     "decode_current(data, expect_seq, out) -> (seq, step, sim_time_ns, recv_wall_ns, "
     "publish_wall_ns) | None"},
    {"encode_sensor", (PyCFunction)(void (*)(void))encode_sensor, METH_FASTCALL,
     "encode_sensor(vec, seq, step, sim_time_ns, publish_wall_ns) -> bytes | None"},
    {"encode_current", (PyCFunction)(void (*)(void))encode_current, METH_FASTCALL,
     "encode_current(vec, seq, step, sim_time_ns, recv_wall_ns, publish_wall_ns) -> bytes | None"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_wire",
                                    "Hot-path SensorSample/CurrentCommand codec (see wire.py).",
                                    -1, methods};

PyMODINIT_FUNC PyInit__wire(void)
{
    const uint16_t one = 1;
    if (*(const unsigned char *)&one != 1) {   /* the layout above is little-endian */
        PyErr_SetString(PyExc_ImportError, "bridge._wire supports little-endian hosts only");
        return NULL;
    }
    return PyModule_Create(&module);
}
