/* Hot-path codec for the two per-period messages of docs/protocol.md (SensorSample,
 * CurrentCommand): one C call per message instead of a dozen CPython operations.
 *
 * On the lockstep loop both processes share one core, so every Python object created
 * between recv() and put() costs several times its warm CPU time (cold caches after each
 * process switch; docs/hil.md).  This module does the header check, the finiteness check
 * and the vector copy in one call and creates only the result (a small tuple or the
 * bytes to send).  bridge/wire.py holds the pure-Python twin with identical semantics;
 * tests/test_protocol.py checks both against the reference codec.  Further down: the
 * lockstep loops' ordinary steps (plant_lockstep, controller_lockstep; their Python twins
 * are the loops in bridge/plant_loops.py and bridge/controller_node.py), and the two
 * flush encoders (pack_record_batch, pack_timing).
 *
 * Layout (little-endian, CDR_LE encapsulation 00 01 00 00, protocol version 2):
 *   0 encap[4]  4 version u16  6 pad[6]  12 seq u64  20 step u64  28 sim_time_ns i64
 *   36 times i64[nt]  36+8nt count u32  40+8nt pad[4]  44+8nt values f64[count]
 *   44+8nt+8count peer u8[16] (the sender's peer id, docs/protocol.md 5.1)
 * nt = 1 for SensorSample (publish_wall_ns), 2 for CurrentCommand (recv, publish).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#define WIRE_VERSION 2
#define PEER_LEN 16
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

/* The fast-path check and copy of one message: 1 (``out`` filled with the n values, the
 * header fields in seq/step/sim/t) if ``p``/``len`` is a well-formed, finite message for n
 * axes with sequence number ``expect`` sent by ``peer``; else 0 (``out`` untouched). */
static int decode_raw(const char *p, Py_ssize_t len, int nt, Py_ssize_t n, uint64_t expect,
                      const char *peer, char *out, uint64_t *seq, uint64_t *step, int64_t *sim,
                      int64_t *t)
{
    Py_ssize_t off = hdr_size(nt);
    uint16_t ver;
    uint32_t cnt;
    if (len != off + 8 * n + PEER_LEN || memcmp(p, ENCAP, 4) != 0
        || memcmp(p + off + 8 * n, peer, PEER_LEN) != 0)
        return 0;
    memcpy(&ver, p + 4, 2);
    memcpy(&cnt, p + off - 8, 4);
    memcpy(seq, p + 12, 8);
    if (ver != WIRE_VERSION || (Py_ssize_t)cnt != n || *seq != expect || !all_finite(p + off, n))
        return 0;
    memcpy(step, p + 20, 8);
    memcpy(sim, p + 28, 8);
    memcpy(t, p + 36, 8 * (size_t)nt);
    memcpy(out, p + off, 8 * (size_t)n);
    return 1;
}

/* decode(data, expect_seq, out, peer) -> (seq, step, sim_time_ns, t0[, t1]) or None.
 * None (``out`` untouched) when the message is not a well-formed, finite message for
 * len(out)/8 axes with sequence number expect_seq sent by ``peer`` (16 bytes): the
 * caller's validating slow path then classifies it.  ``out``: writable C-contiguous
 * buffer of float64. */
static PyObject *decode_nt(PyObject *const *args, Py_ssize_t nargs, int nt, const char *name)
{
    if (nargs != 4) {
        PyErr_Format(PyExc_TypeError, "%s() takes 4 arguments (%zd given)", name, nargs);
        return NULL;
    }
    if (!PyBytes_Check(args[3]) || PyBytes_GET_SIZE(args[3]) != PEER_LEN) {
        PyErr_Format(PyExc_TypeError, "%s(): peer must be %d bytes", name, PEER_LEN);
        return NULL;
    }
    const char *peer = PyBytes_AS_STRING(args[3]);
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
    uint64_t seq, step;
    int64_t sim, t[2];
    if (out.len % 8 != 0) {
        PyErr_Format(PyExc_ValueError, "%s(): output buffer of %zd bytes is not float64", name,
                     out.len);
        goto done;
    }
    if (!decode_raw((const char *)in.buf, in.len, nt, out.len / 8, expect, peer, out.buf, &seq,
                    &step, &sim, t)) {
        res = Py_NewRef(Py_None);
        goto done;
    }
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
done:
    PyBuffer_Release(&out);
    PyBuffer_Release(&in);
    return res;
}

