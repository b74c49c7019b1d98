/* Tile compositor of the fast CPU backend, vectorised across the pixels of a tile row.
 *
 * The same image model and per-pixel arithmetic as the PyTorch reference (see splat_geometry.py):
 * per tile, the splats in stable depth order; per pixel, alpha = min(0.99, opacity exp(-q / 2))
 * where q <= support and alpha >= 1/255, front to back, with a stop before the splat that would
 * take the transmittance below 1e-4. Besides the sums, when asked (a non-NULL out_median_depth),
 * each pixel records its median depth: the depth of the splat at which its transmittance first
 * falls below 1/2. In the weights mode (canonical_weights_job) each pixel's weight alpha T of each
 * splat, at least min_weight, is written out, in blend order (the rows of a least-squares fit to an
 * image: rendering/weights.py), and the sums only when values are given. The transmittance is a float32
 * product (the reference's is a
 * float64 cumprod; over the tens of layers a pixel blends they differ by about 1e-7, and float64
 * here cost two conversions and a split into 4-lane halves per 8-pixel step).
 *
 * Why C: the blend is serial in splats but independent across the pixels of a row. numba/LLVM did
 * not vectorise that loop (the variants tried are in docs/experiments.md); GCC's vector
 * extensions do, 8 pixels a step. setup.py builds this file twice: a baseline build (SSE2 on
 * x86-64, NEON on arm64) and, on x86-64, an x86-64-v3 one (AVX2 + FMA), which cpu_tiles loads
 * where the CPU has it (one build with target_clones is slower than a -march build). No
 * Python.h: the library is loaded with ctypes, so it is tied to no CPython ABI.
 *
 * Layout: a tile is 16 x 16 pixels, p = row * 16 + column, in two 8-pixel blocks a row. The
 * per-tile channel sums are planar (channel-major) for up to PLANAR_MAX channels, so that a block
 * of one channel is one vector; wider sets (features, labels) are pixel-major and each blended
 * pixel adds its channels as one vectorised row, which skips the masked-off pixels of a block
 * (faster than planar at that width).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define TILE 16
#define TILE_PIXELS (TILE * TILE)
#define LANES 8
#define PLANAR_MAX 4
/* Columns of a splat record: the same order as splat_geometry.U ... SUPPORT. */
enum { U, V, CONIC_A, CONIC_B, CONIC_C, DEPTH, OPACITY, SUPPORT, RECORD };

typedef float v8f __attribute__((vector_size(32)));
typedef int32_t v8i __attribute__((vector_size(32)));

static const float MAX_ALPHA = 0.99f, MIN_ALPHA = 1.0f / 255.0f, MIN_TRANSMITTANCE = 1e-4f, HALF = 0.5f;

static inline __attribute__((always_inline)) v8f splat8(float x) { return (v8f){x, x, x, x, x, x, x, x}; }
static inline __attribute__((always_inline)) v8f select8(v8i mask, v8f a, v8f b) { return (v8f)((mask & (v8i)a) | (~mask & (v8i)b)); }
/* Bit l set where lane l of the mask is set. */
static inline __attribute__((always_inline)) int lanes8(v8i mask) {
#ifdef __AVX__
    return __builtin_ia32_movmskps256((v8f)mask);
#else
    int bits = 0;
    for (int l = 0; l < LANES; l++) bits |= (mask[l] & 1) << l;
    return bits;
#endif
}

/* The lane-wise minimum of lanes that are not NaN. */
static inline __attribute__((always_inline)) v8f min8(v8f a, v8f b) {
#ifdef __AVX__
    return __builtin_ia32_minps256(a, b);
#else
    return select8((v8i)(a < b), a, b);
#endif
}

/* exp(x) for -87 <= x <= 0 in float32 (Cephes expf: Cody-Waite reduction, degree-5 minimax
 * polynomial), within 2 ulp of libm's expf. Below -87 the exponent field wraps and a lane holds
 * garbage: the caller uses only exponents >= -4.5 and masks the other lanes, so no clamp is paid. */
