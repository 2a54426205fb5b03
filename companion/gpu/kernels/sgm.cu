// CUDA kernels of the `cupy` backend's semi-global matcher: 9x7 census, SGM path aggregation, winner with
// uniqueness, sub-pixel and the right view's disparity from the same sums, left-right check, 3x3 median and
// the 9-region robust minimum. Compiled once per estimator with NVRTC through cupy.RawModule;
// companion/gpu/plan.py (plan_sgm, sgm_defines) prepends the #defines that fix the image size, the
// disparity count, the lane layout and the number of paths, so every loop bound is a compile-time constant.
//
// The rules reproduced bit for bit are those of companion/core/disparity/sgm.py (the NumPy reference);
// everything is integer arithmetic except the region depth (float32 division f*B/d, as on the CPU).
// P1, P2, the uniqueness ratio, the left-right tolerance and the median switch are kernel arguments.
//
// Lane layout. One line (an image row, column or diagonal walked by one path) is owned by LPL lanes of a
// warp (LPW = 32 / LPL lines per warp). Lane l of a line holds WPL groups of 4 disparities:
// group w covers d = 4 * (l + LPL * w) + j, j = 0..3 (DPAD = 4 * LPL * WPL >= NDISP, the padding
// disparities are excluded). A group's four path costs are two 32-bit words of two 16-bit lanes,
// A = (d0, d1) and B = (d2, d3), so that one 16x2 min handles two disparities. Path costs are <= 62 + P2
// <= 255; an excluded disparity (d > x, or d >= NDISP) is held at 255, which never changes a minimum
// (proof in docs/gpu_notes.md), so the recurrence needs no masks. Costs are stored as one byte per
// (pixel, disparity) in one volume per path: [y][x][DPAD], 4 bytes per lane and group.
//
// Passes: sgm_census (and the reset of the right view's disparity keys); sgm_paths (every direction in one
// launch, each into its own volume); sgm_wta (per run of pixels of a row: the sum of all paths, the winner,
// uniqueness, sub-pixel, and the right view's disparity by a shift register along d merged by atomicMin);
// sgm_post (left-right check, median, the near-range check against the coarse pair's disparity, disparity
// image, region histograms, and in the last block the 9 depths); sgm_shrink makes the coarse pair, which a
// second module of these kernels, built for its size, matches first.
//
// Portability: nothing needs more than sm_53. __reduce_min_sync (sm_80+) and the Hopper DPX 3-way minimum
// (sm_90, CUDA 12+) are used where present, with shuffles and __vminu2 otherwise. Static shared memory
// < 48 KB per block.

typedef unsigned int u32;
typedef unsigned short u16;
typedef unsigned char u8;
typedef unsigned long long u64;

#define FULL_MASK 0xffffffffu
#define N_REG 9
#define KEY_INF 0xffffffffu
#define LPW (32 / LPL)
#define DPAD (4 * LPL * WPL)
#define CEN_HW 4
#define CEN_HH 3
#define PAIR_255 0x00ff00ffu
// Census images: [3][IMG_H][CEN_STR] u64: the left eye, the right eye, and the right eye again one element
// later (column x at CEN_PAD + x + 1), so that any four consecutive right census values start a 16-byte
// pair in one of the two copies (two 16-byte loads instead of four 8-byte ones, each filling twice as much
// of the 32-byte sectors it touches). Image column x sits at CEN_PAD + x. The CEN_PAD columns left of the
// image (zeroed once by the host, never written) let sgm_paths read the right census of x - d for every
// d < DPAD without a bounds test: those disparities are excluded and their costs unused. CEN_STR is even
// (a row starts 16-byte aligned) with room for the shifted copy's last column.
#define CEN_PAD DPAD
#ifndef SGM_PF
#define SGM_PF 2  // sgm_paths: steps between a step's census loads and its recurrence (2 or 4; plan.py)
#endif
#define CEN_STR ((IMG_W + CEN_PAD + 2) / 2 * 2)
#define CEN_IMG ((size_t)IMG_H * CEN_STR)

// ------------------------------------------------------------------------------------------------
// helpers

__device__ __forceinline__ u32 min2x16(u32 a, u32 b) { return __vminu2(a, b); }

__device__ __forceinline__ u32 min3x16(u32 a, u32 b, u32 c) {
#if defined(__CUDA_ARCH__) && (__CUDA_ARCH__ >= 900) && defined(__CUDACC_VER_MAJOR__) && (__CUDACC_VER_MAJOR__ >= 12)
  return __vimin3_u16x2(a, b, c);
#else
  return __vminu2(__vminu2(a, b), c);
#endif
}

__device__ __forceinline__ u32 min3u(u32 a, u32 b, u32 c) {
#if defined(__CUDA_ARCH__) && (__CUDA_ARCH__ >= 900) && defined(__CUDACC_VER_MAJOR__) && (__CUDACC_VER_MAJOR__ >= 12)
  return __vimin3_u32(a, b, c);
#else
  return min(min(a, b), c);
#endif
}

__device__ __forceinline__ u32 popc64(u64 a) { return (u32)__popc((u32)a) + (u32)__popc((u32)(a >> 32)); }

__device__ __forceinline__ float sgm_nan() { return __int_as_float(0x7fc00000); }

// Minimum of v over the LPL lanes of this lane's line (every lane of the warp must call it).
__device__ __forceinline__ u32 line_min(u32 v) {
#if defined(__CUDA_ARCH__) && (__CUDA_ARCH__ >= 800)
  if (LPW <= 2) {
    // one REDUX per line of the warp, each over the whole warp with the other lines neutral
    u32 res = 0;
#pragma unroll
    for (int g = 0; g < LPW; ++g) {
      const u32 r = __reduce_min_sync(FULL_MASK, ((int)(threadIdx.x & 31) / LPL == g) ? v : KEY_INF);
      if ((int)(threadIdx.x & 31) / LPL == g) res = r;
    }
    return res;
  }
#endif
#pragma unroll
  for (int off = LPL / 2; off > 0; off >>= 1) v = min(v, __shfl_xor_sync(FULL_MASK, v, off, LPL));
  return v;
}

