/* BLAKE2b (RFC 7693): the keyed hash of the loop messages' MAC (docs/protocol.md 5.3,
 * bridge/protocol/auth.py), for the C fast path, where calling hashlib per message would cost
 * several Python objects.  Written from the RFC's description (section 3: G, the compression
 * function F with 12 rounds of the message schedule SIGMA, the parameter block folded into h[0];
 * keying: the key zero-padded to one 128-byte block ahead of the data).  tests/test_mac.py
 * checks it against hashlib.blake2b (RFC Appendix A vector, key lengths 0..64, digest 1..64).
 *
 * Two ways in:
 * - b2b_init / b2b_update / b2b_final: any key of 0..64 bytes, any digest of 1..64 bytes;
 * - b2b_keyed_init / b2b_keyed_mac: the state after the key block, computed once per key, so
 *   that a MAC of a message of 1..128 bytes costs one compression (the loops' messages of up to
 *   7 axes; a keyed MAC of such a message otherwise costs two).
 * Everything is static inline: one copy per C file that uses it, inlined where it pays. */
#ifndef AMBHIL_BLAKE2B_H
#define AMBHIL_BLAKE2B_H

#include <stddef.h>
#include <stdint.h>
#include <string.h>

#define B2B_BLOCK 128
#define B2B_MAX_OUT 64
#define B2B_MAX_KEY 64

typedef struct {
    uint64_t h[8];               /* chained state */
    uint64_t t[2];               /* bytes compressed so far (128-bit counter) */
    uint8_t buf[B2B_BLOCK];      /* the block not yet compressed (the last one may be final) */
    size_t fill;                 /* bytes in buf */
    size_t outlen;               /* digest size */
} b2b_ctx;

/* The state after the key block: h and the counter (one block) of a keyed hash whose data
 * has not begun; valid for data of at least one byte (with none the key block is the last). */
typedef struct {
    uint64_t h[8];
    size_t outlen;
} b2b_keyed;

static const uint64_t B2B_IV[8] = {
    0x6a09e667f3bcc908ULL, 0xbb67ae8584caa73bULL, 0x3c6ef372fe94f82bULL, 0xa54ff53a5f1d36f1ULL,
    0x510e527fade682d1ULL, 0x9b05688c2b3e6c1fULL, 0x1f83d9abfb41bd6bULL, 0x5be0cd19137e2179ULL};

/* SIGMA: the message word order of each round; rounds 10 and 11 use rows 0 and 1 again. */
static const uint8_t B2B_SIGMA[12][16] = {
    {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15},
    {14, 10, 4, 8, 9, 15, 13, 6, 1, 12, 0, 2, 11, 7, 5, 3},
    {11, 8, 12, 0, 5, 2, 15, 13, 10, 14, 3, 6, 7, 1, 9, 4},
    {7, 9, 3, 1, 13, 12, 11, 14, 2, 6, 5, 10, 4, 0, 15, 8},
    {9, 0, 5, 7, 2, 4, 10, 15, 14, 1, 11, 12, 6, 8, 3, 13},
    {2, 12, 6, 10, 0, 11, 8, 3, 4, 13, 7, 5, 15, 14, 1, 9},
    {12, 5, 1, 15, 14, 13, 4, 10, 0, 7, 6, 3, 9, 2, 8, 11},
    {13, 11, 7, 14, 12, 1, 3, 9, 5, 0, 15, 4, 8, 6, 2, 10},
    {6, 15, 14, 9, 11, 3, 0, 8, 12, 2, 13, 7, 1, 4, 10, 5},
    {10, 2, 8, 4, 7, 6, 1, 5, 15, 11, 9, 14, 3, 12, 13, 0},
    {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15},
    {14, 10, 4, 8, 9, 15, 13, 6, 1, 12, 0, 2, 11, 7, 5, 3}};

static inline uint64_t b2b_rotr(uint64_t x, unsigned n) { return (x >> n) | (x << (64 - n)); }

static inline uint64_t b2b_load64(const uint8_t *p)   /* little-endian word */
{
    uint64_t w;
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
    memcpy(&w, p, 8);                        /* one load (a quarter of the time per block) */
#else
    w = 0;
    for (int i = 7; i >= 0; i--)
        w = (w << 8) | p[i];
#endif
    return w;
}

/* G: mixes two message words x, y into the four state words a, b, c, d (RFC 7693 3.1) */
#define B2B_G(v, a, b, c, d, x, y)                                                            \
    do {                                                                                      \
        v[a] = v[a] + v[b] + (x);                                                             \
        v[d] = b2b_rotr(v[d] ^ v[a], 32);                                                     \
        v[c] = v[c] + v[d];                                                                   \
        v[b] = b2b_rotr(v[b] ^ v[c], 24);                                                     \
        v[a] = v[a] + v[b] + (y);                                                             \
        v[d] = b2b_rotr(v[d] ^ v[a], 16);                                                     \
        v[c] = v[c] + v[d];                                                                   \
        v[b] = b2b_rotr(v[b] ^ v[c], 63);                                                     \
    } while (0)

/* F: compress one 128-byte block into h; t = bytes so far (this block included), last: the
 * final block (RFC 7693 3.2) */
