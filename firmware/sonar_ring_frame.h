/*
 * sonar_ring hardware frame, version 1: the reference encoder for firmware.
 *
 * Header-only C99, no allocation, no floating point: fill a srf_ping with
 * integers already in wire units (ns, mm/s, amplitude codes) and
 * srf_encode_echoes() writes the whole frame into your buffer, byte by byte
 * little-endian whatever the CPU's byte order.  The frame is specified in the
 * README's "Hardware frame" section; test/test_frame_encoder_c.py builds this
 * header and checks its bytes against the Python reference encoder
 * (sonar_ring.frames.encode_echoes) and decoder.
 *
 *   uint8_t frame[SRF_FRAME_SIZE(2, 2, SRF_FLAG_AMPLITUDE)];
 *   size_t length = srf_encode_echoes(&ping, frame, sizeof frame);  // 0: does not fit
 *   if (length) send(frame, length);                                // one frame per datagram on UDP
 */
#ifndef SONAR_RING_FRAME_H
#define SONAR_RING_FRAME_H

#include <stddef.h>
#include <stdint.h>

#define SRF_VERSION 1u
#define SRF_TYPE_ECHOES 1u
#define SRF_FLAG_AMPLITUDE 0x01u /* K amplitudes per row */
#define SRF_FLAG_PHASE 0x02u     /* K - 1 phase delays per row */
#define SRF_NO_ECHO 0xFFFFFFFFu  /* the TOF of a receiver that missed the echo (its amplitude: 0) */
#define SRF_HEADER_SIZE 7u
#define SRF_PING_SIZE 20u
#define SRF_CRC_SIZE 4u
#define SRF_MAX_PAYLOAD 65535u

/* Bytes of one echo row and of a whole frame of `rows` rows (for buffer sizes; compile-time when constant). */
#define SRF_ROW_SIZE(receivers, flags) \
    (3u + 4u * (receivers) + (((flags) & SRF_FLAG_AMPLITUDE) ? 2u * (receivers) : 0u) \
     + (((flags) & SRF_FLAG_PHASE) ? 4u * ((receivers) - 1u) : 0u))
#define SRF_FRAME_SIZE(rows, receivers, flags) \
    (SRF_HEADER_SIZE + SRF_PING_SIZE + (rows) * SRF_ROW_SIZE(receivers, flags) + SRF_CRC_SIZE)

/* One ping in wire units.  Arrays are row-major: receiver k of row n is [n * receivers + k]. */
typedef struct {
    uint32_t sequence;            /* the previous ping's plus one, wrapping */
    uint64_t device_time_us;      /* device clock when the transmitter fired; 0: no clock */
    uint16_t rows;                /* N echo rows */
    uint8_t receivers;            /* K receivers per group, >= 2 */
    uint8_t flags;                /* SRF_FLAG_AMPLITUDE | SRF_FLAG_PHASE, or 0 */
    uint32_t speed_of_sound_mm_s; /* 0: the host decides */
    const uint16_t *group;        /* [N] */
    const uint8_t *transmitter;   /* [N] */
    const uint32_t *tof_ns;       /* [N * K], SRF_NO_ECHO where missed */
    const uint16_t *amplitude;    /* [N * K] round(65535 * A / A_max), 0 where missed; with SRF_FLAG_AMPLITUDE */
    const int32_t *phase_ns;      /* [N * (K - 1)] after receiver 0; with SRF_FLAG_PHASE */
} srf_ping;

static inline uint8_t *srf_put_u16(uint8_t *out, uint16_t value) {
    out[0] = (uint8_t)value;
    out[1] = (uint8_t)(value >> 8);
    return out + 2;
}

static inline uint8_t *srf_put_u32(uint8_t *out, uint32_t value) {
    out = srf_put_u16(out, (uint16_t)value);
    return srf_put_u16(out, (uint16_t)(value >> 16));
}

static inline uint8_t *srf_put_u64(uint8_t *out, uint64_t value) {
    out = srf_put_u32(out, (uint32_t)value);
    return srf_put_u32(out, (uint32_t)(value >> 32));
}

/* CRC-32 of IEEE 802.3 as zlib computes it (reflected, polynomial 0xEDB88320, initial and final XOR all ones),
 * bit by bit: no table to keep in RAM. */
static inline uint32_t srf_crc32(const uint8_t *data, size_t length) {
    uint32_t crc = 0xFFFFFFFFu;
    for (size_t i = 0; i < length; ++i) {
        crc ^= data[i];
        for (int bit = 0; bit < 8; ++bit) {
            crc = (crc >> 1) ^ (0xEDB88320u & (0u - (crc & 1u)));
        }
    }
    return crc ^ 0xFFFFFFFFu;
}

/* Write the frame of `ping` to `out`; returns its length in bytes, or 0 when the ping has fewer than two
 * receivers, its payload exceeds 65535 bytes or `capacity` is too small. */
static inline size_t srf_encode_echoes(const srf_ping *ping, uint8_t *out, size_t capacity) {
    const size_t k = ping->receivers;
    const uint8_t flags = ping->flags & (SRF_FLAG_AMPLITUDE | SRF_FLAG_PHASE);
    const size_t payload = SRF_PING_SIZE + (size_t)ping->rows * SRF_ROW_SIZE(k, flags);
    if (k < 2 || payload > SRF_MAX_PAYLOAD || capacity < SRF_HEADER_SIZE + payload + SRF_CRC_SIZE) {
        return 0;
    }
    uint8_t *at = out;
    *at++ = 0xA5;
    *at++ = 0x5A;
    *at++ = SRF_VERSION;
    *at++ = SRF_TYPE_ECHOES;
    at = srf_put_u16(at, (uint16_t)payload);
    /* all four bytes 2..5: version, type and both bytes of the length */
    *at++ = (uint8_t)(255u - (SRF_VERSION + SRF_TYPE_ECHOES + (payload & 0xFFu) + (payload >> 8)) % 256u);
    at = srf_put_u32(at, ping->sequence);
    at = srf_put_u64(at, ping->device_time_us);
    at = srf_put_u16(at, ping->rows);
    *at++ = (uint8_t)k;
    *at++ = flags;
    at = srf_put_u32(at, ping->speed_of_sound_mm_s);
    for (size_t n = 0; n < ping->rows; ++n) {
        at = srf_put_u16(at, ping->group[n]);
        *at++ = ping->transmitter[n];
        for (size_t r = 0; r < k; ++r) {
            at = srf_put_u32(at, ping->tof_ns[n * k + r]);
        }
        if (flags & SRF_FLAG_AMPLITUDE) {
            for (size_t r = 0; r < k; ++r) {
                at = srf_put_u16(at, ping->amplitude[n * k + r]);
            }
        }
        if (flags & SRF_FLAG_PHASE) {
            for (size_t r = 0; r + 1 < k; ++r) {
                at = srf_put_u32(at, (uint32_t)ping->phase_ns[n * (k - 1) + r]);
            }
        }
    }
    at = srf_put_u32(at, srf_crc32(out, (size_t)(at - out)));
    return (size_t)(at - out);
}

#endif /* SONAR_RING_FRAME_H */