static inline __attribute__((always_inline)) v8f exp8(v8f x) {
    v8f t = x * splat8(1.44269504088896341f) + splat8(0.5f);
#ifdef __AVX__
    v8f nf = __builtin_ia32_roundps256(t, 0x09); /* floor, one instruction (vroundps) */
    v8i n = __builtin_convertvector(nf, v8i);
#else
    v8i n = __builtin_convertvector(t, v8i);
    n += (v8i)(__builtin_convertvector(n, v8f) > t); /* truncation -> floor for negative t */
    v8f nf = __builtin_convertvector(n, v8f);
#endif
    x = x - nf * splat8(0.693359375f) - nf * splat8(-2.12194440e-4f);
    v8f y = splat8(1.9875691500e-4f);
    y = y * x + splat8(1.3981999507e-3f);
    y = y * x + splat8(8.3334519073e-3f);
    y = y * x + splat8(4.1665795894e-2f);
    y = y * x + splat8(1.6666665459e-1f);
    y = y * x + splat8(5.0000001201e-1f);
    y = y * x * x + x + splat8(1.0f);
    return y * (v8f)((n + 127) << 23);
}

/* Stable ascending order of positive float depths, given as their bits in keys[0, n): LSD radix
 * sort (the bits of positive floats order as the floats do), 8 bits a pass, passes whose digit is
 * the same for all skipped: cheaper than a comparison sort on a tile's thousand or so splats. Uses
 * keys_out and both order buffers as scratch; returns whichever order buffer holds the result. */
static const int32_t *depth_order(uint32_t *keys, uint32_t *keys_out, int32_t *order, int32_t *order_out, int64_t n) {
    for (int64_t i = 0; i < n; i++) order[i] = (int32_t)i;
    int64_t count[256];
    for (int shift = 0; shift < 32; shift += 8) {
        memset(count, 0, sizeof count);
        for (int64_t i = 0; i < n; i++) count[(keys[i] >> shift) & 255]++;
        if (n == 0 || count[(keys[0] >> shift) & 255] == n) continue;
        int64_t total = 0;
        for (int d = 0; d < 256; d++) {
            int64_t c = count[d];
            count[d] = total;
            total += c;
        }
        for (int64_t i = 0; i < n; i++) {
            int64_t at = count[(keys[i] >> shift) & 255]++;
            keys_out[at] = keys[i];
            order_out[at] = order[i];
        }
        uint32_t *k = keys; keys = keys_out; keys_out = k;
        int32_t *o = order; order = order_out; order_out = o;
    }
    return order;
}

typedef struct {
    const int64_t *tile_starts;
    int64_t num_tiles;
    const int32_t *splat_ids;
    const float *splats;
    const int32_t *boxes;
    const float *values;
    int64_t splat_stride, box_stride, value_stride; /* elements from one splat's row to the next */
    int64_t channels, tiles_x, width, height;
    float *out_values, *out_depth_sums, *out_weight_sums, *out_transmittance, *out_median_depth;
    int64_t max_tile_splats;
    int64_t next_tile; /* shared work counter: tiles differ a lot in cost, so hand them out one at a time */
    int failed;
    /* the weights mode (out_ids non-NULL): each tile's entries go to its slots from slot_starts[tile] */
    float min_weight;
    const int64_t *slot_starts;
    int32_t *out_pixels, *out_ids;
    float *out_weights;
    int64_t *out_counts;
} Job;

/* Per-thread scratch, sized for the largest tile. */
typedef struct {
    uint32_t *keys, *keys_out;
    int32_t *order, *order_out;
    float *records, *values, *accum;
    int32_t *boxes, *splat_of; /* splat_of: each depth-ordered record's splat index */
} Scratch;

/* What a job writes; blend_tile is compiled once per mode, so that a render's blend carries no test
 * of the weights mode in its inner loop. */
enum { SUMS = 1, WEIGHTS = 2, WEIGHTS_AND_SUMS = SUMS | WEIGHTS };

