/* The multi-resolution feature grid of NeuS's SDF network in one pass over memory (CPU, float32).

   The same arithmetic as `DenseGrid.forward` in grid.py (the reference the tests compare against):
   a point p in [-1, 1]^3 falls in a cell of each level's grid of `res` points a side at the cell
   centres; its feature is the trilinear blend of the cell's 8 corners, each corner's row in the
   table dense or, past 2^hash_log2 points, hashed (Instant-NGP's primes, XOR-ed). With a Jacobian
   buffer the derivative of each feature in p comes too (0 along an axis where the lookup is
   clamped to the grid). The backward pass adds each corner's share of the incoming gradients into
   the table's gradient; levels own disjoint table rows, so threads split the levels and never
   write the same row.

   Plain C with OpenMP: no Python or torch headers, so it compiles in a second. */

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define MAX_FEATURES 16
#define MAX_THREADS 64

typedef struct {
    const float *table;
    int64_t features;
    const float *points;
    int64_t n;
    int64_t levels;
    const int64_t *res;
    const int64_t *offsets;
    const uint8_t *hashed;
    int64_t hash_mask;
    const float *level_weights;
    float *feats;       /* forward: (n, levels * features) */
    float *jac;         /* forward: (n, 3, levels * features) or NULL */
    const float *grad_feats; /* backward: (n, levels * features) */
    const float *grad_jac;   /* backward: (n, 3, levels * features) or NULL */
    float *grad_table;  /* backward: (rows, features), zeroed and accumulated into */
    int64_t rows;       /* the table's row count */
    int64_t begin, end; /* forward: this thread's points [begin, end); backward: its levels begin, begin + end, ... */
} Job;

/* The cell of coordinate p on a level of `res` points: lower corner, fraction, d(cell units)/dp. */
static inline void cell(float p, float res, int64_t *i0, float *frac, float *du) {
    float x = (p + 1.0f) * (0.5f * res) - 0.5f;
    float u = x > 0.0f ? x : 0.0f;
    if (x != x) u = x; /* a NaN coordinate gives NaN weights: its features are NaN, no other point's */
    if (u > res - 1.0f) u = res - 1.0f;
    float i = floorf(u);
    if (i > res - 2.0f) i = res - 2.0f;
    int64_t k = (i == i) ? (int64_t)i : 0;
    if (k < 0) k = 0; /* never outside the table, whatever the input */
    if (k > (int64_t)res - 2) k = (int64_t)res - 2;
    *i0 = k;
    *frac = u - i;
    *du = (x > 0.0f && x < res - 1.0f) ? 0.5f * res : 0.0f;
}

/* Table rows of the 8 corners of a point's cell and their trilinear weights (w[c][0]) and the
   weights' gradient in the point (w[c][1..3]), level weight included. */
static inline void corners(const Job *job, int64_t l, const float *p, int64_t rows[8], float w[8][4]) {
    const int64_t r = job->res[l];
    const float rf = (float)r;
    int64_t i[3];
    float f[3], du[3];
    for (int a = 0; a < 3; ++a) cell(p[a], rf, &i[a], &f[a], &du[a]);
    const float lw = job->level_weights[l];
    const float wa[3][2] = {{1.0f - f[0], f[0]}, {1.0f - f[1], f[1]}, {1.0f - f[2], f[2]}};
    const float da[3][2] = {{-du[0], du[0]}, {-du[1], du[1]}, {-du[2], du[2]}};
    for (int c = 0; c < 8; ++c) {
        const int dx = c >> 2, dy = (c >> 1) & 1, dz = c & 1;
        const uint64_t x = (uint64_t)(i[0] + dx), y = (uint64_t)(i[1] + dy), z = (uint64_t)(i[2] + dz);
        uint64_t row;
        if (job->hashed[l])
            row = ((x * 1ull) ^ (y * 2654435761ull) ^ (z * 805459861ull)) & (uint64_t)job->hash_mask;
        else
            row = (x * (uint64_t)r + y) * (uint64_t)r + z;
        rows[c] = job->offsets[l] + (int64_t)row;
        w[c][0] = lw * (wa[0][dx] * wa[1][dy] * wa[2][dz]);
        w[c][1] = lw * (da[0][dx] * wa[1][dy] * wa[2][dz]);
        w[c][2] = lw * (wa[0][dx] * da[1][dy] * wa[2][dz]);
        w[c][3] = lw * (wa[0][dx] * wa[1][dy] * da[2][dz]);
    }
}

/* Points go through the kernels in blocks: the corners of a block's points on one level are found
   and their table rows prefetched first, then blended, so the rows' cache misses overlap. */
#define BLOCK 32

