/*
 * The radix sort the kernels share (occupancy_kernels.c, voxel_kernels.c): 64-bit keys sorted by a range of their
 * bits, stably, least significant digit first. A key packs what it is sorted by above a point's row, so keys that
 * start in row order come out sorted by the packed value with equal ones in row order, as NumPy's stable sorts
 * give them.
 */
#ifndef LEGO_LOAM_RADIX_SORT_H
#define LEGO_LOAM_RADIX_SORT_H

#include <stdint.h>

#define RADIX_MAX_DIGIT 11 /* bits a pass: at most 2048 counts, a few kB on the stack */

/* Sort the n keys by their bits low..high - 1 (0 <= low < high <= 64), stably; scratch holds n keys too. Returns
   the buffer the sorted keys ended in (keys or scratch). */
static uint64_t *radix_sort_bits(uint64_t *keys, uint64_t *scratch, int64_t n, int low, int high) {
    const int bits = high - low;
    const int passes = bits > 0 ? (bits + RADIX_MAX_DIGIT - 1) / RADIX_MAX_DIGIT : 0;
    const int digit = passes ? (bits + passes - 1) / passes : 1;
    const uint64_t mask = ((uint64_t)1 << digit) - 1;
    int64_t count[((int64_t)1 << RADIX_MAX_DIGIT) + 1];
    uint64_t *from = keys, *to = scratch;
    for (int pass = 0; pass < passes; ++pass) {
        const int shift = low + pass * digit; /* (< high: the last digit may reach past it, into zeros or ties) */
        for (uint64_t d = 0; d <= mask + 1; ++d) count[d] = 0;
        for (int64_t i = 0; i < n; ++i) count[((from[i] >> shift) & mask) + 1] += 1;
        for (uint64_t d = 0; d < mask; ++d) count[d + 1] += count[d];
        for (int64_t i = 0; i < n; ++i) to[count[(from[i] >> shift) & mask]++] = from[i];
        uint64_t *swap = from;
        from = to;
        to = swap;
    }
    return from;
}

#endif
