// CUDA kernels of the `cupy` backend: BGR -> grey, bilinear rectification, exact SAD block matching with
// the 9-region robust minimum fused in, and a disparity preview. Compiled once per estimator with NVRTC
// through cupy.RawModule; companion/gpu/plan.py prepends the #defines that fix the image size, the
// matching parameters and the tile shape, so every loop bound below is a compile-time constant.
//
// The rules reproduced bit for bit are those of companion/core/disparity/reference.py (cost, valid
// area, tie-break to the LARGEST disparity, integer uniqueness and texture tests), cv2.cvtColor's
// fixed-point grey, and cv2.remap INTER_LINEAR as stated by remap_linear_reference(). Everything is
// integer arithmetic except the remap (float32 with explicit fmaf, compiled with --fmad=false) and
// the region depth (float32 division f*B/d, like companion/core/depth.py). The uniqueness ratio
// and texture threshold are kernel arguments, so changing them does not recompile.
//
// Portability: no feature newer than sm_53 is required; the Hopper DPX min3 instructions are used only
// under __CUDA_ARCH__ >= 900 with a CUDA 12+ compiler, with plain min() otherwise. Static shared memory
// stays under 48 KB per block (plan.py checks it), as every Jetson (TX1 ... Orin) allows.

typedef unsigned int u32;
typedef unsigned short u16;
typedef unsigned char u8;

#define FULL_MASK 0xffffffffu
#define N_REG 9

// ------------------------------------------------------------------------------------------------
// Small helpers

__device__ __forceinline__ u32 min3_u32(u32 a, u32 b, u32 c) {
#if defined(__CUDA_ARCH__) && (__CUDA_ARCH__ >= 900) && defined(__CUDACC_VER_MAJOR__) && (__CUDACC_VER_MAJOR__ >= 12)
  return __vimin3_u32(a, b, c);  // one VIMNMX3 on Hopper
#else
  return min(min(a, b), c);
#endif
}

// Per 16-bit lane minimum of three packed words.
__device__ __forceinline__ u32 min3_u16x2(u32 a, u32 b, u32 c) {
#if defined(__CUDA_ARCH__) && (__CUDA_ARCH__ >= 900) && defined(__CUDACC_VER_MAJOR__) && (__CUDACC_VER_MAJOR__ >= 12)
  return __vimin3_u16x2(a, b, c);
#else
  return __vminu2(__vminu2(a, b), c);
#endif
}

__device__ __forceinline__ float nan_f32() { return __int_as_float(0x7fc00000); }

// OpenCV's fixed-point BGR -> grey (companion/core/stereo.py, GREY_COEFFS_Q15).
__device__ __forceinline__ u32 grey_q15(u32 b, u32 g, u32 r) {
  return (3735u * b + 19235u * g + 9798u * r + 16384u) >> 15;
}

// ------------------------------------------------------------------------------------------------
// 1. BGR (or BGRA, or grey, or YUYV) side-by-side frame -> two grey eye images.
//
// frame: uint8 (IMG_H, 2*IMG_W, CH), C-contiguous. out_l/out_r: uint8 rows of PITCH bytes.
// Grid (ceil(IMG_W/4 / blockDim.x), rows, 2) from row y_off: one thread converts 4 consecutive pixels of one eye
// row, so it stores one aligned 32-bit word (PITCH is a multiple of 16; bytes past IMG_W land in the
// row padding, which holds no image data). SWAP: the staging copy swapped R and B (the host copied
// the frame with OpenCV's parallel BGR->RGB shuffle), so the weights are applied in RGB order.
// CH 2 is YUYV (Y0 U Y1 V): the grey is the luma byte of each pixel, as companion.core.stereo.to_grey
// takes it.

template <int CH, bool SWAP>
__device__ __forceinline__ u32 grey_px(u32 c0, u32 c1, u32 c2) {
  return SWAP ? grey_q15(c2, c1, c0) : grey_q15(c0, c1, c2);
}

