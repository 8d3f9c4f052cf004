/* Hot-path codec for the two per-period messages of docs/protocol.md (SensorSample,
 * CurrentCommand): one C call per message instead of a dozen CPython operations.
 *
 * On the lockstep loop both processes share one core, so every Python object created
 * between recv() and put() costs several times its warm CPU time (cold caches after each
 * process switch; docs/hil.md).  This module does the header check, the finiteness check
 * and the vector copy in one call and creates only the result (a small tuple or the
 * bytes to send).  bridge/protocol/wire.py holds the pure-Python twin with identical semantics;
 * tests/test_protocol.py checks both against the reference codec.  Further down: the two
 * flush encoders (pack_record_batch, pack_timing), and the module ambhil.bridge.protocol._wire
 * itself, which also holds the lockstep loops' ordinary steps (the types PlantLockstep and
 * ControllerLockstep with their LoopCode: _lockstep.h; their Python twins are the loops in
 * bridge/process/plant_lockstep.py and bridge/process/controller_node.py).
 *
 * The message layout and its check-and-copy core (shared with the loops) are in _wire.h, the
 * MAC's BLAKE2b in _blake2b.h.
 */
#include "_wire.h"
#include "_lockstep.h"

/* The seal of a 16- or 48-byte bytes object (_wire.h), from a small cache of the seals last
 * used: a process passes the same one or two seals with every message, and making one costs a
 * BLAKE2b compression (the key block), as much as the message's MAC itself.  The cache is
 * module state, used with the GIL held; the seal is copied out (88 bytes), so nothing the
 * caller does later can change it under it.  -1 with TypeError naming ``what`` otherwise. */
#define SEAL_CACHE 4
static struct {
    Py_ssize_t len;               /* 0: empty */
    char value[SEAL_LEN];
    wire_seal seal;
} seal_cache[SEAL_CACHE];
static int seal_next;

static int seal_get(PyObject *o, wire_seal *out, const char *name, const char *what)
{
    if (!PyBytes_Check(o) || !seal_size_ok(PyBytes_GET_SIZE(o))) {
        PyErr_Format(PyExc_TypeError, "%s(): %s must be a 16-byte peer id or a 48-byte seal "
                     "(id + key)", name, what);
        return -1;
    }
    Py_ssize_t n = PyBytes_GET_SIZE(o);
    const char *v = PyBytes_AS_STRING(o);
    int i = 0;
    while (i < SEAL_CACHE && !(seal_cache[i].len == n && memcmp(seal_cache[i].value, v, (size_t)n) == 0))
        i++;
    if (i == SEAL_CACHE) {
        i = seal_next;
        seal_next = (seal_next + 1) % SEAL_CACHE;
        seal_cache[i].len = n;
        memcpy(seal_cache[i].value, v, (size_t)n);
        seal_make(&seal_cache[i].seal, v, n);
    }
    *out = seal_cache[i].seal;
    return 0;
}

/* decode(data, expect_seq, out, peer_seal) -> (seq, step, sim_time_ns, t0[, t1]) or None.
 * None (``out`` untouched) when the message is not a well-formed, finite message for
 * len(out)/8 axes with sequence number expect_seq sealed by ``peer_seal`` (its id and a mac
 * valid under its key; a 16- or 48-byte seal, _wire.h): the caller's validating slow path
 * then classifies it.  ``out``: writable C-contiguous buffer of float64. */
