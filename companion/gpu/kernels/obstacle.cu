// OBSTACLE_DISTANCE bins from the device disparity image (issue 18): one block per 5-degree bin.
//
// Exactly companion/core/obstacle.py's reduce_obstacle_distance on the disparity as the host sees it
// (int16 x scale, -1 invalid -> NaN): the same float32 compare for the height band (d >= row_thr[v]),
// the same float32 division for the horizontal distance (col_fbk[u] / d), the same rank
// k = max(1, ceil(pct * n / 100)) in double, and the k-th smallest distance found exactly by a
// radix select on the float's bits (non-negative floats order like their bit patterns): four passes of
// an 8-bit histogram in shared memory, each narrowing the prefix. The block's decisions (unknown, no
// obstacle) are uniform, so an early return never strands a barrier.
//
// Launch: grid (72), block (OD_THREADS). Compiled with --fmad=false like the other modules (nothing
// here would fuse, but the rounding must be the reference's).

#ifndef OD_THREADS
#define OD_THREADS 256
#endif

typedef unsigned int od_u32;

extern "C" __global__ void __launch_bounds__(OD_THREADS) obstacle_bins(
    const short* __restrict__ disp, int width, int height, float inv_scale,
    const float* __restrict__ row_thr, const float* __restrict__ col_fbk, const int* __restrict__ bin_cols,
    double pct, int min_points, double min_valid_fraction, float max_m, int min_cm, int max_cm,
    unsigned short* __restrict__ out)
{
    __shared__ od_u32 hist[256];
    __shared__ od_u32 s_valid, s_band, s_prefix, s_k;
    const int j = blockIdx.x;
    const int c0 = bin_cols[2 * j], c1 = bin_cols[2 * j + 1];
    const int t = threadIdx.x;
    if (c1 <= c0) {  // outside the matched view: unknown
        if (t == 0) out[j] = 65535;
        return;
    }
    const int nc = c1 - c0;
    const int n = nc * height;
    if (t == 0) { s_valid = 0; s_band = 0; }
    __syncthreads();
    od_u32 nv = 0, nb = 0;
    for (int i = t; i < n; i += OD_THREADS) {
        const int r = i / nc, c = c0 + (i - r * nc);
        const short q = disp[r * width + c];
        if (q >= 0) {
            ++nv;
            const float d = (float)q * inv_scale;
            if (q > 0 && d >= row_thr[r]) ++nb;
        }
    }
    atomicAdd(&s_valid, nv);
    atomicAdd(&s_band, nb);
    __syncthreads();
    const od_u32 n_valid = s_valid, n_band = s_band;
    if (n_valid == 0 || (double)n_valid < min_valid_fraction * (double)n) {  // nothing matched: unknown
        if (t == 0) out[j] = 65535;
        return;
    }
    if (n_band < (od_u32)min_points) {  // too few points in the band: nothing near
        if (t == 0) out[j] = (unsigned short)(max_cm + 1);
        return;
    }
    const double kk = ceil(pct * (double)n_band / 100.0);
    od_u32 k = kk < 1.0 ? 1u : (od_u32)kk;
    od_u32 prefix = 0;
    for (int shift = 24; shift >= 0; shift -= 8) {
        for (int b = t; b < 256; b += OD_THREADS) hist[b] = 0;
        __syncthreads();
        const od_u32 hi_mask = shift == 24 ? 0u : (0xFFFFFFFFu << (shift + 8));
        for (int i = t; i < n; i += OD_THREADS) {
            const int r = i / nc, c = c0 + (i - r * nc);
            const short q = disp[r * width + c];
            if (q <= 0) continue;
            const float d = (float)q * inv_scale;
            if (!(d >= row_thr[r])) continue;
            const float dist = col_fbk[c] / d;
            const od_u32 key = __float_as_uint(dist);
            if ((key & hi_mask) == prefix) atomicAdd(&hist[(key >> shift) & 255u], 1u);
        }
        __syncthreads();
        if (t == 0) {
            od_u32 cum = 0, b = 0;
            for (; b < 255u; ++b) {
                if (cum + hist[b] >= k) break;
                cum += hist[b];
            }
            s_k = k - cum;
            s_prefix = prefix | (b << shift);
        }
        __syncthreads();
        prefix = s_prefix;
        k = s_k;
        __syncthreads();  // everyone has read them before the next pass clears the histogram
    }
    if (t == 0) {
        const float v = __uint_as_float(prefix);
        int cm;
        if (!(v <= max_m)) {
            cm = max_cm + 1;
        } else {
            const int x = (int)floor((double)v * 100.0);
            cm = x < min_cm ? min_cm : (x > max_cm ? max_cm : x);
        }
        out[j] = (unsigned short)cm;
    }
}