template <int CH, bool SWAP>
__device__ __forceinline__ void grey_body(const u8* __restrict__ frame, u8* __restrict__ out_l,
                                          u8* __restrict__ out_r, int y_off) {
  const int x = 4 * (blockIdx.x * blockDim.x + threadIdx.x);
  const int y = y_off + (int)blockIdx.y;
  const int eye = blockIdx.z;
  if (x >= IMG_W) return;
  const u8* src = frame + (size_t)y * (2 * IMG_W * CH) + (size_t)(eye * IMG_W + x) * CH;
  u8* dst = (eye ? out_r : out_l) + (size_t)y * PITCH + x;
  u32 packed = 0;
  if ((IMG_W * CH) % 4 == 0 && x + 4 <= IMG_W) {
    // Every row and eye starts 4-byte aligned, and 4 pixels are CH whole words: vector loads.
    const u32* s = (const u32*)src;
    if (CH == 1) {
      packed = s[0];
    } else if (CH == 2) {
      // bytes: Y0 U0 Y1 V0 | Y2 U2 Y3 V2
      const u32 w0 = s[0], w1 = s[1];
      packed = (w0 & 255u) | ((w0 >> 8) & 0xff00u) | ((w1 & 255u) << 16) | ((w1 << 8) & 0xff000000u);
    } else if (CH == 3) {
      const u32 w0 = s[0], w1 = s[1], w2 = s[2];
      // bytes: B0 G0 R0 B1 | G1 R1 B2 G2 | R2 B3 G3 R3
      packed = grey_px<CH, SWAP>(w0 & 255u, (w0 >> 8) & 255u, (w0 >> 16) & 255u) |
               grey_px<CH, SWAP>(w0 >> 24, w1 & 255u, (w1 >> 8) & 255u) << 8 |
               grey_px<CH, SWAP>((w1 >> 16) & 255u, w1 >> 24, w2 & 255u) << 16 |
               grey_px<CH, SWAP>((w2 >> 8) & 255u, (w2 >> 16) & 255u, w2 >> 24) << 24;
    } else {
      for (int i = 0; i < 4; ++i) {
        const u32 w = s[i];
        packed |= grey_px<CH, SWAP>(w & 255u, (w >> 8) & 255u, (w >> 16) & 255u) << (8 * i);
      }
    }
  } else {
#pragma unroll
    for (int i = 0; i < 4; ++i) {
      if (x + i < IMG_W) {
        const u8* p = src + i * CH;
        const u32 g = (CH <= 2) ? (u32)p[0] : grey_px<CH, SWAP>(p[0], p[1], p[2]);
        packed |= g << (8 * i);
      }
    }
  }
  *(u32*)dst = packed;
}

extern "C" __global__ void grey_c1(const u8* __restrict__ f, u8* __restrict__ l, u8* __restrict__ r, int y_off) {
  grey_body<1, false>(f, l, r, y_off);
}
extern "C" __global__ void grey_c2(const u8* __restrict__ f, u8* __restrict__ l, u8* __restrict__ r, int y_off) {
  grey_body<2, false>(f, l, r, y_off);
}
extern "C" __global__ void grey_c3(const u8* __restrict__ f, u8* __restrict__ l, u8* __restrict__ r, int y_off) {
  grey_body<3, false>(f, l, r, y_off);
}
extern "C" __global__ void grey_c4(const u8* __restrict__ f, u8* __restrict__ l, u8* __restrict__ r, int y_off) {
  grey_body<4, false>(f, l, r, y_off);
}
extern "C" __global__ void grey_c3_rgb(const u8* __restrict__ f, u8* __restrict__ l, u8* __restrict__ r, int y_off) {
  grey_body<3, true>(f, l, r, y_off);
}
extern "C" __global__ void grey_c4_rgb(const u8* __restrict__ f, u8* __restrict__ l, u8* __restrict__ r, int y_off) {
  grey_body<4, true>(f, l, r, y_off);
}

// ------------------------------------------------------------------------------------------------
// 2. Rectification: cv2.remap(src, map_x, map_y, INTER_LINEAR, BORDER_CONSTANT, 0) on uint8, exactly
// as companion.core.rectifier.remap_linear_reference states it (OpenCV 5's float path):
//   x0 = floor(mx), a = mx - x0 (exact), likewise y; p.. = src (0 outside);
//   top = fma(a, p01 - p00, p00); bot = fma(a, p11 - p10, p10); out = sat(rint(fma(b, bot - top, top))).
// raw_*: grey eyes (rows of PITCH bytes); maps: float32 (IMG_H, IMG_W); rect_*: rows of PITCH bytes.
// Grid (ceil(IMG_W / blockDim.x), rows, 2) from output row y_off.

__device__ __forceinline__ float sample0(const u8* __restrict__ src, int x, int y) {
  return (x >= 0 && x < IMG_W && y >= 0 && y < IMG_H) ? (float)src[(size_t)y * PITCH + x] : 0.0f;
}