/* The message bytes for the n float64 values at ``vec`` (caller has checked them finite),
 * header values v = (sim_time_ns, t0[, t1]), sender id ``me`` (16 bytes); NULL on memory error. */
static PyObject *encode_raw(const char *vec, Py_ssize_t n, int nt, uint64_t seq, uint64_t step,
                            const int64_t *v, const char *me)
{
    Py_ssize_t off = hdr_size(nt);
    PyObject *res = PyBytes_FromStringAndSize(NULL, off + 8 * n + PEER_LEN);
    if (res == NULL)
        return NULL;
    char *p = PyBytes_AS_STRING(res);
    uint16_t ver = WIRE_VERSION;
    uint32_t cnt = (uint32_t)n;
    memcpy(p, ENCAP, 4);
    memcpy(p + 4, &ver, 2);
    memset(p + 6, 0, 6);
    memcpy(p + 12, &seq, 8);
    memcpy(p + 20, &step, 8);
    memcpy(p + 28, v, 8 * (size_t)(1 + nt));
    memcpy(p + off - 8, &cnt, 4);
    memset(p + off - 4, 0, 4);
    memcpy(p + off, vec, 8 * (size_t)n);
    memcpy(p + off + 8 * n, me, PEER_LEN);
    return res;
}

/* encode(vec, seq, step, sim_time_ns, t0[, t1], me) -> bytes, or None if vec has a
 * non-finite value (nothing non-finite is ever sent).  ``vec``: C-contiguous float64;
 * ``me``: the sender's 16-byte peer id, written after the values. */
