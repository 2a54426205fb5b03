// OBSTACLE_DISTANCE bins from the device disparity image: a column of blocks per 5-degree bin.
//
// Exactly companion/core/obstacle.py's reduce_obstacle_distance on the disparity as the host sees it
// (int16 x scale, -1 invalid -> NaN): the same float32 compare for the height band (d >= row_thr[v]),
// the same float32 division for the horizontal distance (col_fbk[u] / d), the same rank
// k = max(1, ceil(pct * n / 100)) in double, and the same wire value (distance_cm: beyond max_m ->
// max_cm + 1, else floor(100 v) clamped to [min_cm, max_cm]).
//
// Why one pass suffices: the wire value is a non-decreasing function of the distance, and the k-th
// smallest commutes with such a function. So the kernel never needs the k-th distance itself, only the
// k-th wire value: a histogram of centimetres, filled in the same pass that counts the valid and in-band
// pixels, then a block-wide scan to find the bin holding rank k. Only when the centimetre range is wider
// than OD_HIST bins (max_distance_m above ~40 m) does a second pass resolve the coarse bin found first
// (bins of 2^shift cm).
//
// Why a column of blocks per bin: a bin is ~70 columns by every row, too little for one block to hide
// its loads (one block per bin took 58 us at 1280x720 on an H100, 18 blocks busy). Block (j, s) counts
// the pixels of bin j in row slice s into a shared histogram and adds its non-zero counts and its valid
// and in-band totals to bin j's global ones (integer sums: the order does not matter); the last block
// of the bin (a ticket counter) takes the totals, zeroes them for the next frame, and finds the rank.
// Its decisions (unknown, no obstacle) are uniform over the block, so an early return never strands a
// barrier.
//
// Threads: the slice's pixels in row-major order, OD_THREADS at a time (a warp reads consecutive
// columns of a row). Launch: grid (72, slices), block (OD_THREADS, a multiple of 32, at most 1024);
// hist_g (72 * OD_HIST) and cnt_g (72 * 4) zero before the first launch. Compiled with --fmad=false
// like the other modules (the rounding must be the reference's).

// OD_THREADS and OD_HIST come from companion/gpu/plan.py (obstacle_defines).
#define OD_WARPS (OD_THREADS / 32)

static_assert(OD_THREADS % 32 == 0 && OD_THREADS <= 1024, "OD_THREADS: whole warps, at most 1024");

typedef unsigned int od_u32;

// The wire value of one distance (metres, float32), as distance_cm does it on the host.
__device__ __forceinline__ int od_wire_cm(float v, float max_m, int min_cm, int max_cm)
{
    if (!(v <= max_m)) return max_cm + 1;
    const int x = (int)floor((double)v * 100.0);
    return x < min_cm ? min_cm : (x > max_cm ? max_cm : x);
}

// The index (wire value - min_cm) of pixel (r, c)'s sample q, or -1 when it is not an in-band point
// (invalid, zero, or below the row's height band): what both passes histogram.
__device__ __forceinline__ int od_index(short q, float inv_scale, float thr, const float* __restrict__ col_fbk, int c,
                                        float max_m, int min_cm, int max_cm)
{
    if (q <= 0) return -1;
    const float d = (float)q * inv_scale;
    if (!(d >= thr)) return -1;
    return od_wire_cm(col_fbk[c] / d, max_m, min_cm, max_cm) - min_cm;
}

// Over the block: which of hist[0, nb) holds rank k (1-based) of the counts, and the rank within it.
// Every thread sums a contiguous chunk; a warp-shuffle scan of the chunk sums finds the chunk.
__device__ void od_find_rank(const od_u32* hist, int nb, od_u32 k, od_u32* wsum, od_u32* s_bin, od_u32* s_k)
{
    const int t = threadIdx.x, lane = t & 31, warp = t >> 5;
    const int per = (nb + OD_THREADS - 1) / OD_THREADS;
    const int b0 = t * per, b1 = b0 + per < nb ? b0 + per : nb;
    od_u32 s = 0;
    for (int b = b0; b < b1; ++b) s += hist[b];
    od_u32 x = s;  // inclusive scan within the warp
    for (int o = 1; o < 32; o <<= 1) {
        const od_u32 y = __shfl_up_sync(0xFFFFFFFFu, x, o);
        if (lane >= o) x += y;
    }
    if (lane == 31) wsum[warp] = x;
    if (t == 0) { *s_bin = (od_u32)(nb - 1); *s_k = 1u; }  // unreachable when k <= the total; defined anyway
    __syncthreads();
    if (warp == 0) {
        od_u32 w = lane < OD_WARPS ? wsum[lane] : 0u;
        for (int o = 1; o < 32; o <<= 1) {
            const od_u32 y = __shfl_up_sync(0xFFFFFFFFu, w, o);
            if (lane >= o) w += y;
        }
        if (lane < OD_WARPS) wsum[lane] = w;
    }
    __syncthreads();
    const od_u32 incl = x + (warp > 0 ? wsum[warp - 1] : 0u);
    od_u32 cum = incl - s;
    if (cum < k && k <= incl) {  // exactly one thread's chunk holds rank k
        for (int b = b0; b < b1; ++b) {
            if (cum + hist[b] >= k) { *s_bin = (od_u32)b; *s_k = k - cum; break; }
            cum += hist[b];
        }
    }
    __syncthreads();
}