extern "C" __global__ void remap_linear(const u8* __restrict__ raw_l, const u8* __restrict__ raw_r,
                                        const float* __restrict__ mlx, const float* __restrict__ mly,
                                        const float* __restrict__ mrx, const float* __restrict__ mry,
                                        u8* __restrict__ rect_l, u8* __restrict__ rect_r, int y_off) {
  const int x = blockIdx.x * blockDim.x + threadIdx.x;
  const int y = y_off + (int)blockIdx.y;
  const int eye = blockIdx.z;
  if (x >= IMG_W) return;
  const size_t i = (size_t)y * IMG_W + x;
  const float mx = eye ? mrx[i] : mlx[i];
  const float my = eye ? mry[i] : mly[i];
  const u8* src = eye ? raw_r : raw_l;
  u32 out = 0;
  // Outside this box all four taps are outside the image and the result is exactly 0; the test also
  // keeps the float -> int conversions below in range (and sends NaN to 0).
  if (mx >= -2.0f && mx <= (float)IMG_W + 1.0f && my >= -2.0f && my <= (float)IMG_H + 1.0f) {
    const float fx = floorf(mx), fy = floorf(my);
    const float a = mx - fx, b = my - fy;
    const int x0 = (int)fx, y0 = (int)fy;
    const float p00 = sample0(src, x0, y0), p01 = sample0(src, x0 + 1, y0);
    const float p10 = sample0(src, x0, y0 + 1), p11 = sample0(src, x0 + 1, y0 + 1);
    const float top = fmaf(a, p01 - p00, p00);
    const float bot = fmaf(a, p11 - p10, p10);
    const float s = fmaf(b, bot - top, top);
    const int v = __float2int_rn(s);  // round half to even, like np.rint
    out = (u32)min(max(v, 0), 255);
  }
  (eye ? rect_r : rect_l)[(size_t)y * PITCH + x] = (u8)out;
}

// ------------------------------------------------------------------------------------------------
// 3. Region finalisation: per-region histograms of integer disparity -> the 9 robust depths.
//
// hist (9 * NDISP u32, region-major) holds, per region, how many valid pixels have each disparity.
// For region i with n valid pixels of area A: fraction = n / A (float64); unknown (NaN) when n == 0 or
// fraction < min_valid; else k = max(1, ceil(pct * n / 100)) and d = the k-th LARGEST disparity, whose
// depth z = fb / d in float32 (d == 0 -> +inf) is the k-th smallest depth; result min(z, max_depth).
// This is companion.core.regions.reduce_regions_from_disparity, operation for operation.
// Runs in one block (>= 9 warps not required: warps loop over regions). `hs` is shared scratch of
// 9 * NDISP u32 already holding the histogram.

__device__ __forceinline__ u32 region_area(int reg) {
  const int rb = reg / 3, cb = reg % 3;
  const int h = rb == 0 ? RE1 : (rb == 1 ? RE2 - RE1 : IMG_H - RE2);
  const int w = cb == 0 ? CE1 : (cb == 1 ? CE2 - CE1 : IMG_W - CE2);
  return (u32)(h * w);
}

__device__ void finalize_regions(const u32* hs, double* __restrict__ result, float fb, double pct,
                                 double min_valid, double max_depth) {
  const int lane = threadIdx.x & 31;
  const int warp = threadIdx.x >> 5;
  const int nwarps = blockDim.x >> 5;
  for (int reg = warp; reg < N_REG; reg += nwarps) {
    const u32* h = hs + reg * NDISP;
    u32 n = 0;
    for (int d = lane; d < NDISP; d += 32) n += h[d];
#pragma unroll
    for (int off = 16; off > 0; off >>= 1) n += __shfl_xor_sync(FULL_MASK, n, off);
    const double frac = (double)n / (double)region_area(reg);
    double depth = (double)nan_f32();
    if (n > 0 && !(frac < min_valid)) {
      const double kd = ceil(pct * (double)n / 100.0);
      const u32 k = kd < 1.0 ? 1u : (u32)kd;
      // Walk the disparities from the largest down, 32 at a time, with a warp prefix sum.
      u32 before = 0;
      int found = -1;
      for (int top = NDISP - 1; top >= 0 && found < 0; top -= 32) {
        const int d = top - lane;
        const u32 v = d >= 0 ? h[d] : 0u;
        u32 incl = v;
#pragma unroll
        for (int off = 1; off < 32; off <<= 1) {
          const u32 t = __shfl_up_sync(FULL_MASK, incl, off);
          if (lane >= off) incl += t;
        }
        const unsigned hit = __ballot_sync(FULL_MASK, before + incl >= k);
        if (hit) found = top - (__ffs(hit) - 1);
        before += __shfl_sync(FULL_MASK, incl, 31);
      }
      const float z = found == 0 ? __int_as_float(0x7f800000) : __fdiv_rn(fb, (float)found);
      depth = (double)z < max_depth ? (double)z : max_depth;
    }
    if (lane == 0) {
      result[reg] = depth;
      result[N_REG + reg] = frac;
    }
  }
}