// ------------------------------------------------------------------------------------------------
// 1. Census 9x7 of both rectified eyes (reference rule 1), from a shared-memory tile, for image rows
// [y_lo, y_hi) (the estimator runs each row band's share as soon as its rectified rows, +-3, are there, so
// that the first bands' census overlaps the later bands' upload). Block (CT_W, CT_H) threads, each CT_R rows
// of one column (a block: CT_W x CT_H * CT_R pixels, so that the tile's halo and the block's start are paid
// for CT_R pixels), grid (ceil(IMG_W / CT_W), ceil((y_hi - y_lo) / (CT_H * CT_R)), 2) (plan.py: CT_* come
// from sgm_defines). A thread walks the CT_R + 6 tile rows its pixels see once, each row's 9 values in
// registers, comparing them with every centre whose window holds that row. Outside the image the tile
// holds 0x7fff, which is never below a centre (<= 255): the reference's 0. The left eye's blocks also reset
// the right view's disparity keys of their pixels for this frame (sgm_wta min-reduces into them).

#define CT_ROWS (CT_H * CT_R)
#define CT_TW (CT_W + 2 * CEN_HW)

extern "C" __global__ void __launch_bounds__(CT_W * CT_H) sgm_census(const u8* __restrict__ rl, const u8* __restrict__ rr,
                                                                     u64* __restrict__ cen, u32* __restrict__ drkey,
                                                                     int y_lo, int y_hi) {
  __shared__ short tile[CT_ROWS + 2 * CEN_HH][CT_TW];
  const u8* img = blockIdx.z ? rr : rl;
  const int bx = (int)blockIdx.x * CT_W - CEN_HW, by = y_lo + (int)blockIdx.y * CT_ROWS - CEN_HH;
  const int tid = (int)(threadIdx.y * CT_W + threadIdx.x);
  for (int i = tid; i < (CT_ROWS + 2 * CEN_HH) * CT_TW; i += CT_W * CT_H) {
    const int ty = i / CT_TW, tx = i % CT_TW;
    const int yy = by + ty, xx = bx + tx;
    tile[ty][tx] = (yy >= 0 && yy < IMG_H && xx >= 0 && xx < IMG_W) ? (short)img[(size_t)yy * PITCH + xx] : (short)0x7fff;
  }
  __syncthreads();
  const int x = (int)(blockIdx.x * CT_W + threadIdx.x);
  const int t0 = (int)threadIdx.y * CT_R;  // the first of this thread's rows, in tile rows (window tops)
  const int y0 = y_lo + (int)blockIdx.y * CT_ROWS + t0;
  if (x >= IMG_W || y0 >= y_hi) return;
  int c[CT_R];
  u64 bits[CT_R];
#pragma unroll
  for (int o = 0; o < CT_R; ++o) {
    c[o] = tile[t0 + o + CEN_HH][threadIdx.x + CEN_HW];
    bits[o] = 0;
  }
#pragma unroll
  for (int r = 0; r < CT_R + 2 * CEN_HH; ++r) {
    int q[2 * CEN_HW + 1];
#pragma unroll
    for (int j = 0; j <= 2 * CEN_HW; ++j) q[j] = tile[t0 + r][threadIdx.x + j];
#pragma unroll
    for (int o = 0; o < CT_R; ++o) {
      const int i = r - o;  // the window row of pixel o that tile row r is
      if (i < 0 || i > 2 * CEN_HH) continue;
#pragma unroll
      for (int j = 0; j <= 2 * CEN_HW; ++j) {
        if (i == CEN_HH && j == CEN_HW) continue;
        const int k = i * (2 * CEN_HW + 1) + j - ((i > CEN_HH || (i == CEN_HH && j > CEN_HW)) ? 1 : 0);
        if (q[j] < c[o]) bits[o] |= 1ull << k;
      }
    }
  }
#pragma unroll
  for (int o = 0; o < CT_R; ++o) {
    const int y = y0 + o;
    if (y >= y_hi) break;
    const size_t at = (size_t)y * CEN_STR + CEN_PAD + x;
    cen[blockIdx.z * CEN_IMG + at] = bits[o];
    if (blockIdx.z) cen[2 * CEN_IMG + at + 1] = bits[o];  // the shifted copy
    else drkey[(size_t)y * IMG_W + x] = KEY_INF;
  }
}

// ------------------------------------------------------------------------------------------------
// 2. The path recurrence (reference rule 3) for one step of one line.
//
// L: this lane's path costs at the previous pixel of the line (A/B words per group), updated in place to
// this pixel's. c: this pixel's census costs (0 where excluded), xm: 0x00ff in each excluded 16-bit lane.
// p1x2 = P1 in both 16-bit lanes. A path starts from L = 0 (then t = 0 and L(p) = C(p)).
//
// With m the line's minimum previous cost and t = min(L(d), L(d-1) + P1, L(d+1) + P1, m + P2), every
// term is >= m, so t - m needs no borrow per 16-bit lane and (t - m) + C <= P2 + 62 <= 255 no carry;
// an excluded disparity is then forced to 255 by OR (its value before the OR is <= 255).

struct PathState {
  u32 A[WPL];
  u32 B[WPL];
};

__device__ __forceinline__ void path_step(PathState& L, const u32 (&cA)[WPL], const u32 (&cB)[WPL],
                                          const u32 (&xA)[WPL], const u32 (&xB)[WPL], u32 p1x2, u32 p2) {
  const int li = (int)(threadIdx.x & 31) % LPL;
  u32 mw = min2x16(L.A[0], L.B[0]);
#pragma unroll
  for (int w = 1; w < WPL; ++w) mw = min3x16(mw, L.A[w], L.B[w]);
  // the lane's minimum in both halves (m * 0x10001), then the line's: min commutes with m -> m * 0x10001
  const u32 mm = line_min(min2x16(mw, __byte_perm(mw, 0u, 0x1032)));
  const u32 mp2 = mm + p2 * 0x00010001u;
  // neighbours across lanes: B of the group below (d - 1 of d0), A of the group above (d + 1 of d3)
  u32 lowB[WPL], highA[WPL];
#pragma unroll
  for (int w = 0; w < WPL; ++w) {
    lowB[w] = __shfl_up_sync(FULL_MASK, L.B[w], 1, LPL);
    highA[w] = __shfl_down_sync(FULL_MASK, L.A[w], 1, LPL);
  }
#pragma unroll
  for (int w = 0; w < WPL; ++w) {
    const u32 wrapB = w > 0 ? __shfl_sync(FULL_MASK, L.B[w > 0 ? w - 1 : 0], LPL - 1, LPL) : PAIR_255;
    const u32 wrapA = w + 1 < WPL ? __shfl_sync(FULL_MASK, L.A[w + 1 < WPL ? w + 1 : 0], 0, LPL) : PAIR_255;
    if (li == 0) lowB[w] = wrapB;
    if (li == LPL - 1) highA[w] = wrapA;
  }
#pragma unroll
  for (int w = 0; w < WPL; ++w) {
    const u32 a = L.A[w], b = L.B[w];
    const u32 dnA = __byte_perm(lowB[w], a, 0x5432);  // (d0 - 1, d0)
    const u32 mid = __byte_perm(a, b, 0x5432);        // (d1, d2): d - 1 of B, d + 1 of A
    const u32 upB = __byte_perm(b, highA[w], 0x5432); // (d3, d3 + 1)
    const u32 tA = min2x16(min3x16(a, dnA + p1x2, mid + p1x2), mp2);
    const u32 tB = min2x16(min3x16(b, mid + p1x2, upB + p1x2), mp2);
    L.A[w] = ((tA - mm) + cA[w]) | xA[w];
    L.B[w] = ((tB - mm) + cB[w]) | xB[w];
  }
}

