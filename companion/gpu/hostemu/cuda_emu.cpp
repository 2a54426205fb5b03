// Host emulation of the CUDA subset used by companion/gpu/kernels/stereo.cu (development tool, see
// companion/gpu/hostemu/__init__.py): CUDA threads as ucontext fibers, randomised scheduling at barriers.
#include "cuda_emu.h"
Fiber* g_cur;
uint3e blockIdx, blockDim, gridDim;
uint64_t g_xbuf[1024];
static std::vector<Fiber*> g_fibers;
static ucontext_t g_main;
static std::mt19937 g_rng(12345);
static int g_bar_count, g_bar_gen;
static int g_wbar_count[32], g_wbar_gen[32];
static void (*g_body)(void*); static void* g_arg;
static int g_nthreads;

static void fiber_entry() { g_body(g_arg); g_cur->done = true; swapcontext(&g_cur->ctx, &g_main); }

void emu_yield() { swapcontext(&g_cur->ctx, &g_main); }
static int active_in_warp(int w) { int n = 0; for (int i = w*32; i < std::min(g_nthreads, w*32+32); ++i) if (!g_fibers[i]->done) ++n; return n; }
void emu_block_barrier() {
  int gen = g_bar_gen;
  if (++g_bar_count == g_nthreads) { g_bar_count = 0; ++g_bar_gen; return; }
  while (g_bar_gen == gen) emu_yield();
}
void emu_warp_barrier() {
  int w = g_cur->lin / 32; int gen = g_wbar_gen[w];
  if (++g_wbar_count[w] == std::min(32, g_nthreads - w*32)) { g_wbar_count[w] = 0; ++g_wbar_gen[w]; return; }
  while (g_wbar_gen[w] == gen) emu_yield();
}
void emu_launch(uint3e grid, uint3e block, void (*body)(void*), void* arg) {
  gridDim = grid; blockDim = block; g_body = body; g_arg = arg;
  int nt = block.x * block.y * block.z; g_nthreads = nt;
  while ((int)g_fibers.size() < nt) { Fiber* f = new Fiber(); f->stack.resize(256 * 1024); g_fibers.push_back(f); }
  for (unsigned bz = 0; bz < grid.z; ++bz) for (unsigned by = 0; by < grid.y; ++by) for (unsigned bx = 0; bx < grid.x; ++bx) {
    blockIdx = {bx, by, bz};
    g_bar_count = 0; for (int w = 0; w < 32; ++w) g_wbar_count[w] = 0;
    for (int t = 0; t < nt; ++t) {
      Fiber* f = g_fibers[t]; f->done = false; f->lin = (unsigned)t;
      f->tidx = {(unsigned)t % block.x, ((unsigned)t / block.x) % block.y, (unsigned)t / (block.x * block.y)};
      getcontext(&f->ctx); f->ctx.uc_stack.ss_sp = f->stack.data(); f->ctx.uc_stack.ss_size = f->stack.size(); f->ctx.uc_link = &g_main;
      makecontext(&f->ctx, (void (*)())fiber_entry, 0);
    }
    int remaining = nt;
    std::vector<int> order(nt);
    while (remaining > 0) {
      // pick a random not-done fiber and run it until it yields or finishes
      int start = g_rng() % nt; int pick = -1;
      for (int k = 0; k < nt; ++k) { int t = (start + k) % nt; if (!g_fibers[t]->done) { pick = t; break; } }
      g_cur = g_fibers[pick];
      swapcontext(&g_main, &g_cur->ctx);
      if (g_cur->done) --remaining;
    }
  }
}