// Called by every thread of every block after its histogram reached `hist_g` (or with nothing to add):
// the last of `total_blocks` blocks to arrive (over all the launches of one frame, which run in order) copies the global histogram into shared `hs`, zeroes it and the counter for
// the next frame (so no per-frame memset launch is needed), and computes the 9 results.
__device__ __forceinline__ void last_block_finalize(u32* hs, u32* __restrict__ hist_g, u32* __restrict__ counter,
                                                    u32 total_blocks, int* flag, double* __restrict__ result,
                                                    float fb, double pct, double min_valid, double max_depth) {
  __threadfence();  // this block's histogram atomics are visible before its ticket
  __syncthreads();
  if (threadIdx.x == 0) {
    const u32 ticket = atomicAdd(counter, 1u);
    *flag = ticket == total_blocks - 1;  // blocks of every launch of this frame (row bands)
  }
  __syncthreads();
  if (!*flag) return;
  __threadfence();
  for (int i = threadIdx.x; i < N_REG * NDISP; i += blockDim.x) {
    hs[i] = __ldcg(hist_g + i);  // L2 (where the atomics landed), not a stale L1 line
    hist_g[i] = 0u;
  }
  if (threadIdx.x == 0) *counter = 0u;
  __syncthreads();
  finalize_regions(hs, result, fb, pct, min_valid, max_depth);
}

// ------------------------------------------------------------------------------------------------
// 4. Fast SAD block matching with the region histograms fused in.
//
// One block owns a tile of TXO output columns x [x0, x0 + TXO) and `rows` output rows, and walks down
// the rows. It keeps, for CPAD = TXO + 2*RAD columns X = x0 - RAD + c and every disparity d, the
// vertical column sum cs(X, d) = sum over the BLK rows of the window of |L(y, X) - R(y, X - d)|,
// updated per row by adding the row that enters the window and subtracting the row that leaves it
// (never recomputing the window). Per output row:
//   V  thread (c, g) updates cs for column c and GQ quads of disparities, 4 absolute differences per
//      instruction (__vabsdiffu4), two disparities per 32-bit word (16-bit lanes, no carries since
//      every sum is < 2^16), and stores them to shared memory;
//   H  thread (pair dp, run) slides a BLK-wide running sum along its run of columns: the window cost
//      C(x, d) = sum of cs over the BLK columns, one add and one subtract per step;
//   M  MS threads per column x find d* = argmin C with ties to the largest d (the minimum of the key
//      cost << 16 | (0xFFFF - d)), then the smallest cost outside d*-1..d*+1 for the uniqueness test
//      (the three excluded costs are overwritten with 0xFFFF in shared memory and the packed minimum
//      is taken again), the texture sum, the disparity, and the region histogram (run-length
//      aggregated per thread down the column before any shared atomic).
// Input rows live in a ring of NR = BLK + 1 shared rows (the entering and the leaving row), each
// prefetched into registers one row ahead so that the global load latency hides behind the compute.
// Shared memory (static, < 48 KB): see struct SmemFast; plan.py computes the same size.

struct SmemFast {
  u32 ring[NR][LWW + RWW];              // per row: L words [0, LWW), R words [LWW, LWW + RWW)
  alignas(16) u32 cs[CPAD * ROWW];      // column sums, [c][pair], two 16-bit disparities per word
  alignas(16) u32 cost[TXO * CSTR];     // window costs, [x][pair]
  u32 tcs[CPAD];                        // texture column sums
  u32 hist[N_REG * NDISP];              // block histogram, region-major; also the finaliser's scratch
  int flag;
};  // 16-byte members: phase V stores and phase M loads are 128-bit (ROWW, CSTR are multiples of 4)