// Census costs of one pixel for this lane's groups. win[w][j] = census of the right pixel x - d0(w) - j
// (any value where that is outside the image). Excluded: d > x or d >= NDISP.
__device__ __forceinline__ void pixel_costs(u64 cL, const u64 (&win)[WPL][4], int x, u32 (&cA)[WPL], u32 (&cB)[WPL],
                                            u32 (&xA)[WPL], u32 (&xB)[WPL]) {
  const int li = (int)(threadIdx.x & 31) % LPL;
#pragma unroll
  for (int w = 0; w < WPL; ++w) {
    const int d0 = 4 * (li + LPL * w);
    if (x >= d0 + 3 && d0 + 3 < NDISP) {  // the usual case: all four included
      // + rather than |: the same (each cost < 2^16), and one IMAD packs it
      cA[w] = popc64(cL ^ win[w][0]) + (popc64(cL ^ win[w][1]) << 16);
      cB[w] = popc64(cL ^ win[w][2]) + (popc64(cL ^ win[w][3]) << 16);
      xA[w] = xB[w] = 0u;
    } else {
      u32 c[4], ex[4];
#pragma unroll
      for (int j = 0; j < 4; ++j) {
        const int d = d0 + j;
        const bool excl = d > x || d >= NDISP;
        c[j] = excl ? 0u : popc64(cL ^ win[w][j]);
        ex[j] = excl ? 0xffu : 0u;
      }
      cA[w] = c[0] | (c[1] << 16);
      cB[w] = c[2] | (c[3] << 16);
      xA[w] = ex[0] | (ex[1] << 16);
      xB[w] = ex[2] | (ex[3] << 16);
    }
  }
}

// One step's loads, issued SGM_PF steps ahead of the recurrence: the left census of the step's pixel and,
// per group, the right census values it does not hold yet (a horizontal walk slides a window of four and
// needs one new value per group; the other walks need all four).
template <int DX, int DY>
struct StepLoads {
  u64 cl;
  u64 r[WPL][DY == 0 ? 1 : 4];
};

// p: the left census of the step's pixel (in the padded layout); the right census of x - d is p[CEN_IMG - d]
// (and p[2 CEN_IMG + 1 - d] in the shifted copy).
template <int DX, int DY>
__device__ __forceinline__ void load_step(const u64* __restrict__ p, int d0, StepLoads<DX, DY>& ld) {
  ld.cl = __ldg(p);
  if (DY == 0) {
    const u64* q = p + CEN_IMG - d0;
#pragma unroll
    for (int w = 0; w < WPL; ++w) ld.r[w][0] = __ldg(q - 4 * LPL * w - (DX > 0 ? 0 : 3));
  } else if (LPL < 32) {
    // two or more lines per warp are neighbouring columns of different parity: from one copy, their
    // 8-byte loads share sectors (measured faster than the pairs at 672x376/64, 16 lanes)
    const u64* q = p + CEN_IMG - d0;
#pragma unroll
    for (int w = 0; w < WPL; ++w)
#pragma unroll
      for (int j = 0; j < 4; ++j) ld.r[w][j] = __ldg(q - 4 * LPL * w - j);
  } else {
    // x - d0 - 3 .. x - d0 as two 16-byte pairs, from the copy where x - d0 - 3 starts a pair: the
    // element index's parity is the address's bit 3 (the buffer is 16-byte aligned, CEN_STR even;
    // groups are 4 elements apart, so every group takes the same copy)
    const u64* q = p + CEN_IMG - d0 - 3;
    if (((size_t)q >> 3) & 1u) q += CEN_IMG + 1;
#pragma unroll
    for (int w = 0; w < WPL; ++w) {
      const ulonglong2* v = (const ulonglong2*)(q - 4 * LPL * w);
      const ulonglong2 a = __ldg(v), b = __ldg(v + 1);
      ld.r[w][3] = a.x;
      ld.r[w][2] = a.y;
      ld.r[w][1] = b.x;
      ld.r[w][0] = b.y;
    }
  }
}