static void *forward_job(void *arg) {
    const Job *job = (const Job *)arg;
    const int64_t F = job->features, L = job->levels;
    int64_t rows[BLOCK][8];
    float w[BLOCK][8][4];
    for (int64_t n0 = job->begin; n0 < job->end; n0 += BLOCK) {
        const int64_t m = job->end - n0 < BLOCK ? job->end - n0 : BLOCK;
        for (int64_t l = 0; l < L; ++l) {
            for (int64_t b = 0; b < m; ++b) {
                corners(job, l, job->points + 3 * (n0 + b), rows[b], w[b]);
                for (int c = 0; c < 8; ++c) __builtin_prefetch(job->table + rows[b][c] * F, 0, 0);
            }
            for (int64_t b = 0; b < m; ++b) {
                float acc[MAX_FEATURES][4] = {{0}};
                for (int c = 0; c < 8; ++c) {
                    const float *v = job->table + rows[b][c] * F;
                    for (int64_t k = 0; k < F; ++k) {
                        acc[k][0] += w[b][c][0] * v[k];
                        acc[k][1] += w[b][c][1] * v[k];
                        acc[k][2] += w[b][c][2] * v[k];
                        acc[k][3] += w[b][c][3] * v[k];
                    }
                }
                const int64_t n = n0 + b;
                float *out = job->feats + (n * L + l) * F;
                for (int64_t k = 0; k < F; ++k) out[k] = acc[k][0];
                if (job->jac) {
                    float *j = job->jac + n * 3 * L * F + l * F;
                    for (int64_t k = 0; k < F; ++k) {
                        j[k] = acc[k][1];
                        j[L * F + k] = acc[k][2];
                        j[2 * L * F + k] = acc[k][3];
                    }
                }
            }
        }
    }
    return NULL;
}

/* Levels are dealt out in turn (thread t of T takes levels t, t + T, ...): the hashed fine levels,
   whose rows miss the cache, are shared out rather than left to one thread. Each thread zeroes its
   levels' rows of the gradient before it adds into them. */
static void *backward_job(void *arg) {
    const Job *job = (const Job *)arg;
    const int64_t F = job->features, L = job->levels;
    int64_t rows[BLOCK][8];
    float w[BLOCK][8][4];
    for (int64_t l = job->begin; l < L; l += job->end) {
        const int64_t first = job->offsets[l], last = l + 1 < L ? job->offsets[l + 1] : job->rows;
        memset(job->grad_table + first * F, 0, (size_t)(last - first) * (size_t)F * sizeof(float));
        if (job->level_weights[l] == 0.0f) continue; /* a level not yet faded in gets no gradient */
        for (int64_t n0 = 0; n0 < job->n; n0 += BLOCK) {
            const int64_t m = job->n - n0 < BLOCK ? job->n - n0 : BLOCK;
            for (int64_t b = 0; b < m; ++b) {
                corners(job, l, job->points + 3 * (n0 + b), rows[b], w[b]);
                for (int c = 0; c < 8; ++c) __builtin_prefetch(job->grad_table + rows[b][c] * F, 1, 0);
            }
            for (int64_t b = 0; b < m; ++b) {
                const int64_t n = n0 + b;
                const float *gf = job->grad_feats + (n * L + l) * F;
                const float *gj = job->grad_jac ? job->grad_jac + n * 3 * L * F + l * F : NULL;
                for (int c = 0; c < 8; ++c) {
                    float *g = job->grad_table + rows[b][c] * F;
                    for (int64_t k = 0; k < F; ++k) {
                        float s = w[b][c][0] * gf[k];
                        if (gj) s += w[b][c][1] * gj[k] + w[b][c][2] * gj[L * F + k] + w[b][c][3] * gj[2 * L * F + k];
                        g[k] += s;
                    }
                }
            }
        }
    }
    return NULL;
}

/* Run `fn` on `threads` threads of OpenMP's pool (torch's own, libgomp, once torch has loaded it: a
   second pool would spin against torch's between their parallel regions), the work split as
   `interleave` says; without OpenMP, on this thread alone. */
static int run_split(Job *base, void *(*fn)(void *), int64_t total, int threads, int interleave) {
    if (threads < 1) threads = 1;
    if (threads > MAX_THREADS) threads = MAX_THREADS;
    if (threads > total) threads = total > 0 ? (int)total : 1;
#ifdef _OPENMP
#pragma omp parallel for num_threads(threads) schedule(static, 1)
#endif
    for (int t = 0; t < threads; ++t) {
        Job job = *base;
        job.begin = interleave ? t : total * t / threads;
        job.end = interleave ? threads : total * (t + 1) / threads;
        fn(&job);
    }
    return 0;
}

int grid_forward(const float *table, int64_t features, const float *points, int64_t n, int64_t levels,
                 const int64_t *res, const int64_t *offsets, const uint8_t *hashed, int64_t hash_mask,
                 const float *level_weights, float *feats, float *jac, int threads) {
    if (features > MAX_FEATURES) return 1;
    Job job = {table, features, points, n, levels, res, offsets, hashed, hash_mask, level_weights,
               feats, jac, NULL, NULL, NULL, 0, 0, 0};
    return run_split(&job, forward_job, n, threads, 0);
}

int grid_backward(int64_t rows, int64_t features, const float *points, int64_t n, int64_t levels, const int64_t *res,
                  const int64_t *offsets, const uint8_t *hashed, int64_t hash_mask, const float *level_weights,
                  const float *grad_feats, const float *grad_jac, float *grad_table, int threads) {
    if (features > MAX_FEATURES) return 1;
    Job job = {NULL, features, points, n, levels, res, offsets, hashed, hash_mask, level_weights,
               NULL, NULL, grad_feats, grad_jac, grad_table, rows, 0, 0};
    return run_split(&job, backward_job, levels, threads, 1);
}