template <bool WD, bool RG>
__device__ __forceinline__ void sad_fast_body(const u8* __restrict__ rl, const u8* __restrict__ rr,
                                              short* __restrict__ disp, u32* __restrict__ hist_g,
                                              u32* __restrict__ counter, double* __restrict__ result,
                                              int y_begin, int y_end, int rows, u32 total_blocks, u32 uniq,
                                              u32 texmin, float fb, double pct, double min_valid,
                                              double max_depth) {
  __shared__ SmemFast sm;
  const int tid = threadIdx.x;
  const int x0 = X_START + (int)blockIdx.x * TXO;
  const int y0 = y_begin + (int)blockIdx.y * rows;  // this launch's output rows: [y_begin, y_end)
  const int y1 = min(y0 + rows, y_end);
  const int X0 = x0 - RAD;                  // column of c = 0
  const int LA = (X0 - 1) & ~3;             // first byte of the L part (one extra column: texture)
  const int RA = (X0 - (NDISP - 1)) & ~3;   // first byte of the R part
  const int nin = (x0 < X_END && y0 < y1) ? (y1 - y0) + 2 * RAD : 0;  // input rows to stream

  if (RG) {
    for (int i = tid; i < N_REG * NDISP; i += NT) sm.hist[i] = 0u;
  }

  // ---- phase V constants: thread (vc, vg)
  const int vc = tid % CPAD;
  const int vg = tid / CPAD;
  const int vLpos = X0 + vc - LA;  // byte of L(X) in the L part
  // Byte position of R(X - 4q - 3) for q = vg*GQ; quad k of this thread is 4k bytes lower.
  const int P0 = X0 + vc - 4 * (vg * GQ) - 3 - RA;
  const int wbase = P0 >> 2;
  const int ob = P0 & 3;
  // __byte_perm selector putting R(X - 4q - j) into byte j: source byte ob + 3 - j of (hi:lo).
  const u32 rsel = (u32)((ob + 3) | ((ob + 2) << 4) | ((ob + 1) << 8) | (ob << 12));
  u32 cs[2 * GQ];
#pragma unroll
  for (int k = 0; k < 2 * GQ; ++k) cs[k] = 0u;
  u32 tcs = 0u;

  // ---- phase H constants: thread (hdp, hrun)
  const int hdp = tid % DP2;
  const int hrun = tid / DP2;
  const int hi0 = hrun * HK;
  const int hi1 = min(min(hi0 + HK, TXO), X_END - x0);  // no window costs past the valid columns

  // ---- phase M constants: thread (mxi, ms); all threads take part (shuffles), only `mact` write.
  const int mxi_raw = tid / MS;
  const int ms = tid % MS;
  const bool mact = mxi_raw < TXO && x0 + mxi_raw < X_END;
  const int mxi = min(mxi_raw, TXO - 1);
  const int mx = x0 + mxi;
  const int mcb = mx < CE1 ? 0 : (mx < CE2 ? 1 : 2);
  int run_bin = -1;
  u32 run_cnt = 0u;

  // ---- row streaming
  u32 pre[LDPT];
  auto load_row = [&](int Y) {
    const u32* gl = (const u32*)(rl + (size_t)Y * PITCH + LA);
    const u32* gr = (const u32*)(rr + (size_t)Y * PITCH + RA);
#pragma unroll
    for (int j = 0; j < LDPT; ++j) {
      const int i = tid + j * NT;
      if (i < LWW) pre[j] = gl[i];
      else if (i < LWW + RWW) pre[j] = gr[i - LWW];
    }
  };
  if (nin > 0) load_row(y0 - RAD);

  for (int it = 0; it < nin; ++it) {
    const int slot_in = it % NR;
    const int slot_out = (it + 1) % NR;  // == (it - BLK) % NR: the row leaving the window
#pragma unroll
    for (int j = 0; j < LDPT; ++j) {
      const int i = tid + j * NT;
      if (i < LWW + RWW) sm.ring[slot_in][i] = pre[j];
    }
    __syncthreads();
    if (it + 1 < nin) load_row(y0 - RAD + it + 1);

    // ---- phase V
    {
      const u8* Lin = (const u8*)&sm.ring[slot_in][0];
      const u32* Rin = &sm.ring[slot_in][LWW];
      const u32 lin = Lin[vLpos];
      const u32 Lrep = lin * 0x01010101u;
      u32 rw[GQ + 1];
#pragma unroll
      for (int j = 0; j <= GQ; ++j) rw[j] = Rin[wbase - GQ + 1 + j];
#pragma unroll
      for (int k = 0; k < GQ; ++k) {
        const u32 ad = __vabsdiffu4(Lrep, __byte_perm(rw[GQ - 1 - k], rw[GQ - k], rsel));
        cs[2 * k] += __byte_perm(ad, 0u, 0x4140);      // d = 4q, 4q+1
        cs[2 * k + 1] += __byte_perm(ad, 0u, 0x4342);  // d = 4q+2, 4q+3
      }
      if (texmin > 0 && vg == 0) {
        const u32 lp = Lin[vLpos - 1];
        tcs += lin > lp ? lin - lp : lp - lin;
      }
      if (it >= BLK) {
        const u8* Lout = (const u8*)&sm.ring[slot_out][0];
        const u32* Rout = &sm.ring[slot_out][LWW];
        const u32 lout = Lout[vLpos];
        const u32 Lrep_o = lout * 0x01010101u;
#pragma unroll
        for (int j = 0; j <= GQ; ++j) rw[j] = Rout[wbase - GQ + 1 + j];
#pragma unroll
        for (int k = 0; k < GQ; ++k) {
          const u32 ad = __vabsdiffu4(Lrep_o, __byte_perm(rw[GQ - 1 - k], rw[GQ - k], rsel));
          cs[2 * k] -= __byte_perm(ad, 0u, 0x4140);
          cs[2 * k + 1] -= __byte_perm(ad, 0u, 0x4342);
        }
        if (texmin > 0 && vg == 0) {
          const u32 lp = Lout[vLpos - 1];
          tcs -= lout > lp ? lout - lp : lp - lout;
        }
      }
    }

    if (it < 2 * RAD) continue;  // still filling the first window: no output row yet (block-uniform)
    const int y = y0 - RAD + it - RAD;

    // publish the column sums
    {
      u32* dst = &sm.cs[vc * ROWW + 2 * vg * GQ];
#if (2 * GQ) % 4 == 0
#pragma unroll
      for (int k = 0; k < 2 * GQ; k += 4) *(uint4*)(dst + k) = make_uint4(cs[k], cs[k + 1], cs[k + 2], cs[k + 3]);
#else
#pragma unroll
      for (int k = 0; k < 2 * GQ; k += 2) *(uint2*)(dst + k) = make_uint2(cs[k], cs[k + 1]);
#endif
      if (texmin > 0 && vg == 0) sm.tcs[vc] = tcs;
    }
    __syncthreads();

    // ---- phase H: running horizontal window sums
    if (hrun < HRUNS && hi0 < hi1) {
      u32 acc = 0u;
#pragma unroll
      for (int j = 0; j < BLK; ++j) acc += sm.cs[(hi0 + j) * ROWW + hdp];
      sm.cost[hi0 * CSTR + hdp] = acc;
#pragma unroll
      for (int i = 1; i < HK; ++i) {
        if (hi0 + i < hi1) {
          acc += sm.cs[(hi0 + i + 2 * RAD) * ROWW + hdp];
          acc -= sm.cs[(hi0 + i - 1) * ROWW + hdp];
          sm.cost[(hi0 + i) * CSTR + hdp] = acc;
        }
      }
    }
    __syncthreads();

    // ---- phase M: winner, uniqueness, texture, output, histogram
    {
      u32* crow = &sm.cost[mxi * CSTR];
      // Thread ms owns the pair words 4*(ms + MS*k) + j (k < MSW/4, j < 4): interleaved so that the
      // MS threads of one column hit different banks with their 16-byte loads.
      u32 best = 0xffffffffu;
#pragma unroll
      for (int k = 0; k < MSW / 4; ++k) {
        const uint4 v = *(const uint4*)(crow + 4 * (ms + MS * k));
        const u32 w4[4] = {v.x, v.y, v.z, v.w};
#pragma unroll
        for (int j = 0; j < 4; ++j) {
          // Local index l = 2*(4k + j) + h orders this thread's disparities like d does; the key's low
          // half is 0xFFFF - l so that the minimum key is the smallest cost, then the largest l.
          const u32 l = 2u * (4u * k + j);
          const u32 klo = w4[j] * 0x10000u + (0xffffu - l);
          const u32 khi = (w4[j] & 0xffff0000u) | (0xffffu - l - 1u);
          best = min3_u32(best, klo, khi);
        }
      }
      {
        // local index -> disparity, then the key over all MS threads
        const u32 l = 0xffffu - (best & 0xffffu);
        const u32 kk = l >> 3, j = (l >> 1) & 3u, h = l & 1u;
        const u32 d = 2u * (4u * (ms + MS * kk) + j) + h;
        best = (best & 0xffff0000u) | (0xffffu - d);
      }
#pragma unroll
      for (int off = 1; off < MS; off <<= 1) best = min(best, __shfl_xor_sync(FULL_MASK, best, off));
      const u32 cstar = best >> 16;
      const int dstar = (int)(0xffffu - (best & 0xffffu));

      // Uniqueness: the smallest cost with |d - d*| > 1.
      if (mact && ms == 0) {
        u16* c16 = (u16*)crow;  // little-endian: disparity d is half-word d
        c16[dstar] = 0xffffu;
        if (dstar > 0) c16[dstar - 1] = 0xffffu;
        if (dstar + 1 < NDISP) c16[dstar + 1] = 0xffffu;
      }
      __syncwarp();
      u32 m2 = 0xffffffffu;
#pragma unroll
      for (int k = 0; k < MSW / 4; ++k) {
        const uint4 v = *(const uint4*)(crow + 4 * (ms + MS * k));
        m2 = min3_u16x2(m2, v.x, v.y);
        m2 = min3_u16x2(m2, v.z, v.w);
      }
      m2 = min(m2 & 0xffffu, m2 >> 16);
#pragma unroll
      for (int off = 1; off < MS; off <<= 1) m2 = min(m2, __shfl_xor_sync(FULL_MASK, m2, off));
      // 0xFFFF marks "no such disparity": every real cost is <= 255 * BLK^2 < 0xFFFF here.
      bool reject = m2 != 0xffffu && 100u * m2 <= (100u + uniq) * cstar;

      if (texmin > 0) {
        u32 ts = 0u;
#pragma unroll
        for (int jj = 0; jj < (BLK + MS - 1) / MS; ++jj) {
          const int j = ms + jj * MS;
          if (j < BLK) ts += sm.tcs[mxi + j];
        }
#pragma unroll
        for (int off = 1; off < MS; off <<= 1) ts += __shfl_xor_sync(FULL_MASK, ts, off);
        reject = reject || ts < texmin;
      }

      if (mact && ms == 0) {
        const int dres = reject ? -1 : dstar;
        if (WD) disp[(size_t)y * IMG_W + mx] = (short)dres;
        if (RG && dres >= 0) {
          const int rb = y < RE1 ? 0 : (y < RE2 ? 1 : 2);
          const int bin = (rb * 3 + mcb) * NDISP + dres;
          if (bin == run_bin) {
            ++run_cnt;
          } else {
            if (run_cnt) atomicAdd(&sm.hist[run_bin], run_cnt);
            run_bin = bin;
            run_cnt = 1u;
          }
        }
      }
    }
  }

  if (RG) {
    if (run_cnt) atomicAdd(&sm.hist[run_bin], run_cnt);
    __syncthreads();
    for (int i = tid; i < N_REG * NDISP; i += NT) {
      const u32 v = sm.hist[i];
      if (v) atomicAdd(hist_g + i, v);
    }
    last_block_finalize(sm.hist, hist_g, counter, total_blocks, &sm.flag, result, fb, pct, min_valid,
                        max_depth);
  }
}