// Walk one line of direction (DX, DY) from (x0, y0) for `len` pixels (`steps` >= len iterations so that all
// lines of the warp keep stepping together; inactive steps store nothing), storing the path costs.
//
// Why it is written this way (sgm_paths is issue-bound: every instruction per step counts): the census
// pointer advances by a constant per step (clamped at the line's last pixel, so that the loads of inactive
// steps stay inside the image) and the loads use constant offsets from it, with no bounds tests (the
// padding); the loop is unrolled by UNR so that the ring of load buffers rotates by name and, on horizontal
// walks, the window of four right census values too, instead of by moves. The census loads of step t are
// issued at step t - SGM_PF (2, or 4 where few warps per scheduler leave the loads' latency exposed:
// plan.py) and its costs computed at step t - 1, so the recurrence (the only loop-carried chain) does not
// wait for memory.
template <int DX, int DY>
__device__ void walk_line(const u64* __restrict__ cen, u8* __restrict__ vol, int x0, int y0, int len, int steps,
                          u32 p1x2, u32 p2) {
  // UNR is a multiple of SGM_PF (the load ring's slot of step s is then s % SGM_PF, known at compile time)
  // and, on rows, of 4 (the window ring)
  constexpr int UNR = DY == 0 ? (SGM_PF > 4 ? SGM_PF : 4) : (SGM_PF > 2 ? SGM_PF : 2);
  constexpr long CSTEP = (long)DY * CEN_STR + DX;           // census elements per step
  constexpr long VSTEP = ((long)DY * IMG_W + DX) * DPAD;    // volume bytes per step
  const int li = (int)(threadIdx.x & 31) % LPL;
  const int d0 = 4 * li;
  const bool any = len > 0;
  const int xs = any ? x0 : 0, ys = any ? y0 : 0;
  const int last = any ? len - 1 : 0;
  const u64* p = cen + (size_t)ys * CEN_STR + CEN_PAD + xs;  // the census of the next step to load
  u32* dst = (u32*)(vol + ((size_t)ys * IMG_W + xs) * DPAD) + li;
  PathState L;
#pragma unroll
  for (int w = 0; w < WPL; ++w) L.A[w] = L.B[w] = 0u;
  // win[w][k]: a horizontal walk's window of right census values, a ring whose slot of value x - d0 - j
  // at step t is (t - j) & 3 going right, (t + j) & 3 going left (other walks load all four per step).
  u64 win[WPL][4];
  u32 cA[WPL], cB[WPL], xA[WPL], xB[WPL];
  {
    const u64* q = p + CEN_IMG - d0;
    u64 cur[WPL][4];  // step 0's right census values, j = 0..3
#pragma unroll
    for (int w = 0; w < WPL; ++w)
#pragma unroll
      for (int j = 0; j < 4; ++j) {
        cur[w][j] = __ldg(q - 4 * LPL * w - j);
        win[w][(DX > 0 ? -j : j) & 3] = cur[w][j];
      }
    pixel_costs(__ldg(p), cur, xs, cA, cB, xA, xB);
  }
  int t_load = 1;  // the step whose loads are issued next
  auto advance = [&]() {
    if (t_load <= last) p += CSTEP;
    ++t_load;
  };
  advance();
  // a ring of SGM_PF steps' loads: step t's in slot t % SGM_PF
  StepLoads<DX, DY> buf[SGM_PF];
#pragma unroll
  for (int i = 1; i < SGM_PF; ++i) {
    load_step<DX, DY>(p, d0, buf[i]);  // steps 1 .. SGM_PF - 1
    advance();
  }
  const int total = (steps + UNR - 1) / UNR * UNR;
  for (int s0 = 0; s0 < total; s0 += UNR) {
#pragma unroll
    for (int q = 0; q < UNR; ++q) {
      const int s = s0 + q;
      load_step<DX, DY>(p, d0, buf[q % SGM_PF]);  // step s + SGM_PF
      advance();
      path_step(L, cA, cB, xA, xB, p1x2, p2);
      if (s < len) {
#pragma unroll
        for (int w = 0; w < WPL; ++w) dst[LPL * w] = __byte_perm(L.A[w], L.B[w], 0x6420);
      }
      dst = (u32*)((u8*)dst + VSTEP);
      // the costs of step s + 1 (its loads are in buf[(q + 1) % SGM_PF])
      const StepLoads<DX, DY>& nx = buf[(q + 1) % SGM_PF];
      u64 cur[WPL][4];
#pragma unroll
      for (int w = 0; w < WPL; ++w) {
        if (DY == 0) {
          const int t = q + 1;  // step s + 1 modulo UNR (= 4)
          if (DX > 0) {
            win[w][t & 3] = nx.r[w][0];
#pragma unroll
            for (int j = 0; j < 4; ++j) cur[w][j] = win[w][(t - j) & 3];
          } else {
            win[w][(t + 3) & 3] = nx.r[w][0];
#pragma unroll
            for (int j = 0; j < 4; ++j) cur[w][j] = win[w][(t + j) & 3];
          }
        } else {
#pragma unroll
          for (int j = 0; j < 4; ++j) cur[w][j] = nx.r[w][DY == 0 ? 0 : j];
        }
      }
      pixel_costs(nx.cl, cur, x0 + DX * (s + 1), cA, cB, xA, xB);
    }
  }
}

// Diagonal line `line` of direction (DX, DY): its first pixel and its length.
template <int DX, int DY>
__device__ __forceinline__ void diagonal_line(int line, int& x0, int& y0, int& len) {
  if (line < IMG_W) {
    x0 = line;
    y0 = DY > 0 ? 0 : IMG_H - 1;
  } else {
    x0 = DX > 0 ? 0 : IMG_W - 1;
    y0 = DY > 0 ? line - IMG_W + 1 : IMG_H - 2 - (line - IMG_W);
  }
  const int lx = DX > 0 ? IMG_W - x0 : x0 + 1;
  const int ly = DY > 0 ? IMG_H - y0 : y0 + 1;
  len = min(lx, ly);
}

__device__ __forceinline__ int warp_max(int v) {
#pragma unroll
  for (int off = 16; off > 0; off >>= 1) v = max(v, __shfl_xor_sync(FULL_MASK, v, off));
  return v;
}

#define TASKS_H ((IMG_H + LPW - 1) / LPW)
#define TASKS_V ((IMG_W + LPW - 1) / LPW)
#define TASKS_D ((IMG_W + IMG_H - 1 + LPW - 1) / LPW)
#define VOL_BYTES ((size_t)IMG_H * IMG_W * DPAD)

template <int DX, int DY>
__device__ __forceinline__ void diagonal_task(const u64* __restrict__ cen, u8* vol,
                                              int task, u32 p1x2, u32 p2) {
  const int line = task * LPW + (int)(threadIdx.x & 31) / LPL;
  int x0 = 0, y0 = 0, len = 0;
  if (line < IMG_W + IMG_H - 1) diagonal_line<DX, DY>(line, x0, y0, len);
  walk_line<DX, DY>(cen, vol, x0, y0, len, warp_max(len), p1x2, p2);
}

// 3. Every path, one volume each, in one launch: warp task -> (direction, lines). Volume order is the
// reference's PATH_DIRECTIONS: left-to-right, right-to-left, top-to-bottom, bottom-to-top, then (8 paths)
// the diagonals (1,1), (-1,1), (1,-1), (-1,-1). The longest walks (rows) are handed out first. Block: 128
// threads.