static PyObject *decode_nt(PyObject *const *args, Py_ssize_t nargs, int nt, const char *name)
{
    if (nargs != 4) {
        PyErr_Format(PyExc_TypeError, "%s() takes 4 arguments (%zd given)", name, nargs);
        return NULL;
    }
    wire_seal peer;
    if (seal_get(args[3], &peer, name, "peer_seal") < 0)
        return NULL;
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
    if (!decode_raw((const char *)in.buf, in.len, nt, out.len / 8, expect, &peer, out.buf, &seq,
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

/* encode(vec, seq, step, sim_time_ns, t0[, t1], me_seal) -> bytes, or None if vec has a
 * non-finite value (nothing non-finite is ever sent).  ``vec``: C-contiguous float64;
 * ``me_seal``: the sender's seal (16 or 48 bytes): its id is written after the values, then
 * the mac under its key. */
static PyObject *encode_nt(PyObject *const *args, Py_ssize_t nargs, int nt, const char *name)
{
    if (nargs != 5 + nt) {
        PyErr_Format(PyExc_TypeError, "%s() takes %d arguments (%zd given)", name, 5 + nt, nargs);
        return NULL;
    }
    wire_seal me;
    if (seal_get(args[4 + nt], &me, name, "me_seal") < 0)
        return NULL;
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
        res = encode_raw((const char *)vec.buf, n, nt, seq, step, v, &me);
done:
    PyBuffer_Release(&vec);
    return res;
}

static PyObject *decode_sensor(PyObject *Py_UNUSED(m), PyObject *const *a, Py_ssize_t n)
{
    return decode_nt(a, n, 1, "decode_sensor");
}
static PyObject *decode_current(PyObject *Py_UNUSED(m), PyObject *const *a, Py_ssize_t n)
{
    return decode_nt(a, n, 2, "decode_current");
}
static PyObject *encode_sensor(PyObject *Py_UNUSED(m), PyObject *const *a, Py_ssize_t n)
{
    return encode_nt(a, n, 1, "encode_sensor");
}
static PyObject *encode_current(PyObject *Py_UNUSED(m), PyObject *const *a, Py_ssize_t n)
{
    return encode_nt(a, n, 2, "encode_current");
}

/* pack_record_batch(seq, version, sent, received) -> bytes: the RecordBatch of
 * bridge/record_batch.py (same bytes as its _pack/encode) in one call: ``sent`` is a list of
 * SensorSample payloads (log time = their publish_wall_ns, at offset 36), ``received`` a list
 * of (log_time_ns, payload) tuples.  The plant calls it every 10 ms on its loop thread, where
 * the numpy version costs several times its warm time on cold caches. */
static inline void put_u32(char *p, uint32_t v) { memcpy(p, &v, 4); }

static PyObject *pack_record_batch(PyObject *Py_UNUSED(m), PyObject *const *a, Py_ssize_t n)
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

static PyObject *pack_timing(PyObject *Py_UNUSED(m), PyObject *const *a, Py_ssize_t n)
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

/* blake2b(data, key, digest_size) -> bytes: the C BLAKE2b of _blake2b.h, for
 * tests/test_mac.py to compare with hashlib (key of 0..64 bytes, digest of 1..64). */
static PyObject *blake2b(PyObject *Py_UNUSED(m), PyObject *const *a, Py_ssize_t n)
{
    if (n != 3) {
        PyErr_SetString(PyExc_TypeError, "blake2b(data, key, digest_size)");
        return NULL;
    }
    long size = PyLong_AsLong(a[2]);
    if (size == -1 && PyErr_Occurred())
        return NULL;
    Py_buffer d, k;
    if (PyObject_GetBuffer(a[0], &d, PyBUF_SIMPLE) < 0)
        return NULL;
    if (PyObject_GetBuffer(a[1], &k, PyBUF_SIMPLE) < 0) {
        PyBuffer_Release(&d);
        return NULL;
    }
    PyObject *res = NULL;
    b2b_ctx c;
    uint8_t out[B2B_MAX_OUT];
    if (size < 1 || b2b_init(&c, (size_t)size, k.buf, (size_t)k.len) < 0) {
        PyErr_Format(PyExc_ValueError, "blake2b(): digest_size %ld (1..64) or key of %zd bytes "
                     "(0..64) out of range", size, k.len);
    } else {
        b2b_update(&c, d.buf, (size_t)d.len);
        b2b_final(&c, out);
        res = PyBytes_FromStringAndSize((const char *)out, size);
    }
    PyBuffer_Release(&k);
    PyBuffer_Release(&d);
    return res;
}

static PyMethodDef methods[] = {
    {"decode_sensor", (PyCFunction)(void (*)(void))decode_sensor, METH_FASTCALL,
     "decode_sensor(data, expect_seq, out, peer_seal) -> (seq, step, sim_time_ns, publish_wall_ns) | None"},
    {"decode_current", (PyCFunction)(void (*)(void))decode_current, METH_FASTCALL,
     "decode_current(data, expect_seq, out, peer_seal) -> (seq, step, sim_time_ns, recv_wall_ns, "
     "publish_wall_ns) | None"},
    {"encode_sensor", (PyCFunction)(void (*)(void))encode_sensor, METH_FASTCALL,
     "encode_sensor(vec, seq, step, sim_time_ns, publish_wall_ns, me_seal) -> bytes | None"},
    {"encode_current", (PyCFunction)(void (*)(void))encode_current, METH_FASTCALL,
     "encode_current(vec, seq, step, sim_time_ns, recv_wall_ns, publish_wall_ns, me_seal) -> bytes | None"},
    {"pack_timing", (PyCFunction)(void (*)(void))pack_timing, METH_FASTCALL,
     "pack_timing(seq, step, sim_time_ns, period_ns, overruns, lat, rtt, tet, flags) -> Timing bytes (cdr.py)"},
    {"pack_record_batch", (PyCFunction)(void (*)(void))pack_record_batch, METH_FASTCALL,
     "pack_record_batch(seq, version, sent, received) -> RecordBatch bytes (record_batch.py)"},
    {"blake2b", (PyCFunction)(void (*)(void))blake2b, METH_FASTCALL,
     "blake2b(data, key, digest_size) -> bytes: the fast path's keyed BLAKE2b (tests only)"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_wire",
                                    "Hot path of the loops: SensorSample/CurrentCommand codec, lockstep loops, flush encoders (see wire.py).",
                                    -1, methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__wire(void)
{
    const uint16_t one = 1;
    if (*(const unsigned char *)&one != 1) {   /* the layout above is little-endian */
        PyErr_SetString(PyExc_ImportError, "ambhil.bridge.protocol._wire supports little-endian hosts only");
        return NULL;
    }
    if (lockstep_ready() < 0)
        return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m == NULL)
        return NULL;
    if (lockstep_add(m) < 0)
        goto fail;
    return m;
fail:
    Py_DECREF(m);
    return NULL;
}
