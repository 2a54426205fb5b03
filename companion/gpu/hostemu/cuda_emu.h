// Minimal CUDA-on-CPU emulation: each CUDA thread is a ucontext fiber; __syncthreads/__syncwarp and
// warp shuffles are cooperative barriers; the scheduler picks a random runnable fiber at every yield
// so that missing barriers show up as wrong results.
#pragma once
#include <ucontext.h>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <cmath>
#include <cfenv>
#include <vector>
#include <random>
#include <atomic>
#include <algorithm>
#include <cassert>
#include <cstdio>

struct uint3e { unsigned x, y, z; };
struct uint4 { unsigned x, y, z, w; } __attribute__((aligned(16)));
struct uint2 { unsigned x, y; } __attribute__((aligned(8)));
struct ulonglong2 { unsigned long long x, y; } __attribute__((aligned(16)));
inline uint4 make_uint4(unsigned a, unsigned b, unsigned c, unsigned d) { return {a, b, c, d}; }
inline uint2 make_uint2(unsigned a, unsigned b) { return {a, b}; }

struct Fiber { ucontext_t ctx; uint3e tidx; unsigned lin; bool done; std::vector<char> stack; };  // lin: linear thread id
extern Fiber* g_cur;
extern uint3e blockIdx, blockDim, gridDim;
#define threadIdx (g_cur->tidx)

#define __global__
#define __device__
#define __host__
#define __forceinline__ inline
#define __restrict__ __restrict
#define __shared__ static
#define __launch_bounds__(...)

void emu_yield();
void emu_block_barrier();
void emu_warp_barrier();

inline void __syncthreads() { emu_block_barrier(); }
inline void __syncwarp(unsigned = 0xffffffffu) { emu_warp_barrier(); }
inline void __threadfence() { std::atomic_thread_fence(std::memory_order_seq_cst); }

extern uint64_t g_xbuf[1024];
// Warp shuffles with CUDA's width semantics (segments of `width` lanes; a source outside the caller's
// segment, or past it for up/down, returns the caller's own value).
template <class T> inline T emu_exchange(T v, unsigned src_of_t) {
  unsigned t = g_cur->lin; uint64_t bits = 0; std::memcpy(&bits, &v, sizeof(T)); g_xbuf[t] = bits;
  emu_warp_barrier(); uint64_t r = g_xbuf[src_of_t]; emu_warp_barrier();
  T out; std::memcpy(&out, &r, sizeof(T)); return out; }
template <class T> inline T __shfl_xor_sync(unsigned, T v, int m, int width = 32) {
  unsigned t = g_cur->lin, lane = t & 31u, seg = lane & ~(unsigned)(width - 1), src = lane ^ (unsigned)m;
  if ((src & ~(unsigned)(width - 1)) != seg) src = lane;
  return emu_exchange(v, (t & ~31u) | src); }
template <class T> inline T __shfl_up_sync(unsigned, T v, unsigned d, int width = 32) {
  unsigned t = g_cur->lin, lane = t & 31u, in = lane & (unsigned)(width - 1);
  return emu_exchange(v, in >= d ? t - d : t); }
template <class T> inline T __shfl_down_sync(unsigned, T v, unsigned d, int width = 32) {
  unsigned t = g_cur->lin, lane = t & 31u, in = lane & (unsigned)(width - 1);
  return emu_exchange(v, in + d < (unsigned)width ? t + d : t); }
template <class T> inline T __shfl_sync(unsigned, T v, int src, int width = 32) {
  unsigned t = g_cur->lin, lane = t & 31u, seg = lane & ~(unsigned)(width - 1);
  return emu_exchange(v, (t & ~31u) | seg | ((unsigned)src & (unsigned)(width - 1))); }
inline unsigned __ballot_sync(unsigned, bool p) {
  unsigned t = g_cur->lin; g_xbuf[t] = p; emu_warp_barrier(); unsigned m = 0;
  for (int i = 0; i < 32; ++i) if (g_xbuf[(t & ~31u) + i]) m |= 1u << i; emu_warp_barrier(); return m; }

inline unsigned atomicAdd(unsigned* p, unsigned v) { unsigned o = *p; *p = o + v; return o; }  // single OS thread
inline unsigned atomicMin(unsigned* p, unsigned v) { unsigned o = *p; *p = o < v ? o : v; return o; }
template <class T> inline T __ldcg(const T* p) { return *p; }
template <class T> inline T __ldg(const T* p) { return *p; }
template <class T> inline T __ldcs(const T* p) { return *p; }
template <class T> inline void __stcs(T* p, T v) { *p = v; }
inline int __popc(unsigned x) { return __builtin_popcount(x); }
inline int __ffs(unsigned x) { return x ? __builtin_ctz(x) + 1 : 0; }
inline float __int_as_float(int i) { float f; std::memcpy(&f, &i, 4); return f; }
inline unsigned __float_as_uint(float f) { unsigned u; std::memcpy(&u, &f, 4); return u; }
inline float __uint_as_float(unsigned u) { float f; std::memcpy(&f, &u, 4); return f; }
inline int __float2int_rn(float f) { return (int)std::nearbyintf(f); }
inline float __fdiv_rn(float a, float b) { return a / b; }
#include <math.h>
inline unsigned min(unsigned a, unsigned b) { return a < b ? a : b; }
inline int min(int a, int b) { return a < b ? a : b; }
inline unsigned max(unsigned a, unsigned b) { return a > b ? a : b; }
inline int max(int a, int b) { return a > b ? a : b; }
inline unsigned __byte_perm(unsigned x, unsigned y, unsigned s) {
  uint64_t v = ((uint64_t)y << 32) | x; unsigned r = 0;
  for (int i = 0; i < 4; ++i) { unsigned sel = (s >> (4 * i)) & 7u; r |= (unsigned)((v >> (8 * sel)) & 255u) << (8 * i); }
  return r; }
inline unsigned __vabsdiffu4(unsigned a, unsigned b) { unsigned r = 0;
  for (int i = 0; i < 4; ++i) { int x = (a >> (8*i)) & 255, y = (b >> (8*i)) & 255; r |= (unsigned)std::abs(x - y) << (8*i); } return r; }
inline unsigned __vminu2(unsigned a, unsigned b) { unsigned lo = std::min(a & 0xffffu, b & 0xffffu), hi = std::min(a >> 16, b >> 16); return lo | (hi << 16); }


void emu_launch(uint3e grid, uint3e block, void (*body)(void*), void* arg);