#define SAD_FAST_ARGS                                                                                \
  const u8 *__restrict__ rl, const u8 *__restrict__ rr, short *__restrict__ disp, u32 *__restrict__ hist_g, \
      u32 *__restrict__ counter, double *__restrict__ result, int y_begin, int y_end, int rows,            \
      u32 total_blocks, u32 uniq, u32 texmin, float fb, double pct, double min_valid, double max_depth
#define SAD_FAST_PASS                                                                                 \
  rl, rr, disp, hist_g, counter, result, y_begin, y_end, rows, total_blocks, uniq, texmin, fb, pct, min_valid, \
      max_depth

extern "C" __global__ void __launch_bounds__(NT) sad_fast_regions(SAD_FAST_ARGS) {
  sad_fast_body<false, true>(SAD_FAST_PASS);
}
extern "C" __global__ void __launch_bounds__(NT) sad_fast_regions_disp(SAD_FAST_ARGS) {
  sad_fast_body<true, true>(SAD_FAST_PASS);
}
extern "C" __global__ void __launch_bounds__(NT) sad_fast_disp(SAD_FAST_ARGS) {
  sad_fast_body<true, false>(SAD_FAST_PASS);
}

// ------------------------------------------------------------------------------------------------
// 5. Fallback SAD kernel for configurations the fast kernel does not cover (window costs that do not
// fit 16 bits: BLK > 15, or tiles that do not fit 48 KB of shared memory). One thread per valid pixel,
// the whole window per disparity: slow but exact. The uniqueness minimum is found in the same pass:
// when d becomes the best, the smallest cost at or below d - 2 is the prefix minimum two steps back,
// and costs at or above best + 2 are collected afterwards.

