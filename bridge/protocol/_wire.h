/* The SensorSample / CurrentCommand message as both halves of the extension
 * ambhil.bridge.protocol._wire see it: the codec (_wire.c) and the lockstep loops (_lockstep.h)
 * check, copy and build messages with the functions below.  They are static inline here so
 * that the loops' per-message calls compile as they did when the codec and the loops were
 * one file (-O2, the compiler's own inlining choice).
 *
 * Layout (little-endian, CDR_LE encapsulation 00 01 00 00, protocol version 3):
 *   0 encap[4]  4 version u16  6 pad[6]  12 seq u64  20 step u64  28 sim_time_ns i64
 *   36 times i64[nt]  36+8nt count u32  40+8nt pad[4]  44+8nt values f64[count]
 *   44+8nt+8count peer u8[16] (the sender's peer id, docs/protocol.md 5.1)
 *   60+8nt+8count mac u8[16] (keyed BLAKE2b-128 of every byte before it, docs/protocol.md 5.3)
 * nt = 1 for SensorSample (publish_wall_ns), 2 for CurrentCommand (recv, publish).
 *
 * A *seal* names a sender and the key of its messages' MAC: 48 bytes = peer id (16) || topic
 * key (32) (bridge/protocol/auth.py RunAuth.seal / peer_seal); a 16-byte value is that id with
 * the all-zero key (tests, in-process runs, callers not yet given a key).
 */
#ifndef AMBHIL_WIRE_H
#define AMBHIL_WIRE_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "_blake2b.h"

#define WIRE_VERSION 3
#define PEER_LEN 16
#define MAC_LEN 16
#define SEAL_KEY_LEN 32
#define SEAL_LEN (PEER_LEN + SEAL_KEY_LEN)
#define TAIL_LEN (PEER_LEN + MAC_LEN)    /* what ends a loop message: peer id, mac */
static const unsigned char ENCAP[4] = {0x00, 0x01, 0x00, 0x00};

/* What one C file of the extension gives another (the lockstep types, the loops' shared
 * helpers): bound inside the .so, not exported next to PyInit__wire. */
#if defined(__GNUC__)
#define WIRE_INTERNAL __attribute__((visibility("hidden")))
#else
#define WIRE_INTERNAL
#endif

static inline Py_ssize_t hdr_size(int nt) { return 44 + 8 * (Py_ssize_t)nt; }

static inline int all_finite(const char *p, Py_ssize_t n)
{
    for (Py_ssize_t i = 0; i < n; i++) {
        double x;
        memcpy(&x, p + 8 * i, 8);
        if (!isfinite(x))
            return 0;
    }
    return 1;
}

/* A seal ready for use: the id and the key's precomputed BLAKE2b state (one compression per
 * MAC of up to 128 bytes before the mac: SensorSample up to 7 axes, CurrentCommand up to 6). */
typedef struct {
    char id[PEER_LEN];
    b2b_keyed key;
} wire_seal;

static inline int seal_size_ok(Py_ssize_t n) { return n == PEER_LEN || n == SEAL_LEN; }

/* The seal of a 16- or 48-byte value (the caller has checked the size with seal_size_ok). */
static inline void seal_make(wire_seal *s, const char *v, Py_ssize_t n)
{
    static const char zero_key[SEAL_KEY_LEN] = {0};
    memcpy(s->id, v, PEER_LEN);
    b2b_keyed_init(&s->key, n == SEAL_LEN ? v + PEER_LEN : zero_key, SEAL_KEY_LEN, MAC_LEN);
}

/* The fast-path check and copy of one message: 1 (``out`` filled with the n values, the
 * header fields in seq/step/sim/t) if ``p``/``len`` is a well-formed, finite message for n
 * axes with sequence number ``expect`` sent by ``peer`` (its id, and a mac valid under its
 * key); else 0 (``out`` untouched).  The mac is checked last: it is the costly check. */
static inline int decode_raw(const char *p, Py_ssize_t len, int nt, Py_ssize_t n, uint64_t expect,
                             const wire_seal *peer, char *out, uint64_t *seq, uint64_t *step,
                             int64_t *sim, int64_t *t)
{
    Py_ssize_t off = hdr_size(nt), body = off + 8 * n + PEER_LEN;
    uint16_t ver;
    uint32_t cnt;
    uint8_t mac[MAC_LEN];
    if (len != body + MAC_LEN || memcmp(p, ENCAP, 4) != 0
        || memcmp(p + off + 8 * n, peer->id, PEER_LEN) != 0)
        return 0;
    memcpy(&ver, p + 4, 2);
    memcpy(&cnt, p + off - 8, 4);
    memcpy(seq, p + 12, 8);
    if (ver != WIRE_VERSION || (Py_ssize_t)cnt != n || *seq != expect || !all_finite(p + off, n))
        return 0;
    b2b_keyed_mac(&peer->key, p, (size_t)body, mac);
    if (!b2b_equal(mac, (const uint8_t *)p + body, MAC_LEN))
        return 0;
    memcpy(step, p + 20, 8);
    memcpy(sim, p + 28, 8);
    memcpy(t, p + 36, 8 * (size_t)nt);
    memcpy(out, p + off, 8 * (size_t)n);
    return 1;
}

/* The message bytes for the n float64 values at ``vec`` (caller has checked them finite),
 * header values v = (sim_time_ns, t0[, t1]), sealed by ``me`` (its id, then the mac under its
 * key); NULL on memory error. */
static inline PyObject *encode_raw(const char *vec, Py_ssize_t n, int nt, uint64_t seq, uint64_t step,
                                   const int64_t *v, const wire_seal *me)
{
    Py_ssize_t off = hdr_size(nt), body = off + 8 * n + PEER_LEN;
    PyObject *res = PyBytes_FromStringAndSize(NULL, body + MAC_LEN);
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
    memcpy(p + off + 8 * n, me->id, PEER_LEN);
    b2b_keyed_mac(&me->key, p, (size_t)body, (uint8_t *)p + body);
    return res;
}

#endif /* AMBHIL_WIRE_H */