extern "C" __global__ void __launch_bounds__(128) sgm_paths(const u64* __restrict__ cen,
                                                            u8* __restrict__ vols, u32 p1, u32 p2) {
  int task = (int)(blockIdx.x * (blockDim.x / 32) + threadIdx.x / 32);
  const int sub = (int)(threadIdx.x & 31) / LPL;
  const u32 p1x2 = p1 * 0x00010001u;
  if (task < 2 * TASKS_H) {
    const bool rtl = task >= TASKS_H;
    const int row = (rtl ? task - TASKS_H : task) * LPW + sub;
    const int len = row < IMG_H ? IMG_W : 0;
    if (rtl) walk_line<-1, 0>(cen, vols + VOL_BYTES, IMG_W - 1, row, len, IMG_W, p1x2, p2);
    else walk_line<1, 0>(cen, vols, 0, row, len, IMG_W, p1x2, p2);
    return;
  }
  task -= 2 * TASKS_H;
  if (task < 2 * TASKS_V) {
    const bool up = task >= TASKS_V;
    const int col = (up ? task - TASKS_V : task) * LPW + sub;
    const int len = col < IMG_W ? IMG_H : 0;
    if (up) walk_line<0, -1>(cen, vols + 3 * VOL_BYTES, col, IMG_H - 1, len, IMG_H, p1x2, p2);
    else walk_line<0, 1>(cen, vols + 2 * VOL_BYTES, col, 0, len, IMG_H, p1x2, p2);
    return;
  }
#if NPATHS == 8
  task -= 2 * TASKS_V;
  if (task < TASKS_D) { diagonal_task<1, 1>(cen, vols + 4 * VOL_BYTES, task, p1x2, p2); return; }
  task -= TASKS_D;
  if (task < TASKS_D) { diagonal_task<-1, 1>(cen, vols + 5 * VOL_BYTES, task, p1x2, p2); return; }
  task -= TASKS_D;
  if (task < TASKS_D) { diagonal_task<1, -1>(cen, vols + 6 * VOL_BYTES, task, p1x2, p2); return; }
  task -= TASKS_D;
  if (task < TASKS_D) { diagonal_task<-1, -1>(cen, vols + 7 * VOL_BYTES, task, p1x2, p2); return; }
#endif
}

// ------------------------------------------------------------------------------------------------
// 4. Winner, uniqueness, sub-pixel and the right view's disparity (reference rules 4-8), in parallel.
//
// One line of LPL lanes per run of RUN pixels of a row, walked from x_lo + RUN - 1 down to x_lo (pixels
// past the image are idle steps). At pixel x, lane l sums the path costs of its disparities over the
// NPATHS volumes into S (16-bit lanes). Winner: the minimum key S << 8 | (255 - d) over the line (ties to
// the largest d). Uniqueness: the minimum key with |d - d*| >= 2. Sub-pixel: S(d* - 1) and S(d* + 1) from
// the lanes holding them. dl: -1 (no unique winner) or d* << 16 | v (v = 16 d* + offset).
// Right disparity: slot d of a shift register R holds the best key of right pixel x - d over the run's
// pixels so far; pixel x adds key(S(x, d), d) to slot d, slot 0 (right pixel x) goes to drkey by
// atomicMin, and R shifts one disparity down; after the run the slots still holding right pixels >= 0 go
// the same way. drkey (reset to KEY_INF by sgm_census) then holds, per right pixel, the minimum key over
// every left pixel x = xr + d: the reference's dR = 255 - (key & 255). Block: 128 threads.

__device__ __forceinline__ u32 pick_sum(const u32 (&SA)[WPL], const u32 (&SB)[WPL], int d) {
  // this lane's S for disparity d, if this lane holds it (the caller shuffles from the owner)
  const int w = (d >> 2) / LPL, j = d & 3;
  u32 r = 0;
#pragma unroll
  for (int ww = 0; ww < WPL; ++ww) {
    if (ww == w) {
      const u32 word = j < 2 ? SA[ww] : SB[ww];
      r = (j & 1) ? word >> 16 : word & 0xffffu;
    }
  }
  return r;
}

#define RUNS_PER_ROW ((IMG_W + RUN - 1) / RUN)