static inline __attribute__((always_inline)) void blend_tile(const Job *job, int64_t tile, Scratch *s, const int mode) {
    const int64_t first = job->tile_starts[tile], n = job->tile_starts[tile + 1] - first, channels = job->channels;
    const int32_t *ids = job->splat_ids + first;
    /* Sort, then gather the tile's records, boxes and values in depth order: scattered reads
     * once, in a tight loop, rather than inside the blend. The depths' loop brings each splat's
     * line into the cache for the gather; the lines of splats 32 ahead are asked for early, so
     * that more of those misses overlap. */
    for (int64_t k = 0; k < n; k++) {
        if (k + 32 < n) __builtin_prefetch(&job->splats[(int64_t)ids[k + 32] * job->splat_stride]);
        memcpy(&s->keys[k], &job->splats[(int64_t)ids[k] * job->splat_stride + DEPTH], sizeof(uint32_t));
    }
    const int32_t *order = depth_order(s->keys, s->keys_out, s->order, s->order_out, n);
    for (int64_t k = 0; k < n; k++) {
        int64_t i = ids[order[k]];
        memcpy(s->records + k * RECORD, job->splats + i * job->splat_stride, RECORD * sizeof(float));
        memcpy(s->boxes + k * 4, job->boxes + i * job->box_stride, 4 * sizeof(int32_t));
        if (channels) memcpy(s->values + k * channels, job->values + i * job->value_stride, channels * sizeof(float));
        s->splat_of[k] = (int32_t)i;
    }
    const int64_t u0 = (tile % job->tiles_x) * TILE, v0 = (tile / job->tiles_x) * TILE;
    const int64_t u1 = u0 + TILE < job->width ? u0 + TILE : job->width;
    const int64_t v1 = v0 + TILE < job->height ? v0 + TILE : job->height;

    float transmittance[TILE_PIXELS] __attribute__((aligned(32)));
    /* float32 sums: their rounding, ~1e-6 relative over the ~30 layers a pixel blends, is far
     * inside the tests' 1e-4, and a vector then holds 8 pixels instead of 4 */
    float depth_sum[TILE_PIXELS] __attribute__((aligned(32)));
    float weight_sum[TILE_PIXELS] __attribute__((aligned(32)));
    int32_t done[TILE_PIXELS] __attribute__((aligned(32)));
    float median_depth[TILE_PIXELS] __attribute__((aligned(32))); /* 0 until the transmittance falls below 1/2 */
    float *accum = s->accum;
    for (int p = 0; p < TILE_PIXELS; p++) transmittance[p] = 1.0f;
    memset(depth_sum, 0, sizeof depth_sum);
    memset(weight_sum, 0, sizeof weight_sum);
    memset(done, 0, sizeof done);
    const int track_median = job->out_median_depth != NULL;
    if (track_median) memset(median_depth, 0, sizeof median_depth);
    memset(accum, 0, channels * TILE_PIXELS * sizeof(float));
    int64_t active = (u1 - u0) * (v1 - v0);
    int64_t slot = (mode & WEIGHTS) ? job->slot_starts[tile] : 0;
    const v8f lane = {0, 1, 2, 3, 4, 5, 6, 7};
    const v8i lane_i = {0, 1, 2, 3, 4, 5, 6, 7};

    for (int64_t k = 0; k < n && active > 0; k++) {
        const float *r = s->records + k * RECORD;
        const int32_t *box = s->boxes + k * 4;
        const float *value = s->values + k * channels;
        const float half_a = -0.5f * r[CONIC_A], half_b2 = -r[CONIC_B], half_c = -0.5f * r[CONIC_C];
        const v8f opacity = splat8(r[OPACITY]), depth = splat8(r[DEPTH]);
        const v8f min_exponent = splat8(-0.5f * r[SUPPORT]); /* exponent -q/2 below it: alpha < 1/255 */
        const int64_t col_lo = (box[0] > u0 ? box[0] : u0) - u0, col_hi = (box[1] + 1 < u1 ? box[1] + 1 : u1) - u0;
        const int64_t row_lo = (box[2] > v0 ? box[2] : v0) - v0, row_hi = (box[3] + 1 < v1 ? box[3] + 1 : v1) - v0;
        /* Per 8-pixel block of a tile row: the columns the splat's box covers (none outside it), and
         * the exponent -q/2 split into dx-only terms and a coefficient of dy, so that a row adds
         * only its dy terms. */
        const int64_t first_block = col_lo / LANES, last_block = (col_hi - 1) / LANES;
        v8i columns[TILE / LANES];
        v8f x_terms[TILE / LANES], xy_terms[TILE / LANES];
        for (int64_t block = 0; block < TILE / LANES; block++) {
            const int32_t start = (int32_t)(block * LANES);
            columns[block] = (lane_i + start >= (int32_t)col_lo) & (lane_i + start < (int32_t)col_hi);
            const v8f dx = splat8(r[U]) - (lane + splat8((float)(u0 + start)));
            x_terms[block] = splat8(half_a) * dx * dx;
            xy_terms[block] = splat8(half_b2) * dx;
        }
        for (int64_t row = row_lo; row < row_hi; row++) {
            const float dy = r[V] - (float)(v0 + row);
            const v8f dy8 = splat8(dy), y_term = splat8(half_c * dy * dy);
            /* Both blocks of the row, unrolled, those outside the box skipped: the terms above stay
             * in registers and there is no loop whose length changes from splat to splat. */
#pragma GCC unroll 2
            for (int64_t block = 0; block < TILE / LANES; block++) {
                if (block < first_block || block > last_block) continue;
                const int64_t p = row * TILE + block * LANES;
                v8i done_now;
                memcpy(&done_now, done + p, sizeof done_now);
                const v8f exponent = x_terms[block] + xy_terms[block] * dy8 + y_term;
                v8i mask = columns[block] & ~done_now & (v8i)(exponent >= min_exponent);
                if (!lanes8(mask)) continue;
                v8f alpha = opacity * exp8(exponent);
                alpha = min8(alpha, splat8(MAX_ALPHA));
                mask &= (v8i)(alpha >= splat8(MIN_ALPHA));
                if (!lanes8(mask)) continue;
                v8f t;
                memcpy(&t, transmittance + p, sizeof t);
                const v8f next = t * (splat8(1.0f) - alpha);
                /* 3DGS: stop before the splat that would take the transmittance below 1e-4. With the
                 * median depth, one test finds both that and the splat taking it below 1/2: from 1/2
                 * or above one splat cannot reach 1e-4 (alpha <= 0.99), so those lanes test 1/2. */
                const v8i above_half = track_median ? (v8i)(t >= splat8(HALF)) : (v8i){0, 0, 0, 0, 0, 0, 0, 0};
                const v8i hit = mask & (v8i)(next < select8(above_half, splat8(HALF), splat8(MIN_TRANSMITTANCE)));
                if (lanes8(hit)) {
                    const v8i stop = hit & ~above_half, crosses_half = hit & above_half;
                    const int stopped = lanes8(stop);
                    if (stopped) {
                        done_now |= stop;
                        memcpy(done + p, &done_now, sizeof done_now);
                        active -= __builtin_popcount(stopped);
                        mask &= ~stop;
                    }
                    if (lanes8(crosses_half)) {
                        v8f m;
                        memcpy(&m, median_depth + p, sizeof m);
                        m = select8(crosses_half, depth, m);
                        memcpy(median_depth + p, &m, sizeof m);
                    }
                }
                const v8f weight = (v8f)(mask & (v8i)(alpha * t));
                t = select8(mask, next, t);
                memcpy(transmittance + p, &t, sizeof t);
                if (mode & WEIGHTS) {
                    for (int bits = lanes8(mask); bits; bits &= bits - 1) {
                        const int l = __builtin_ctz(bits);
                        if (weight[l] >= job->min_weight) {
                            job->out_pixels[slot] = (int32_t)((v0 + row) * job->width + u0 + block * LANES + l);
                            job->out_ids[slot] = s->splat_of[k];
                            job->out_weights[slot] = weight[l];
                            slot++;
                        }
                    }
                    if (!(mode & SUMS)) continue; /* the sums too, when asked: the render of every weight */
                }
                if (channels <= PLANAR_MAX) {
                    for (int64_t ch = 0; ch < channels; ch++) {
                        float *sum = accum + ch * TILE_PIXELS + p;
                        v8f acc;
                        memcpy(&acc, sum, sizeof acc);
                        acc += weight * splat8(value[ch]);
                        memcpy(sum, &acc, sizeof acc);
                    }
                } else {
                    for (int bits = lanes8(mask); bits; bits &= bits - 1) {
                        const int l = __builtin_ctz(bits);
                        const float w1 = weight[l];
                        float *sum = accum + (p + l) * channels;
                        for (int64_t ch = 0; ch < channels; ch++) sum[ch] += w1 * value[ch];
                    }
                }
                v8f d, w;
                memcpy(&d, depth_sum + p, sizeof d);
                memcpy(&w, weight_sum + p, sizeof w);
                d += weight * depth;
                w += weight;
                memcpy(depth_sum + p, &d, sizeof d);
                memcpy(weight_sum + p, &w, sizeof w);
            }
        }
    }
    if (mode & WEIGHTS) {
        job->out_counts[tile] = slot - job->slot_starts[tile];
        if (!(mode & SUMS)) return;
    }
    for (int64_t v = v0; v < v1; v++) {
        for (int64_t u = u0; u < u1; u++) {
            const int64_t p = (v - v0) * TILE + (u - u0), pixel = v * job->width + u;
            if (channels <= PLANAR_MAX) {
                for (int64_t ch = 0; ch < channels; ch++) job->out_values[pixel * channels + ch] = accum[ch * TILE_PIXELS + p];
            } else {
                memcpy(job->out_values + pixel * channels, accum + p * channels, channels * sizeof(float));
            }
            if (job->out_depth_sums) job->out_depth_sums[pixel] = depth_sum[p];
            job->out_weight_sums[pixel] = weight_sum[p];
            job->out_transmittance[pixel] = transmittance[p];
            if (track_median) job->out_median_depth[pixel] = median_depth[p];
        }
    }
}

