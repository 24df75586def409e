/* SHA-256 (FIPS 180-4) and HMAC-SHA256 (RFC 2104), small and dependency-free, for the board
 * protocol (the hardware FMU and the board daemon).  Checked against Python's hashlib/hmac (tests/test_hw_fmu.py). */
#ifndef HMAC_SHA256_H
#define HMAC_SHA256_H
#include <stddef.h>
#include <stdint.h>

typedef struct {
    uint32_t h[8];
    uint64_t length; /* bytes hashed so far */
    uint8_t block[64];
    size_t used;
} Sha256;

void sha256_init(Sha256 *s);
void sha256_update(Sha256 *s, const uint8_t *data, size_t n);
void sha256_final(Sha256 *s, uint8_t out[32]);
void hmac_sha256(const uint8_t *key, size_t key_len, const uint8_t *data, size_t n, uint8_t out[32]);
/* A key with its padded blocks hashed once: each MAC then costs two compressions for a short
 * message instead of four (bounded work per datagram on the board). */
typedef struct {
    Sha256 inner, outer;
} HmacKey;
void hmac_key_init(HmacKey *k, const uint8_t *key, size_t key_len);
void hmac_key_mac(const HmacKey *k, const uint8_t *data, size_t n, uint8_t out[32]);
/* 1 when the 32-byte MACs are equal (constant time), else 0 */
int hmac_equal(const uint8_t a[32], const uint8_t b[32]);
#endif