extern "C" __global__ void __launch_bounds__(128) sgm_wta(const u8* __restrict__ vols, int* __restrict__ dl,
                                                          u32* __restrict__ drkey, u32 uniq) {
  const int task = (int)(blockIdx.x * (blockDim.x / 32) + threadIdx.x / 32) * LPW + (int)(threadIdx.x & 31) / LPL;
  const int li = (int)(threadIdx.x & 31) % LPL;
  const int row = task / RUNS_PER_ROW;
  const bool row_ok = row < IMG_H;
  const int y = row_ok ? row : 0;
  const int x_lo = (task % RUNS_PER_ROW) * RUN;
  u32 R[WPL][4];
#pragma unroll
  for (int w = 0; w < WPL; ++w)
#pragma unroll
    for (int j = 0; j < 4; ++j) R[w][j] = KEY_INF;
  const u32* vrow = (const u32*)(vols + (size_t)y * IMG_W * DPAD);
  u32 nxt[NPATHS][WPL];
  {
    const int x = min(x_lo + RUN - 1, IMG_W - 1);
#pragma unroll
    for (int k = 0; k < NPATHS; ++k)
#pragma unroll
      for (int w = 0; w < WPL; ++w) nxt[k][w] = __ldcs(vrow + (size_t)k * (VOL_BYTES / 4) + (size_t)x * (DPAD / 4) + li + LPL * w);
  }
  // unrolled by 2 so that nxt and cur alternate by name instead of by moves
#pragma unroll 2
  for (int q = RUN - 1; q >= 0; --q) {
    const int x = x_lo + q;
    const bool act = row_ok && x < IMG_W;
    u32 cur[NPATHS][WPL];
#pragma unroll
    for (int k = 0; k < NPATHS; ++k)
#pragma unroll
      for (int w = 0; w < WPL; ++w) cur[k][w] = nxt[k][w];
    if (q > 0) {
      const int xn = min(x - 1, IMG_W - 1);
#pragma unroll
      for (int k = 0; k < NPATHS; ++k)
#pragma unroll
        for (int w = 0; w < WPL; ++w)
          nxt[k][w] = __ldcs(vrow + (size_t)k * (VOL_BYTES / 4) + (size_t)xn * (DPAD / 4) + li + LPL * w);
    }
    // sums (16-bit lanes: (d0, d1) and (d2, d3)), keys, winner; d is a candidate when d <= lim
    const int lim = act ? min(x, NDISP - 1) : -1;
    u32 SA[WPL], SB[WPL];
    u32 key[WPL][4];
    u32 best = KEY_INF;
#pragma unroll
    for (int w = 0; w < WPL; ++w) {
      u32 sa = 0u, sb = 0u;
#pragma unroll
      for (int k = 0; k < NPATHS; ++k) {
        sa += __byte_perm(cur[k][w], 0u, 0x4140);
        sb += __byte_perm(cur[k][w], 0u, 0x4342);
      }
      SA[w] = sa;
      SB[w] = sb;
      const int d0 = 4 * (li + LPL * w);
      // key = S << 8 | (255 - d): S's two bytes above 255 - d (< 256, so its byte 1 is a zero), one PRMT
      const u32 raw[4] = {__byte_perm(sa, (u32)(255 - d0), 0x5104), __byte_perm(sa, (u32)(254 - d0), 0x5324),
                          __byte_perm(sb, (u32)(253 - d0), 0x5104), __byte_perm(sb, (u32)(252 - d0), 0x5324)};
#pragma unroll
      for (int j = 0; j < 4; ++j) key[w][j] = d0 + j <= lim ? raw[j] : KEY_INF;
      best = min(best, min3u(key[w][0], key[w][1], min(key[w][2], key[w][3])));
    }
    best = line_min(best);
    const int dstar = 255 - (int)(best & 0xffu);
    const u32 sstar = best >> 8;
    // uniqueness: the best key at |d - d*| >= 2
    u32 other = KEY_INF;
#pragma unroll
    for (int w = 0; w < WPL; ++w) {
      const int d0 = 4 * (li + LPL * w);
#pragma unroll
      for (int j = 0; j < 4; ++j) {
        if ((u32)(d0 + j - dstar + 1) > 2u) other = min(other, key[w][j]);  // |d - d*| >= 2
      }
    }
    other = line_min(other);
    // sub-pixel neighbours from the lanes that hold them
    const int dm = dstar > 0 ? dstar - 1 : 0;
    const int dp = dstar + 1 < DPAD ? dstar + 1 : dstar;
    const u32 c0 = __shfl_sync(FULL_MASK, pick_sum(SA, SB, dm), (dm >> 2) % LPL, LPL);
    const u32 c2 = __shfl_sync(FULL_MASK, pick_sum(SA, SB, dp), (dp >> 2) % LPL, LPL);
    // right disparity: add this pixel, hand slot 0 (right pixel x) on, shift one disparity down
#pragma unroll
    for (int w = 0; w < WPL; ++w)
#pragma unroll
      for (int j = 0; j < 4; ++j) R[w][j] = min(R[w][j], key[w][j]);
    if (li == 0 && act) atomicMin(drkey + (size_t)y * IMG_W + x, R[0][0]);
#pragma unroll
    for (int w = 0; w < WPL; ++w) {
      const u32 next_lane = __shfl_down_sync(FULL_MASK, R[w][0], 1, LPL);
      const u32 next_group = w + 1 < WPL ? __shfl_sync(FULL_MASK, R[w + 1 < WPL ? w + 1 : 0][0], 0, LPL) : KEY_INF;
      R[w][0] = R[w][1];
      R[w][1] = R[w][2];
      R[w][2] = R[w][3];
      R[w][3] = li == LPL - 1 ? next_group : next_lane;
    }
    if (li == 0 && act) {
      int out = -1;
      const bool unique = other == KEY_INF || 100u * (other >> 8) > (100u + uniq) * sstar;
      if (unique) {
        int v = 16 * dstar;
        if (dstar >= 1 && dstar + 1 <= min(x, NDISP - 1)) {
          const int den = (int)c0 + (int)c2 - 2 * (int)sstar;
          // floor of an exact quotient: |n| < 2^17 and 2 den < 2^14 are exact floats, and a quotient that
          // is not an integer lies >= 1 / (2 den) from one, far beyond half an ulp of |q| <= 9: exact
          v += (int)floorf(__fdiv_rn((float)(16 * ((int)c0 - (int)c2) + den), (float)(2 * den)));
        }
        out = (dstar << 16) | v;
      }
      dl[(size_t)y * IMG_W + x] = out;
    }
  }
  // slot d now belongs to right pixel x_lo - 1 - d
  if (row_ok) {
#pragma unroll
    for (int w = 0; w < WPL; ++w)
#pragma unroll
      for (int j = 0; j < 4; ++j) {
        const int xr = x_lo - 1 - (4 * (li + LPL * w) + j);
        if (xr >= 0 && R[w][j] != KEY_INF) atomicMin(drkey + (size_t)y * IMG_W + xr, R[w][j]);
      }
  }
}

// ------------------------------------------------------------------------------------------------
// 4b. The near-range check's coarse pair (reference rule 11): both rectified eyes shrunk NEAR_S times, each
// coarse pixel the rounded mean of its NEAR_S x NEAR_S block, into the coarse module's pitched images (this
// module's PITCH is the source's). Grid (ceil(wc / 64), hc, 2), block 64: one coarse pixel per thread.

extern "C" __global__ void __launch_bounds__(64) sgm_shrink(const u8* __restrict__ rl, const u8* __restrict__ rr,
                                                            u8* __restrict__ cl, u8* __restrict__ cr, int wc, int hc,
                                                            int dst_pitch) {
  const int xc = (int)(blockIdx.x * 64 + threadIdx.x), yc = (int)blockIdx.y;
  if (xc >= wc || yc >= hc) return;
  const u8* src = blockIdx.z ? rr : rl;
  u32 acc = 0;
#pragma unroll
  for (int i = 0; i < NEAR_S; ++i)
#pragma unroll
    for (int j = 0; j < NEAR_S; ++j) acc += src[(size_t)(yc * NEAR_S + i) * PITCH + xc * NEAR_S + j];
  (blockIdx.z ? cr : cl)[(size_t)yc * dst_pitch + xc] = (u8)((acc + NEAR_S * NEAR_S / 2) / (NEAR_S * NEAR_S));
}

// ------------------------------------------------------------------------------------------------
// 5. Left-right check, median, peak removal, near-range check, disparity image, region histograms, and
// the 9 depths (reference rules 9-11; near: the coarse module's disparity, near_w x near_h, or null for
// none; regions as companion.core.regions.reduce_regions on the float disparity v / 16).
//
// Without peak removal one launch does it all (stage 0). With it (rule 10's second part), stage 1 writes
// the checked and median-filtered disparity to disp and stops; sgm_peaks_init, sgm_peaks_link and
// sgm_peaks_count find its segments; stage 2 reads disp back, invalidates the pixels of segments of at
// most peak_max pixels (but those at the range's end), and goes on with the near-range check, the
// histograms and the depths.
//
// A block owns a slab of SLAB_ROWS rows inside one row band of the regions (so its pixels fall in 3
// regions). It first writes the left-right-checked v of its rows and the row above and below into shared
// memory, then takes each pixel's median from there and counts the valid results in a shared histogram
// of 3 * NBINS 16-bit counters (a slab has at most 65535 pixels), whose non-zero counts it adds to the
// global histogram (9 * NBINS u32). The last block over all slabs (a ticket counter) finds, per region, n
// and the k-th largest v, z = fb / (v / 16) in float32, and zeroes the histogram and the counter for the
// next frame. Block: 256 threads.