/* Take tiles of `job` and blend them until none is left, with scratch of this thread's own. */
static void worker(Job *job) {
    const int64_t m = job->max_tile_splats > 0 ? job->max_tile_splats : 1;
    Scratch s = {
        malloc(m * sizeof(uint32_t)), malloc(m * sizeof(uint32_t)), malloc(m * sizeof(int32_t)),
        malloc(m * sizeof(int32_t)), malloc(m * RECORD * sizeof(float)), malloc((m * job->channels + 1) * sizeof(float)),
        aligned_alloc(32, (job->channels * TILE_PIXELS + LANES) * sizeof(float)), malloc(m * 4 * sizeof(int32_t)),
        malloc(m * sizeof(int32_t)),
    };
    if (s.keys && s.keys_out && s.order && s.order_out && s.records && s.values && s.accum && s.boxes && s.splat_of) {
        int64_t tile;
        /* a compositing job sums; a weights job writes its weights, and sums too when given values */
        const int mode = !job->out_ids ? SUMS : job->out_values ? WEIGHTS_AND_SUMS : WEIGHTS;
        while ((tile = __atomic_fetch_add(&job->next_tile, 1, __ATOMIC_RELAXED)) < job->num_tiles) {
            if (mode == SUMS) blend_tile(job, tile, &s, SUMS);
            else if (mode == WEIGHTS) blend_tile(job, tile, &s, WEIGHTS);
            else blend_tile(job, tile, &s, WEIGHTS_AND_SUMS);
        }
    } else {
        __atomic_store_n(&job->failed, 1, __ATOMIC_RELAXED);
    }
    free(s.keys); free(s.keys_out); free(s.order); free(s.order_out);
    free(s.records); free(s.values); free(s.accum); free(s.boxes); free(s.splat_of);
}