extern "C" __global__ void sad_naive(const u8* __restrict__ rl, const u8* __restrict__ rr,
                                     short* __restrict__ disp, u32 uniq, u32 texmin) {
  const int x = X_START + (int)(blockIdx.x * blockDim.x + threadIdx.x);
  const int y = Y_START + (int)blockIdx.y;
  if (x >= X_END || y >= Y_END) return;
  const u32 INF = 0xffffffffu;
  u32 best = INF, left = INF, right = INF, p1 = INF, p2 = INF;
  int dbest = 0;
  for (int d = 0; d < NDISP; ++d) {
    u32 c = 0;
    for (int i = -RAD; i <= RAD; ++i) {
      const u8* lrow = rl + (size_t)(y + i) * PITCH;
      const u8* rrow = rr + (size_t)(y + i) * PITCH;
      for (int j = -RAD; j <= RAD; ++j) {
        const int a = lrow[x + j], b = rrow[x + j - d];
        c += (u32)(a > b ? a - b : b - a);
      }
    }
    if (c <= best) {  // ties go to the larger d
      best = c;
      dbest = d;
      left = p2;
      right = INF;
    } else if (d >= dbest + 2) {
      right = min(right, c);
    }
    p2 = p1;
    p1 = min(p1, c);
  }
  const u32 m2 = min(left, right);
  bool reject = m2 != INF && 100ull * m2 <= (100ull + uniq) * (unsigned long long)best;
  if (texmin > 0) {
    u32 t = 0;
    for (int i = -RAD; i <= RAD; ++i) {
      const u8* lrow = rl + (size_t)(y + i) * PITCH;
      for (int j = -RAD; j <= RAD; ++j) {
        const int a = lrow[x + j], b = lrow[x + j - 1];
        t += (u32)(a > b ? a - b : b - a);
      }
    }
    reject = reject || t < texmin;
  }
  disp[(size_t)y * IMG_W + x] = (short)(reject ? -1 : dbest);
}

// ------------------------------------------------------------------------------------------------
// 6. Region histograms from a disparity image (after sad_naive, or the unfused variant of the fast
// kernel): one block per valid row band, then the same last-block finalisation.

struct SmemRegions {
  u32 hist[N_REG * NDISP];
  int flag;
};