#define POST_THREADS 256
#define HIST_WORDS ((3 * NBINS + 1) / 2)
#define FIN_CHUNK ((NBINS + POST_THREADS - 1) / POST_THREADS)
#define CHK_ROWS (SLAB_ROWS + 2)

__device__ __forceinline__ u32 sgm_region_area(int reg) {
  const int rb = reg / 3, cb = reg % 3;
  const int h = rb == 0 ? RE1 : (rb == 1 ? RE2 - RE1 : IMG_H - RE2);
  const int w = cb == 0 ? CE1 : (cb == 1 ? CE2 - CE1 : IMG_W - CE2);
  return (u32)(h * w);
}

struct SmemPost {
  u32 hist[HIST_WORDS];
  short chk[CHK_ROWS * IMG_W];
  u32 warp_sum[POST_THREADS / 32];
  int found;
  int flag;
};

// The lower median of the valid values among the 3x3 neighbours (rows r - 1 .. r + 1 of chk); the centre
// is valid. Invalid neighbours become 0x7fff (above every v <= 16 * 255) and a comparator network
// (Batcher's for 9 inputs, pruned to the 23 comparators that fix the 5 smallest: checked on all 512 0/1
// inputs) sorts the 5 smallest into v[0..4]; with n valid the lower median is v[(n - 1) / 2], n >= 1.
#define SGM_MED_PAIRS 0, 8, 0, 4, 1, 5, 2, 6, 3, 7, 4, 8, 0, 2, 1, 3, 4, 6, 5, 7, 2, 8, 2, 4, 3, 5, 6, 8, 0, 1, 2, 3, 4, 5, 6, 7, 1, 8, 1, 4, 3, 6, 1, 2, 3, 4

__device__ __forceinline__ int median_valid_3x3(const short* chk, int r, int x) {
  int v[9];
  int n = 0;
#pragma unroll
  for (int i = 0; i < 3; ++i)
#pragma unroll
    for (int j = 0; j < 3; ++j) {
      const int xx = x + j - 1;
      const int q = (xx >= 0 && xx < IMG_W) ? (int)chk[(r + i - 1) * IMG_W + xx] : -1;
      v[i * 3 + j] = q >= 0 ? q : 0x7fff;
      n += q >= 0;
    }
  constexpr int pairs[] = {SGM_MED_PAIRS};
#pragma unroll
  for (int c = 0; c < (int)(sizeof(pairs) / sizeof(pairs[0])); c += 2) {
    const int lo = min(v[pairs[c]], v[pairs[c + 1]]);
    v[pairs[c + 1]] = max(v[pairs[c]], v[pairs[c + 1]]);
    v[pairs[c]] = lo;
  }
  const int target = (n - 1) / 2;
  int res = v[0];
#pragma unroll
  for (int k = 1; k < 5; ++k)
    if (target == k) res = v[k];
  return n > 0 ? res : -1;
}

// Peak removal's segments (reference rule 10): union-find over the links |v_p - v_q| <= tol between valid
// 4-neighbours (Playne & Hawick 2018: each root hooks onto the smaller by atomicMin, retried until the
// hook holds). Labels are pixel indices; a segment's pixels end with one root, whatever the order of the
// unions, so the counts are exact. Grid: one thread per pixel, PEAK_THREADS a block.
#define PEAK_THREADS 256

__device__ __forceinline__ u32 peaks_find(const u32* lab, u32 x) {
  u32 y = ((volatile const u32*)lab)[x];
  while (y != x) {
    x = y;
    y = ((volatile const u32*)lab)[x];
  }
  return x;
}

__device__ __forceinline__ void peaks_union(u32* lab, u32 a, u32 b) {
  bool done = false;
  while (!done) {
    a = peaks_find(lab, a);
    b = peaks_find(lab, b);
    if (a < b) {
      const u32 old = atomicMin(lab + b, a);
      done = old == b;
      b = old;
    } else if (b < a) {
      const u32 old = atomicMin(lab + a, b);
      done = old == a;
      a = old;
    } else {
      done = true;
    }
  }
}

// Every pixel its own segment, and the counts zeroed for this frame.
extern "C" __global__ void __launch_bounds__(PEAK_THREADS) sgm_peaks_init(u32* __restrict__ lab, u32* __restrict__ cnt) {
  const u32 i = blockIdx.x * PEAK_THREADS + threadIdx.x;
  if (i >= (u32)(IMG_W * IMG_H)) return;
  lab[i] = i;
  cnt[i] = 0u;
}

// Join each valid pixel with its right and lower neighbours where they are linked.
extern "C" __global__ void __launch_bounds__(PEAK_THREADS) sgm_peaks_link(const short* __restrict__ disp, u32* lab, int tol) {
  const u32 i = blockIdx.x * PEAK_THREADS + threadIdx.x;
  if (i >= (u32)(IMG_W * IMG_H)) return;
  const int v = disp[i];
  if (v < 0) return;
  const int x = (int)(i % IMG_W), y = (int)(i / IMG_W);
  if (x + 1 < IMG_W) {
    const int q = disp[i + 1];
    if (q >= 0 && abs(q - v) <= tol) peaks_union(lab, i, i + 1);
  }
  if (y + 1 < IMG_H) {
    const int q = disp[i + IMG_W];
    if (q >= 0 && abs(q - v) <= tol) peaks_union(lab, i, i + IMG_W);
  }
}

// Each pixel's label becomes its root, and each valid pixel counts in its root's segment.
extern "C" __global__ void __launch_bounds__(PEAK_THREADS) sgm_peaks_count(const short* __restrict__ disp, u32* lab,
                                                                           u32* __restrict__ cnt) {
  const u32 i = blockIdx.x * PEAK_THREADS + threadIdx.x;
  if (i >= (u32)(IMG_W * IMG_H)) return;
  const u32 r = peaks_find(lab, i);
  lab[i] = r;  // only ever shortens a path: every reader still reaches the same root
  if (disp[i] >= 0) atomicAdd(cnt + r, 1u);
}