/* A job on the heap, its largest tile counted (for the scratch), for canonical_job_work. */
static int64_t new_job(Job init) {
    for (int64_t t = 0; t < init.num_tiles; t++) {
        int64_t count = init.tile_starts[t + 1] - init.tile_starts[t];
        if (count > init.max_tile_splats) init.max_tile_splats = count;
    }
    Job *job = malloc(sizeof *job);
    if (job) *job = init;
    return (int64_t)(intptr_t)job;
}

/* A compositing job over every tile (0 if memory ran out), to be worked by canonical_job_work. */
int64_t canonical_composite_job(const int64_t *tile_starts, int64_t num_tiles, const int32_t *splat_ids,
                                const float *splats, int64_t splat_stride, const int32_t *boxes, int64_t box_stride,
                                const float *values, int64_t value_stride, int64_t channels, int64_t tiles_x,
                                int64_t width, int64_t height, float *out_values, float *out_depth_sums,
                                float *out_weight_sums, float *out_transmittance, float *out_median_depth) {
    Job job = {tile_starts, num_tiles, splat_ids, splats, boxes, values, splat_stride, box_stride, value_stride,
               channels, tiles_x, width, height, out_values, out_depth_sums, out_weight_sums, out_transmittance,
               out_median_depth, 0, 0, 0};
    return new_job(job);
}