static PyObject *encode_nt(PyObject *const *args, Py_ssize_t nargs, int nt, const char *name)
{
    if (nargs != 5 + nt) {
        PyErr_Format(PyExc_TypeError, "%s() takes %d arguments (%zd given)", name, 5 + nt, nargs);
        return NULL;
    }
    PyObject *me = args[4 + nt];
    if (!PyBytes_Check(me) || PyBytes_GET_SIZE(me) != PEER_LEN) {
        PyErr_Format(PyExc_TypeError, "%s(): the sender id must be %d bytes", name, PEER_LEN);
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
    Py_ssize_t n = vec.len / 8;
    if (vec.len % 8 != 0 || n == 0 || n > 0xFFFFFFFFLL) {
        PyErr_Format(PyExc_ValueError, "%s(): vector of %zd bytes is not a float64 vector",
                     name, vec.len);
        goto done;
    }
    if (!all_finite((const char *)vec.buf, n))
        res = Py_NewRef(Py_None);
    else
        res = encode_raw((const char *)vec.buf, n, nt, seq, step, v, PyBytes_AS_STRING(me));
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

/* pack_record_batch(seq, version, sent, received) -> bytes: the RecordBatch of
 * bridge/record_batch.py (same bytes as its _pack/encode) in one call: ``sent`` is a list of
 * SensorSample payloads (log time = their publish_wall_ns, at offset 36), ``received`` a list
 * of (log_time_ns, payload) tuples.  The plant calls it every 10 ms on its loop thread, where
 * the numpy version costs several times its warm time on cold caches. */
static inline void put_u32(char *p, uint32_t v) { memcpy(p, &v, 4); }

static PyObject *pack_record_batch(PyObject *m, PyObject *const *a, Py_ssize_t n)
{
    if (n != 4 || !PyList_Check(a[2]) || !PyList_Check(a[3])) {
        PyErr_SetString(PyExc_TypeError, "pack_record_batch(seq, version, sent: list, received: list)");
        return NULL;
    }
    unsigned long long seq = PyLong_AsUnsignedLongLong(a[0]);
    long version = PyLong_AsLong(a[1]);
    if (PyErr_Occurred())
        return NULL;
    PyObject *sent = a[2], *recv = a[3];
    Py_ssize_t ns = PyList_GET_SIZE(sent), nc = PyList_GET_SIZE(recv), N = ns + nc, D = 0;
    for (Py_ssize_t i = 0; i < ns; i++) {
        PyObject *b = PyList_GET_ITEM(sent, i);
        if (!PyBytes_Check(b) || PyBytes_GET_SIZE(b) < 44) {
            PyErr_Format(PyExc_ValueError, "RecordBatch: sent message %zd is not a SensorSample", i);
            return NULL;
        }
        D += PyBytes_GET_SIZE(b);
    }
    for (Py_ssize_t i = 0; i < nc; i++) {
        PyObject *t = PyList_GET_ITEM(recv, i);
        if (!PyTuple_Check(t) || PyTuple_GET_SIZE(t) != 2 || !PyBytes_Check(PyTuple_GET_ITEM(t, 1))) {
            PyErr_Format(PyExc_ValueError, "RecordBatch: received item %zd is not (log_time_ns, bytes)", i);
            return NULL;
        }
        D += PyBytes_GET_SIZE(PyTuple_GET_ITEM(t, 1));
    }
    if (N > 0xFFFFFFFFLL || D > 0xFFFFFFFFLL) {
        PyErr_SetString(PyExc_OverflowError, "RecordBatch too large");
        return NULL;
    }
    /* offsets: CDR body starts at 4; arrays align to their item size relative to it */
    Py_ssize_t p_log = N ? 44 : 40;
    Py_ssize_t p_nt = p_log + 8 * N;                 /* u32 count of topics */
    Py_ssize_t p_top = p_nt + 4;
    Py_ssize_t p_after = p_top + N;
    Py_ssize_t pad = (4 - ((p_after - 4) % 4)) % 4;
    Py_ssize_t p_nsz = p_after + pad;
    Py_ssize_t p_sz = p_nsz + 4;
    Py_ssize_t p_nd = p_sz + 4 * N;
    Py_ssize_t p_data = p_nd + 4;
    PyObject *out = PyBytes_FromStringAndSize(NULL, p_data + D);
    if (out == NULL)
        return NULL;
    char *o = PyBytes_AS_STRING(out);
    memset(o, 0, p_log);
    memcpy(o, ENCAP, 4);
    uint16_t v16 = (uint16_t)version;
    memcpy(o + 4, &v16, 2);
    memcpy(o + 12, &seq, 8);
    if (ns) {                                        /* step and sim time of the first sample */
        memcpy(o + 20, PyBytes_AS_STRING(PyList_GET_ITEM(sent, 0)) + 20, 16);
    }
    put_u32(o + 36, (uint32_t)N);
    memset(o + p_after, 0, pad);
    put_u32(o + p_nt, (uint32_t)N);
    put_u32(o + p_nsz, (uint32_t)N);
    put_u32(o + p_nd, (uint32_t)D);
    char *d = o + p_data;
    for (Py_ssize_t i = 0; i < ns; i++) {
        PyObject *b = PyList_GET_ITEM(sent, i);
        const char *src = PyBytes_AS_STRING(b);
        uint32_t sz = (uint32_t)PyBytes_GET_SIZE(b);
        memcpy(o + p_log + 8 * i, src + 36, 8);      /* publish_wall_ns */
        o[p_top + i] = 0;
        put_u32(o + p_sz + 4 * i, sz);
        memcpy(d, src, sz);
        d += sz;
    }
    for (Py_ssize_t i = 0; i < nc; i++) {
        PyObject *t = PyList_GET_ITEM(recv, i);
        long long lg = PyLong_AsLongLong(PyTuple_GET_ITEM(t, 0));
        if (lg == -1 && PyErr_Occurred()) {
            Py_DECREF(out);
            return NULL;
        }
        PyObject *b = PyTuple_GET_ITEM(t, 1);
        uint32_t sz = (uint32_t)PyBytes_GET_SIZE(b);
        Py_ssize_t j = ns + i;
        memcpy(o + p_log + 8 * j, &lg, 8);
        o[p_top + j] = 1;
        put_u32(o + p_sz + 4 * j, sz);
        memcpy(d, PyBytes_AS_STRING(b), sz);
        d += sz;
    }
    return out;
}

/* pack_timing(seq, step, sim_time_ns, period_ns, overruns, lat, rtt, tet, flags) -> bytes:
 * the Timing message of bridge/cdr.py encode_timing (same bytes), the arrays given as
 * contiguous int64 / uint8 buffers (slices of the plant's per-step arrays). */
static Py_ssize_t align_to(char *o, Py_ssize_t p, Py_ssize_t k)
{
    Py_ssize_t body = p - 4, pad = (k - body % k) % k;
    if (o)
        memset(o + p, 0, pad);
    return p + pad;
}

static PyObject *pack_timing(PyObject *m, PyObject *const *a, Py_ssize_t n)
{
    if (n != 9) {
        PyErr_SetString(PyExc_TypeError, "pack_timing(seq, step, sim_time_ns, period_ns, overruns, "
                                         "lat, rtt, tet, flags)");
        return NULL;
    }
    unsigned long long seq = PyLong_AsUnsignedLongLong(a[0]), step = PyLong_AsUnsignedLongLong(a[1]);
    long long sim = PyLong_AsLongLong(a[2]), per = PyLong_AsLongLong(a[3]);
    unsigned long long ovr = PyLong_AsUnsignedLongLong(a[4]);
    if (PyErr_Occurred())
        return NULL;
    Py_buffer b[4];
    int got = 0;
    PyObject *out = NULL;
    for (; got < 4; got++)
        if (PyObject_GetBuffer(a[5 + got], &b[got], PyBUF_C_CONTIGUOUS) < 0)
            goto done;
    Py_ssize_t cnt = b[3].len;
    for (int i = 0; i < 3; i++)
        if (b[i].len != 8 * cnt) {
            PyErr_SetString(PyExc_ValueError, "Timing arrays must have equal length");
            goto done;
        }
    /* size: header to overruns = 4 + 48, then 3 x (u32 + [pad] + 8 cnt), u32 + cnt */
    Py_ssize_t p = 52;
    for (int i = 0; i < 3; i++) {
        p += 4;
        if (cnt)
            p = align_to(NULL, p, 8);
        p += 8 * cnt;
    }
    p += 4 + cnt;
    out = PyBytes_FromStringAndSize(NULL, p);
    if (out == NULL)
        goto done;
    char *o = PyBytes_AS_STRING(out);
    memset(o, 0, 12);
    memcpy(o, ENCAP, 4);
    uint16_t v16 = WIRE_VERSION;
    memcpy(o + 4, &v16, 2);
    memcpy(o + 12, &seq, 8);
    memcpy(o + 20, &step, 8);
    memcpy(o + 28, &sim, 8);
    memcpy(o + 36, &per, 8);
    memcpy(o + 44, &ovr, 8);
    p = 52;
    uint32_t c32 = (uint32_t)cnt;
    for (int i = 0; i < 3; i++) {
        memcpy(o + p, &c32, 4);
        p += 4;
        if (cnt)
            p = align_to(o, p, 8);
        memcpy(o + p, b[i].buf, 8 * cnt);
        p += 8 * cnt;
    }
    memcpy(o + p, &c32, 4);
    memcpy(o + p + 4, b[3].buf, cnt);
done:
    for (int i = 0; i < got; i++)
        PyBuffer_Release(&b[i]);
    return out;
}

/* ---- the lockstep loop's fast path: consecutive ordinary steps in one C call ----
 *
 * bridge/plant_loops.py (plant) and bridge/controller_node.py (controller) run their
 * lockstep loops through these when the extension is built: every step whose message is
 * the fast-path one (decode above succeeds) and whose step object behaves as before runs
 * here without a Python bytecode of the loop's own; anything else returns to the Python
 * loop, which handles it exactly as its own fast path would have.  Same calls, same order,
 * same stamps as the Python loops (put, list appends, recv().payload.to_bytes(), advance or
 * step, time.time_ns()); progress is written to ``st`` after each step, so an exception
 * raised by put/recv leaves the caller's bookkeeping exact. */
#include <time.h>

static PyObject *s_step_index, *s_status, *s_payload, *s_to_bytes;

static inline int64_t wall_ns(void)   /* time.time_ns() */
{
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

/* recv().payload.to_bytes() */
static PyObject *recv_bytes(PyObject *recv)
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

/* fn(arg) with the result dropped; -1 on error */
static inline int call1(PyObject *fn, PyObject *arg)
{
    PyObject *r = PyObject_CallOneArg(fn, arg);
    if (r == NULL)
        return -1;
    Py_DECREF(r);
    return 0;
}

static inline int set_mark(PyObject *wmark, long long v)   /* wmark[0] = v */
{
    PyObject *o = PyLong_FromLongLong(v);
    return o == NULL ? -1 : PyList_SetItem(wmark, 0, o);
}

/* The pending exception as an object if it is an Exception (the caller turns it into a
 * fault naming the step), else NULL with it still set (KeyboardInterrupt, SystemExit). */
static PyObject *take_exception(void)
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

enum { L_DONE = 0, L_SLOW = 1, L_FLUSH = 2, L_CHECK = 3, L_RAISED = 4, L_NONFINITE = 5 };

static int get_buffers(PyObject *const *objs, Py_buffer *b, int nb, const int *writable)
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

/* plant_lockstep(y_mv, y_obj, rx_mv, u, advance, plant, has_status, put, recv, sent,
 *                received, rtt, tet, st, wmark, me, peer, period_ns, k, k_end, next_flush,
 *                rb_due) -> (code, k, a, b)
 *
 * Steps k, k+1, ... of bridge/plant_loops.lockstep while they are ordinary: publish sample k
 * (encoded from y_mv, stamped, put, appended to ``sent``), receive the reply to k from the
 * paired controller (into rx_mv; (t1, data) appended to ``received``; rtt[k] and tet[k]
 * stored), ``advance(u)``.  ``st`` (int64[2]) gets (steps done, sim_time_ns of the last
 * step begun) as it goes.  Returns
 *   (0, k_end, None, None)  all steps done
 *   (1, k, t0, data)        sample k sent, ``data`` is not its fast-path reply
 *   (2, k + 1, t1, None)    step k done, a flush is due (k + 1 >= next_flush or t1 >= rb_due)
 *   (3, k, y, t1)           step k advanced, its output needs the caller's check (a new object,
 *                           or a status set)
 *   (4, k, exc, None)       advance raised ``exc`` at step k
 *   (5, k, None, None)      y_mv is not finite at step k (nothing sent) */
static PyObject *plant_lockstep(PyObject *m, PyObject *const *a, Py_ssize_t na)
{
    (void)m;
    if (na != 22 || !PyList_Check(a[9]) || !PyList_Check(a[10]) || !PyList_Check(a[14])
        || !PyBytes_Check(a[15]) || PyBytes_GET_SIZE(a[15]) != PEER_LEN
        || !PyBytes_Check(a[16]) || PyBytes_GET_SIZE(a[16]) != PEER_LEN) {
        PyErr_SetString(PyExc_TypeError, "plant_lockstep(y_mv, y_obj, rx_mv, u, advance, plant, "
                        "has_status, put, recv, sent: list, received: list, rtt, tet, st, "
                        "wmark: list, me: bytes16, peer: bytes16, period_ns, k, k_end, "
                        "next_flush, rb_due)");
        return NULL;
    }
    PyObject *y_obj = a[1], *u = a[3], *advance = a[4], *plant = a[5], *put = a[7],
             *recv = a[8], *sent = a[9], *received = a[10], *wmark = a[14];
    int has_status = PyObject_IsTrue(a[6]);
    const char *me = PyBytes_AS_STRING(a[15]), *peer = PyBytes_AS_STRING(a[16]);
    long long period = PyLong_AsLongLong(a[17]), k = PyLong_AsLongLong(a[18]),
              k_end = PyLong_AsLongLong(a[19]), next_flush = PyLong_AsLongLong(a[20]),
              rb_due = PyLong_AsLongLong(a[21]);
    if (has_status < 0 || PyErr_Occurred())
        return NULL;
    PyObject *bobj[5] = {a[0], a[2], a[11], a[12], a[13]};
    const int wr[5] = {0, 1, 1, 1, 1};
    Py_buffer b[5];
    if (get_buffers(bobj, b, 5, wr) < 0)
        return NULL;
    PyObject *res = NULL;
    Py_ssize_t n = b[0].len / 8;
    int64_t *rtt = (int64_t *)b[2].buf, *tet = (int64_t *)b[3].buf, *st = (int64_t *)b[4].buf;
    if (b[0].len % 8 || b[1].len != b[0].len || n == 0 || b[2].len < 8 * k_end
        || b[3].len < 8 * k_end || b[4].len < 16 || k < 0) {
        PyErr_SetString(PyExc_ValueError, "plant_lockstep: buffer sizes do not match");
        goto done;
    }
    for (; k < k_end; k++) {
        if (PyErr_CheckSignals() < 0)
            goto done;
        PyObject *o = PyObject_GetAttr(plant, s_step_index);
        if (o == NULL)
            goto done;
        long long step_i = PyLong_AsLongLong(o);
        Py_DECREF(o);
        if (step_i == -1 && PyErr_Occurred())
            goto done;
        int64_t v[2] = {step_i * period, 0};
        st[1] = v[0];
        if (set_mark(wmark, k) < 0)
            goto done;
        int64_t t0 = v[1] = wall_ns();           /* publish stamp and round-trip start */
        if (!all_finite((const char *)b[0].buf, n)) {
            res = Py_BuildValue("(iLOO)", L_NONFINITE, k, Py_None, Py_None);
            goto done;
        }
        PyObject *msg = encode_raw((const char *)b[0].buf, n, 1, (uint64_t)k, (uint64_t)step_i,
                                   v, me);
        if (msg == NULL)
            goto done;
        if (call1(put, msg) < 0 || PyList_Append(sent, msg) < 0) {
            Py_DECREF(msg);
            goto done;
        }
        Py_DECREF(msg);
        PyObject *data = recv_bytes(recv);
        if (data == NULL)
            goto done;
        uint64_t seq, step;
        int64_t sim, t[2];
        if (!decode_raw(PyBytes_AS_STRING(data), PyBytes_GET_SIZE(data), 2, n, (uint64_t)k,
                        peer, b[1].buf, &seq, &step, &sim, t)) {
            res = Py_BuildValue("(iLLN)", L_SLOW, k, (long long)t0, data);
            goto done;
        }
        int64_t t1 = wall_ns();
        PyObject *kept = Py_BuildValue("(LN)", (long long)t1, data);
        if (kept == NULL || PyList_Append(received, kept) < 0) {
            Py_XDECREF(kept);
            goto done;
        }
        Py_DECREF(kept);
        rtt[k] = t1 - t0;
        tet[k] = t[1] - t[0];                    /* the controller's publish - receive stamps */
        PyObject *y = PyObject_CallOneArg(advance, u);
        if (y == NULL) {
            PyObject *e = take_exception();
            if (e != NULL)
                res = Py_BuildValue("(iLNO)", L_RAISED, k, e, Py_None);
            goto done;
        }
        int check = y != y_obj;
        if (!check && has_status) {
            PyObject *s = PyObject_GetAttr(plant, s_status);
            if (s == NULL) {
                Py_DECREF(y);
                goto done;
            }
            check = PyObject_IsTrue(s);
            Py_DECREF(s);
            if (check < 0) {
                Py_DECREF(y);
                goto done;
            }
        }
        if (check) {
            res = Py_BuildValue("(iLNL)", L_CHECK, k, y, (long long)t1);
            goto done;
        }
        Py_DECREF(y);
        st[0] = k + 1;
        if (k + 1 >= next_flush || t1 >= rb_due) {
            res = Py_BuildValue("(iLLO)", L_FLUSH, k + 1, (long long)t1, Py_None);
            goto done;
        }
    }
    res = Py_BuildValue("(iLOO)", L_DONE, k_end, Py_None, Py_None);
done:
    for (int i = 0; i < 5; i++)
        PyBuffer_Release(&b[i]);
    return res;
}

/* controller_lockstep(recv, put, y_mv, y_in, step, c_obj, c_mv, me, peer, wmark,
 *                     restarts, st) -> (code, a, b, c)
 *
 * The controller's side of bridge/controller_node.py's loop: receive sample last_seq + 1
 * (st[0]) from the paired plant into y_mv, ``c = step(y_in)``, encode c_mv stamped with the
 * receive and publish times, put; st = (last_seq, steps) after each reply sent, wmark[0] =
 * steps.  Returns to the caller (which handles the message as its own loop would) on
 *   (1, data, t_rx, None)   a message that is not the next fast-path sample, or a sample
 *                           at or past restarts[0] (the list the caller's event callback
 *                           appends scheduled restarts to): not acted on here
 *   (3, c, h, t_rx)         step() returned another object than c_obj (h: the decoded
 *                           (seq, step, sim_time_ns, publish_wall_ns); st[0] = seq)
 *   (4, exc, h, None)       step() raised ValueError or TypeError (st[0] = seq)
 *   (5, h, t_rx, None)      c_mv not finite (nothing sent; st[0] = seq) */
static PyObject *controller_lockstep(PyObject *m, PyObject *const *a, Py_ssize_t na)
{
    (void)m;
    if (na != 12 || !PyBytes_Check(a[7]) || PyBytes_GET_SIZE(a[7]) != PEER_LEN
        || !PyBytes_Check(a[8]) || PyBytes_GET_SIZE(a[8]) != PEER_LEN || !PyList_Check(a[9])
        || !PyList_Check(a[10])) {
        PyErr_SetString(PyExc_TypeError, "controller_lockstep(recv, put, y_mv, y_in, step, c_obj, "
                        "c_mv, me: bytes16, peer: bytes16, wmark: list, restarts: list, st)");
        return NULL;
    }
    PyObject *recv = a[0], *put = a[1], *y_in = a[3], *step_fn = a[4], *c_obj = a[5],
             *wmark = a[9], *restarts = a[10];
    const char *me = PyBytes_AS_STRING(a[7]), *peer = PyBytes_AS_STRING(a[8]);
    PyObject *bobj[3] = {a[2], a[6], a[11]};
    const int wr[3] = {1, 0, 1};
    Py_buffer b[3];
    if (get_buffers(bobj, b, 3, wr) < 0)
        return NULL;
    PyObject *res = NULL;
    Py_ssize_t n = b[0].len / 8, nc = b[1].len / 8;
    int64_t *st = (int64_t *)b[2].buf;
    if (b[0].len % 8 || b[1].len % 8 || n == 0 || nc == 0 || b[2].len < 16) {
        PyErr_SetString(PyExc_ValueError, "controller_lockstep: buffer sizes do not match");
        goto done;
    }
    for (;;) {
        if (PyErr_CheckSignals() < 0)
            goto done;
        PyObject *data = recv_bytes(recv);
        if (data == NULL)
            goto done;
        int64_t t_rx = wall_ns();
        uint64_t seq, step;
        int64_t sim, t[2];
        int restart = 0;
        int ok = decode_raw(PyBytes_AS_STRING(data), PyBytes_GET_SIZE(data), 1, n,
                            (uint64_t)(st[0] + 1), peer, b[0].buf, &seq, &step, &sim, t);
        if (ok && PyList_GET_SIZE(restarts) > 0) {   /* appended by a zenoh callback thread */
            long long r0 = PyLong_AsLongLong(PyList_GET_ITEM(restarts, 0));
            if (r0 == -1 && PyErr_Occurred()) {
                Py_DECREF(data);
                goto done;
            }
            restart = r0 <= (long long)step;
        }
        if (!ok || restart) {
            res = Py_BuildValue("(iNLO)", L_SLOW, data, (long long)t_rx, Py_None);
            goto done;
        }
        Py_DECREF(data);
        st[0] = (int64_t)seq;
        PyObject *c = PyObject_CallOneArg(step_fn, y_in), *e = NULL;
        if (c == NULL || c != c_obj) {
            if (c == NULL) {     /* ValueError / TypeError: the caller's fault; others propagate */
                if (!PyErr_ExceptionMatches(PyExc_ValueError)
                    && !PyErr_ExceptionMatches(PyExc_TypeError))
                    goto done;
                if ((e = take_exception()) == NULL)
                    goto done;
            }
            PyObject *h = Py_BuildValue("(KKLL)", (unsigned long long)seq,
                                        (unsigned long long)step, (long long)sim, (long long)t[0]);
            if (h == NULL) {
                Py_XDECREF(c);
                Py_XDECREF(e);
                goto done;
            }
            if (c != NULL)
                res = Py_BuildValue("(iNNL)", L_CHECK, c, h, (long long)t_rx);
            else
                res = Py_BuildValue("(iNNO)", L_RAISED, e, h, Py_None);
            goto done;
        }
        Py_DECREF(c);
        if (!all_finite((const char *)b[1].buf, nc)) {
            res = Py_BuildValue("(i(KKLL)LO)", L_NONFINITE, (unsigned long long)seq,
                                (unsigned long long)step, (long long)sim, (long long)t[0],
                                (long long)t_rx, Py_None);
            goto done;
        }
        int64_t v[3] = {sim, t_rx, wall_ns()};
        PyObject *msg = encode_raw((const char *)b[1].buf, nc, 2, seq, step, v, me);
        if (msg == NULL)
            goto done;
        int r = call1(put, msg);
        Py_DECREF(msg);
        if (r < 0)
            goto done;
        st[1] += 1;
        if (set_mark(wmark, st[1]) < 0)
            goto done;
    }
done:
    for (int i = 0; i < 3; i++)
        PyBuffer_Release(&b[i]);
    return res;
}

static PyMethodDef methods[] = {
    {"decode_sensor", (PyCFunction)(void (*)(void))decode_sensor, METH_FASTCALL,
     "decode_sensor(data, expect_seq, out, peer) -> (seq, step, sim_time_ns, publish_wall_ns) | None"},
    {"decode_current", (PyCFunction)(void (*)(void))decode_current, METH_FASTCALL,
     "decode_current(data, expect_seq, out, peer) -> (seq, step, sim_time_ns, recv_wall_ns, "
     "publish_wall_ns) | None"},
    {"encode_sensor", (PyCFunction)(void (*)(void))encode_sensor, METH_FASTCALL,
     "encode_sensor(vec, seq, step, sim_time_ns, publish_wall_ns, me) -> bytes | None"},
    {"encode_current", (PyCFunction)(void (*)(void))encode_current, METH_FASTCALL,
     "encode_current(vec, seq, step, sim_time_ns, recv_wall_ns, publish_wall_ns, me) -> bytes | None"},
    {"pack_timing", (PyCFunction)(void (*)(void))pack_timing, METH_FASTCALL,
     "pack_timing(seq, step, sim_time_ns, period_ns, overruns, lat, rtt, tet, flags) -> Timing bytes (cdr.py)"},
    {"pack_record_batch", (PyCFunction)(void (*)(void))pack_record_batch, METH_FASTCALL,
     "pack_record_batch(seq, version, sent, received) -> RecordBatch bytes (record_batch.py)"},
    {"plant_lockstep", (PyCFunction)(void (*)(void))plant_lockstep, METH_FASTCALL,
     "plant_lockstep(...) -> (code, k, a, b): ordinary lockstep steps of the plant (see _wire.c)"},
    {"controller_lockstep", (PyCFunction)(void (*)(void))controller_lockstep, METH_FASTCALL,
     "controller_lockstep(...) -> (code, a, b, c): ordinary lockstep replies of the controller"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_wire",
                                    "Hot path of the loops: SensorSample/CurrentCommand codec, lockstep loops, flush encoders (see wire.py).",
                                    -1, methods};

PyMODINIT_FUNC PyInit__wire(void)
{
    const uint16_t one = 1;
    if (*(const unsigned char *)&one != 1) {   /* the layout above is little-endian */
        PyErr_SetString(PyExc_ImportError, "ambhil.bridge.protocol._wire supports little-endian hosts only");
        return NULL;
    }
    s_step_index = PyUnicode_InternFromString("step_index");
    s_status = PyUnicode_InternFromString("status");
    s_payload = PyUnicode_InternFromString("payload");
    s_to_bytes = PyUnicode_InternFromString("to_bytes");
    if (!s_step_index || !s_status || !s_payload || !s_to_bytes)
        return NULL;
    return PyModule_Create(&module);
}