extern "C" __global__ void __launch_bounds__(POST_THREADS) sgm_post(const int* __restrict__ dl,
                                                                    const u32* __restrict__ drkey,
                                                                    short* __restrict__ disp, u32* __restrict__ hist_g,
                                                                    u32* __restrict__ counter,
                                                                    double* __restrict__ result, int lr_max, int median,
                                                                    float fb, double pct, double min_valid,
                                                                    double max_depth, const short* __restrict__ near,
                                                                    int near_w, int near_h, int stage,
                                                                    const u32* __restrict__ lab,
                                                                    const u32* __restrict__ cnt, int peak_max) {
  __shared__ SmemPost sm;
  const int tid = (int)threadIdx.x;
  int b = (int)blockIdx.x, band, ya, yb;
  if (b < NSLAB0) {
    band = 0;
    ya = b * SLAB_ROWS;
    yb = min(ya + SLAB_ROWS, RE1);
  } else if (b < NSLAB0 + NSLAB1) {
    band = 1;
    ya = RE1 + (b - NSLAB0) * SLAB_ROWS;
    yb = min(ya + SLAB_ROWS, RE2);
  } else {
    band = 2;
    ya = RE2 + (b - NSLAB0 - NSLAB1) * SLAB_ROWS;
    yb = min(ya + SLAB_ROWS, IMG_H);
  }
  for (int i = tid; i < HIST_WORDS; i += POST_THREADS) sm.hist[i] = 0u;
  // left-right check of rows ya - 1 .. yb (-1 outside the image); stage 2 reads disp instead
  const int nchk = stage == 2 ? 0 : (yb - ya + 2) * IMG_W;
  for (int i = tid; i < nchk; i += POST_THREADS) {
    const int r = i / IMG_W, x = i % IMG_W, y = ya - 1 + r;
    int out = -1;
    if (y >= 0 && y < IMG_H) {
      const int raw = dl[(size_t)y * IMG_W + x];
      if (raw >= 0) {
        const int ds = raw >> 16;
        out = raw & 0xffff;
        if (lr_max >= 0) {
          const int back = 255 - (int)(drkey[(size_t)y * IMG_W + x - ds] & 0xffu);
          const int diff = ds > back ? ds - back : back - ds;
          if (diff > lr_max) out = -1;
        }
      }
    }
    sm.chk[i] = (short)out;
  }
  __syncthreads();
  const int npx = (yb - ya) * IMG_W;
  for (int idx = tid; idx < npx; idx += POST_THREADS) {
    const int r = idx / IMG_W + 1, x = idx % IMG_W;
    const size_t at = (size_t)(ya + r - 1) * IMG_W + x;
    int v;
    if (stage == 2) {
      v = disp[at];
      // a peak (rule 10), unless at the range's end
      if (v >= 0 && v < 16 * (NDISP - 1) && cnt[lab[at]] <= (u32)peak_max) v = -1;
    } else {
      v = sm.chk[r * IMG_W + x];
      if (median && v >= 0) v = median_valid_3x3(sm.chk, r, x);
      if (stage == 1) {
        disp[at] = (short)v;
        continue;
      }
    }
    if (near != nullptr && v < 0) {  // the near-range check (rule 11): the coarse match beyond [0, NDISP)
      const int yc = min((ya + r - 1) / NEAR_S, near_h - 1), xc = min(x / NEAR_S, near_w - 1);
      const int q = near[(size_t)yc * near_w + xc];
      if (q >= 0 && NEAR_S * q >= 16 * NDISP) v = 16 * (NDISP - 1);
    }
    disp[at] = (short)v;
    if (v >= 0) {
      const int cb = x < CE1 ? 0 : (x < CE2 ? 1 : 2);
      const int bin = cb * NBINS + v;
      atomicAdd(&sm.hist[bin >> 1], 1u << (16 * (bin & 1)));
    }
  }
  if (stage == 1) return;  // uniform over the grid: the histograms wait for stage 2
  __syncthreads();
  for (int i = tid; i < 3 * NBINS; i += POST_THREADS) {
    const u32 c = (sm.hist[i >> 1] >> (16 * (i & 1))) & 0xffffu;
    if (c) atomicAdd(hist_g + (band * 3 + i / NBINS) * NBINS + i % NBINS, c);
  }

  // ---- the last block turns the histogram into the 9 results
  __threadfence();
  __syncthreads();
  if (tid == 0) sm.flag = atomicAdd(counter, 1u) == gridDim.x - 1;
  __syncthreads();
  if (!sm.flag) return;
  __threadfence();
  const int lane = tid & 31, warp = tid >> 5;
  for (int reg = 0; reg < N_REG; ++reg) {
    // thread t holds bins NBINS-1-t*FIN_CHUNK down to NBINS-(t+1)*FIN_CHUNK (from the largest v)
    u32 h[FIN_CHUNK];
    u32 part = 0;
#pragma unroll
    for (int c = 0; c < FIN_CHUNK; ++c) {
      const int bin = NBINS - 1 - tid * FIN_CHUNK - c;
      h[c] = 0u;
      if (bin >= 0) {
        u32* p = hist_g + reg * NBINS + bin;
        h[c] = __ldcg(p);
        *p = 0u;
      }
      part += h[c];
    }
    u32 incl = part;
#pragma unroll
    for (int off = 1; off < 32; off <<= 1) {
      const u32 t = __shfl_up_sync(FULL_MASK, incl, off);
      if (lane >= off) incl += t;
    }
    if (lane == 31) sm.warp_sum[warp] = incl;
    if (tid == 0) sm.found = -1;
    __syncthreads();
    u32 before = 0, n = 0;
    for (int w = 0; w < POST_THREADS / 32; ++w) {
      const u32 ws = sm.warp_sum[w];
      if (w < warp) before += ws;
      n += ws;
    }
    const double frac = (double)n / (double)sgm_region_area(reg);
    const bool known = n > 0 && !(frac < min_valid);
    if (known) {
      const double kd = ceil(pct * (double)n / 100.0);
      const u32 k = kd < 1.0 ? 1u : (u32)kd;
      const u32 lo = before + incl - part;  // valid pixels in bins above this thread's
      if (lo < k && k <= lo + part) {
        u32 acc = lo;
#pragma unroll
        for (int c = 0; c < FIN_CHUNK; ++c) {
          acc += h[c];
          if (acc >= k) {
            sm.found = NBINS - 1 - tid * FIN_CHUNK - c;
            break;
          }
        }
      }
    }
    __syncthreads();
    if (tid == 0) {
      double depth = (double)sgm_nan();
      if (known) {
        const int v = sm.found;
        const float z = v == 0 ? __int_as_float(0x7f800000) : __fdiv_rn(fb, (float)v * 0.0625f);
        depth = (double)z < max_depth ? (double)z : max_depth;
      }
      result[reg] = depth;
      result[N_REG + reg] = frac;
    }
    __syncthreads();
  }
  if (tid == 0) *counter = 0u;
}