static inline void b2b_compress(uint64_t h[8], const uint8_t block[B2B_BLOCK], const uint64_t t[2],
                                int last)
{
    uint64_t v[16], m[16];
    for (int i = 0; i < 16; i++)
        m[i] = b2b_load64(block + 8 * i);
    for (int i = 0; i < 8; i++) {
        v[i] = h[i];
        v[i + 8] = B2B_IV[i];
    }
    v[12] ^= t[0];
    v[13] ^= t[1];
    if (last)
        v[14] = ~v[14];
    /* unrolled, SIGMA's indices are constants and m stays in registers: 136 ns per block
     * instead of 330 (-O2, the speed of hashlib's; benchmarks/codec.py) */
#if defined(__clang__)
#pragma unroll
#elif defined(__GNUC__)
#pragma GCC unroll 12
#endif
    for (int r = 0; r < 12; r++) {
        const uint8_t *s = B2B_SIGMA[r];
        B2B_G(v, 0, 4, 8, 12, m[s[0]], m[s[1]]);      /* columns */
        B2B_G(v, 1, 5, 9, 13, m[s[2]], m[s[3]]);
        B2B_G(v, 2, 6, 10, 14, m[s[4]], m[s[5]]);
        B2B_G(v, 3, 7, 11, 15, m[s[6]], m[s[7]]);
        B2B_G(v, 0, 5, 10, 15, m[s[8]], m[s[9]]);     /* diagonals */
        B2B_G(v, 1, 6, 11, 12, m[s[10]], m[s[11]]);
        B2B_G(v, 2, 7, 8, 13, m[s[12]], m[s[13]]);
        B2B_G(v, 3, 4, 9, 14, m[s[14]], m[s[15]]);
    }
    for (int i = 0; i < 8; i++)
        h[i] ^= v[i] ^ v[i + 8];
}

static inline void b2b_count(b2b_ctx *c, size_t n)
{
    c->t[0] += n;
    if (c->t[0] < n)
        c->t[1]++;
}

static inline void b2b_update(b2b_ctx *c, const void *data, size_t len)
{
    const uint8_t *p = (const uint8_t *)data;
    while (len > 0) {
        if (c->fill == B2B_BLOCK) {          /* more data follows: this block is not the last */
            b2b_count(c, B2B_BLOCK);
            b2b_compress(c->h, c->buf, c->t, 0);
            c->fill = 0;
        }
        size_t k = B2B_BLOCK - c->fill;
        if (k > len)
            k = len;
        memcpy(c->buf + c->fill, p, k);
        c->fill += k;
        p += k;
        len -= k;
    }
}

/* Returns 0, or -1 for a digest size outside 1..64 or a key longer than 64 bytes. */
static inline int b2b_init(b2b_ctx *c, size_t outlen, const void *key, size_t keylen)
{
    if (outlen < 1 || outlen > B2B_MAX_OUT || keylen > B2B_MAX_KEY)
        return -1;
    memcpy(c->h, B2B_IV, sizeof c->h);
    c->h[0] ^= 0x01010000ULL ^ ((uint64_t)keylen << 8) ^ (uint64_t)outlen;  /* parameter block */
    c->t[0] = c->t[1] = 0;
    c->fill = 0;
    c->outlen = outlen;
    if (keylen > 0) {                       /* the key, zero-padded, is the first block */
        uint8_t block[B2B_BLOCK] = {0};
        memcpy(block, key, keylen);
        b2b_update(c, block, B2B_BLOCK);
        memset(block, 0, sizeof block);
    }
    return 0;
}

static inline void b2b_final(b2b_ctx *c, uint8_t *out)
{
    uint8_t d[B2B_MAX_OUT];
    b2b_count(c, c->fill);
    memset(c->buf + c->fill, 0, B2B_BLOCK - c->fill);
    b2b_compress(c->h, c->buf, c->t, 1);
    for (int i = 0; i < 8; i++)
        for (int j = 0; j < 8; j++)
            d[8 * i + j] = (uint8_t)(c->h[i] >> (8 * j));
    memcpy(out, d, c->outlen);
}

/* The state after the key block of key (1..64 bytes), digest outlen: -1 if either is out of
 * range. */
static inline int b2b_keyed_init(b2b_keyed *k, const void *key, size_t keylen, size_t outlen)
{
    b2b_ctx c;
    if (keylen < 1 || b2b_init(&c, outlen, key, keylen) < 0)
        return -1;
    b2b_count(&c, B2B_BLOCK);                /* compress the key block now: data will follow */
    b2b_compress(c.h, c.buf, c.t, 0);
    memcpy(k->h, c.h, sizeof k->h);
    k->outlen = outlen;
    memset(&c, 0, sizeof c);
    return 0;
}

/* The keyed digest of len >= 1 bytes under the precomputed key state k */
static inline void b2b_keyed_mac(const b2b_keyed *k, const void *data, size_t len, uint8_t *out)
{
    b2b_ctx c;
    memcpy(c.h, k->h, sizeof c.h);
    c.t[0] = B2B_BLOCK;
    c.t[1] = 0;
    c.fill = 0;
    c.outlen = k->outlen;
    b2b_update(&c, data, len);
    b2b_final(&c, out);
}

/* 1 if the n bytes at a and b are equal; the time does not depend on where they differ */
static inline int b2b_equal(const uint8_t *a, const uint8_t *b, size_t n)
{
    uint8_t d = 0;
    for (size_t i = 0; i < n; i++)
        d |= a[i] ^ b[i];
    return d == 0;
}

#endif /* AMBHIL_BLAKE2B_H */