extern "C" __global__ void regions_from_disp(const short* __restrict__ disp, u32* __restrict__ hist_g,
                                             u32* __restrict__ counter, double* __restrict__ result,
                                             int rows, float fb, double pct, double min_valid,
                                             double max_depth) {
  __shared__ SmemRegions sm;
  for (int i = threadIdx.x; i < N_REG * NDISP; i += blockDim.x) sm.hist[i] = 0u;
  __syncthreads();
  const int ya = Y_START + (int)blockIdx.x * rows;
  const int yb = min(ya + rows, Y_END);
  for (int y = ya; y < yb; ++y) {
    const int rb = y < RE1 ? 0 : (y < RE2 ? 1 : 2);
    for (int x = X_START + (int)threadIdx.x; x < X_END; x += blockDim.x) {
      const int d = disp[(size_t)y * IMG_W + x];
      if (d >= 0) {
        const int cb = x < CE1 ? 0 : (x < CE2 ? 1 : 2);
        atomicAdd(&sm.hist[(rb * 3 + cb) * NDISP + d], 1u);
      }
    }
  }
  __syncthreads();
  for (int i = threadIdx.x; i < N_REG * NDISP; i += blockDim.x) {
    const u32 v = sm.hist[i];
    if (v) atomicAdd(hist_g + i, v);
  }
  last_block_finalize(sm.hist, hist_g, counter, gridDim.x, &sm.flag, result, fb, pct, min_valid, max_depth);
}

// ------------------------------------------------------------------------------------------------
// 7. Disparity preview for overlays: float32 (ceil(IMG_H/f), ceil(IMG_W/f)), each cell the LARGEST
// valid disparity of its f x f block (the nearest surface: the conservative summary) times `scale`
// (1 for the SAD matcher's integer pixels, 1/16 for the SGM matcher's fixed point), NaN when none.

// One pixel of the map's eroded disparity (k = 0: the pixel itself; -1 invalid, the smallest): the
// smallest of its row's pixels x - k .. x + k inside the image, unless it stands more than an eighth
// nearer than some pixel within 2k on each side (a thin upright thing, not a smeared edge); then the
// larger of that and the nearest within one column of it in the row above and the row below, capped
// at itself (a bar is tall; a lone false match is not). CPU reference: RowErosion in
// companion/core/blocks.py.
__device__ __forceinline__ int eroded_px(const short* __restrict__ disp, int x, int y, int k) {
  const short* row = disp + (size_t)y * IMG_W;
  const int d0 = row[x];
  int m = d0;
  for (int j = max(0, x - k); j <= min(IMG_W - 1, x + k); ++j) m = min(m, (int)row[j]);
  if (m == d0) return m;  // k = 0, or nothing nearer to take off
  bool left = false, right = false;
  for (int j = max(0, x - 2 * k); j < x; ++j) left |= 8 * (int)row[j] < 7 * d0;
  for (int j = x + 1; j <= min(IMG_W - 1, x + 2 * k); ++j) right |= 8 * (int)row[j] < 7 * d0;
  if (!(left && right)) return m;
  int s = d0;
  for (int dy = -1; dy <= 1; dy += 2) {
    if (y + dy < 0 || y + dy >= IMG_H) continue;
    const short* nb = row + dy * IMG_W;
    int n = -1;
    for (int j = max(0, x - 1); j <= min(IMG_W - 1, x + 1); ++j) n = max(n, (int)nb[j]);
    s = min(s, n);
  }
  return max(m, s);
}

// The block's largest eroded disparity (eroded_px), times `scale`; NaN when none is valid.
__device__ __forceinline__ float eroded_block_max(const short* __restrict__ disp, int f, int ox, int oy,
                                                  float scale, int k) {
  int best = -1;
  for (int y = oy * f; y < min(oy * f + f, IMG_H); ++y)
    for (int x = ox * f; x < min(ox * f + f, IMG_W); ++x) best = max(best, eroded_px(disp, x, y, k));
  return best >= 0 ? (float)best * scale : nan_f32();
}

extern "C" __global__ void preview_max(const short* __restrict__ disp, float* __restrict__ out, int f, int ow,
                                       int oh, float scale) {
  const int ox = blockIdx.x * blockDim.x + threadIdx.x;
  const int oy = blockIdx.y;
  if (ox >= ow || oy >= oh) return;
  out[(size_t)oy * ow + ox] = eroded_block_max(disp, f, ox, oy, scale, 0);
}

// ------------------------------------------------------------------------------------------------
// 8. The local map's blocks with planner.block_erode_px = k > 0: as preview_max, of the eroded
// disparity (eroded_px). CPU reference: BlockMax(erode_px=k) in companion/core/blocks.py.

extern "C" __global__ void memory_max(const short* __restrict__ disp, float* __restrict__ out, int f, int ow,
                                      int oh, float scale, int k) {
  const int ox = blockIdx.x * blockDim.x + threadIdx.x;
  const int oy = blockIdx.y;
  if (ox >= ow || oy >= oh) return;
  out[(size_t)oy * ow + ox] = eroded_block_max(disp, f, ox, oy, scale, k);
}