extern "C" __global__ void __launch_bounds__(OD_THREADS) obstacle_bins(
    const short* __restrict__ disp, int width, int height, float inv_scale,
    const float* __restrict__ row_thr, const float* __restrict__ col_fbk, const int* __restrict__ bin_cols,
    double pct, int min_points, double min_valid_fraction, float max_m, int min_cm, int max_cm,
    od_u32* __restrict__ hist_g, od_u32* __restrict__ cnt_g, unsigned short* __restrict__ out)
{
    __shared__ od_u32 hist[OD_HIST];
    __shared__ od_u32 wsum[32];
    __shared__ od_u32 s_valid, s_band, s_bin, s_k, s_last;
    const int j = blockIdx.x;
    const int c0 = bin_cols[2 * j], c1 = bin_cols[2 * j + 1];
    const int t = threadIdx.x;
    if (c1 <= c0) {  // outside the matched view: unknown
        if (t == 0 && blockIdx.y == 0) out[j] = 65535;
        return;
    }
    // Wire values min_cm .. max_cm + 1, as indices 0 .. nb - 1; coarse bins of 2^shift when too many.
    const int nb = max_cm + 2 - min_cm;
    int shift = 0;
    while (((nb - 1) >> shift) >= OD_HIST) ++shift;
    const int nb1 = ((nb - 1) >> shift) + 1;
    if (t == 0) { s_valid = 0; s_band = 0; }
    for (int b = t; b < nb1; b += OD_THREADS) hist[b] = 0;
    __syncthreads();
    const int ncols = c1 - c0;
    const int r0 = (int)(((long long)blockIdx.y * height) / gridDim.y);
    const int r1 = (int)(((long long)(blockIdx.y + 1) * height) / gridDim.y);
    const int npx = (r1 - r0) * ncols;
    od_u32 nv = 0, nbd = 0;
    for (int i = t; i < npx; i += OD_THREADS) {
        const int r = r0 + i / ncols, c = c0 + i % ncols;
        const short q = disp[(size_t)r * width + c];
        if (q < 0) continue;
        ++nv;
        const int x = od_index(q, inv_scale, row_thr[r], col_fbk, c, max_m, min_cm, max_cm);
        if (x >= 0) {
            ++nbd;
            atomicAdd(&hist[x >> shift], 1u);
        }
    }
    atomicAdd(&s_valid, nv);
    atomicAdd(&s_band, nbd);
    __syncthreads();
    od_u32* hj = hist_g + (size_t)j * OD_HIST;
    od_u32* cj = cnt_g + 4 * j;
    for (int b = t; b < nb1; b += OD_THREADS)
        if (hist[b]) atomicAdd(hj + b, hist[b]);
    if (t == 0) {
        if (s_valid) atomicAdd(cj, s_valid);
        if (s_band) atomicAdd(cj + 1, s_band);
    }
    // ---- the bin's last block: the totals (zeroed for the next frame), then the rank
    __threadfence();
    __syncthreads();
    if (t == 0) s_last = atomicAdd(cj + 2, 1u) == gridDim.y - 1;
    __syncthreads();
    if (!s_last) return;
    __threadfence();
    for (int b = t; b < nb1; b += OD_THREADS) {
        hist[b] = __ldcg(hj + b);
        hj[b] = 0u;
    }
    if (t == 0) {
        s_valid = __ldcg(cj);
        s_band = __ldcg(cj + 1);
        cj[0] = cj[1] = cj[2] = 0u;
    }
    __syncthreads();
    const od_u32 n_valid = s_valid, n_band = s_band;
    const int n = ncols * height;
    if (n_valid == 0 || (double)n_valid < min_valid_fraction * (double)n) {  // nothing matched: unknown
        if (t == 0) out[j] = 65535;
        return;
    }
    if (n_band < (od_u32)min_points) {  // too few points in the band: nothing near
        if (t == 0) out[j] = (unsigned short)(max_cm + 1);
        return;
    }
    const double kk = ceil(pct * (double)n_band / 100.0);
    const od_u32 k = kk < 1.0 ? 1u : (od_u32)kk;
    od_find_rank(hist, nb1, k, wsum, &s_bin, &s_k);
    int idx = (int)s_bin;
    if (shift > 0) {  // resolve the coarse bin: a second pass over its members only, every row, this block
        const int coarse = idx;
        const od_u32 k2 = s_k;
        const int nb2 = 1 << shift;
        __syncthreads();  // everyone has read s_bin and s_k
        for (int b = t; b < nb2; b += OD_THREADS) hist[b] = 0;
        __syncthreads();
        const int nall = height * ncols;
        for (int i = t; i < nall; i += OD_THREADS) {
            const int r = i / ncols, c = c0 + i % ncols;
            const int x = od_index(disp[(size_t)r * width + c], inv_scale, row_thr[r], col_fbk, c, max_m, min_cm, max_cm);
            if (x >= 0 && (x >> shift) == coarse) atomicAdd(&hist[x & (nb2 - 1)], 1u);
        }
        __syncthreads();
        od_find_rank(hist, nb2, k2, wsum, &s_bin, &s_k);
        idx = (coarse << shift) + (int)s_bin;
    }
    if (t == 0) out[j] = (unsigned short)(min_cm + idx);
}