/* The weights mode's job (0 if memory ran out): per tile, the entries (pixel v * width + u, splat
 * index, weight >= min_weight) in blend order into the slots from slot_starts[tile] (room for one per
 * pixel of each splat's box in the tile), and their number into out_counts[tile]. With values (NULL:
 * none), the same pass also blends them as canonical_composite_job does, every weight in, into
 * out_values, out_weight_sums and out_transmittance (no depth sums, no median depth). */
int64_t canonical_weights_job(const int64_t *tile_starts, int64_t num_tiles, const int32_t *splat_ids,
                              const float *splats, int64_t splat_stride, const int32_t *boxes, int64_t box_stride,
                              int64_t tiles_x, int64_t width, int64_t height, float min_weight,
                              const int64_t *slot_starts, int32_t *out_pixels, int32_t *out_ids, float *out_weights,
                              int64_t *out_counts, const float *values, int64_t value_stride, int64_t channels,
                              float *out_values, float *out_weight_sums, float *out_transmittance) {
    if (!values) channels = 0;
    Job job = {tile_starts, num_tiles, splat_ids, splats, boxes, values, splat_stride, box_stride, value_stride,
               channels, tiles_x, width, height, values ? out_values : NULL, NULL, out_weight_sums, out_transmittance,
               NULL, 0, 0, 0, min_weight, slot_starts, out_pixels, out_ids, out_weights, out_counts};
    return new_job(job);
}

/* Blend tiles of `job` until none is left. Every thread of a team calls it once: the threads are
 * the caller's (cpu_tiles runs it on numba's OpenMP threads, which would otherwise spin idle
 * against threads of our own on the same cores). */
void canonical_job_work(int64_t job) { worker((Job *)(intptr_t)job); }

/* Free `job`. Returns 0, or -1 if a thread ran out of memory for its tile buffers. */
int canonical_job_finish(int64_t job) {
    Job *j = (Job *)(intptr_t)job;
    const int failed = j->failed;
    free(j);
    return failed ? -1 : 0;
}

/* The stable depth order of n positive depths into out_order (for tests). Returns 0, or -1 if
 * memory ran out. */
int canonical_stable_depth_order(const float *depths, int64_t n, int32_t *out_order) {
    const int64_t m = n > 0 ? n : 1;
    uint32_t *keys = malloc(m * sizeof *keys), *keys_out = malloc(m * sizeof *keys_out);
    int32_t *order = malloc(m * sizeof *order), *order_out = malloc(m * sizeof *order_out);
    int status = -1;
    if (keys && keys_out && order && order_out) {
        memcpy(keys, depths, n * sizeof *keys);
        memcpy(out_order, depth_order(keys, keys_out, order, order_out, n), n * sizeof *out_order);
        status = 0;
    }
    free(keys); free(keys_out); free(order); free(order_out);
    return status;
}

/* Whether this CPU runs the x86-64-v3 build (AVX2, FMA, BMI2, ...); asked of the baseline build. */
int canonical_cpu_has_x86_64_v3(void) {
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
    __builtin_cpu_init();
    return __builtin_cpu_supports("x86-64-v3") != 0;
#else
    return 0;
#endif
}
