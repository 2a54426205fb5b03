// Host-emulation entry points: one C function per kernel launch (development tool, see __init__.py).
#include "cuda_emu.h"
#include KERNEL_FILE
struct FastArgs { const u8* rl; const u8* rr; short* disp; u32* hist; u32* counter; double* result; int yb, ye, rows; u32 total, uniq, texmin; float fb; double pct, minv, maxd; int variant; };
static void fast_thunk(void* p) { FastArgs* a = (FastArgs*)p;
  if (a->variant == 0) sad_fast_regions(a->rl, a->rr, a->disp, a->hist, a->counter, a->result, a->yb, a->ye, a->rows, a->total, a->uniq, a->texmin, a->fb, a->pct, a->minv, a->maxd);
  else if (a->variant == 1) sad_fast_regions_disp(a->rl, a->rr, a->disp, a->hist, a->counter, a->result, a->yb, a->ye, a->rows, a->total, a->uniq, a->texmin, a->fb, a->pct, a->minv, a->maxd);
  else sad_fast_disp(a->rl, a->rr, a->disp, a->hist, a->counter, a->result, a->yb, a->ye, a->rows, a->total, a->uniq, a->texmin, a->fb, a->pct, a->minv, a->maxd); }
extern "C" void run_fast(int variant, const u8* rl, const u8* rr, short* disp, u32* hist, u32* counter, double* result, int yb, int ye, int rows, u32 total, u32 uniq, u32 texmin, float fb, double pct, double minv, double maxd, int gx, int gy) {
  FastArgs a{rl, rr, disp, hist, counter, result, yb, ye, rows, total, uniq, texmin, fb, pct, minv, maxd, variant}; emu_launch({(unsigned)gx,(unsigned)gy,1},{NT,1,1}, fast_thunk, &a); }
struct RegArgs { const short* disp; u32* hist; u32* counter; double* result; int rows; float fb; double pct, minv, maxd; };
static void reg_thunk(void* p) { RegArgs* a = (RegArgs*)p; regions_from_disp(a->disp, a->hist, a->counter, a->result, a->rows, a->fb, a->pct, a->minv, a->maxd); }
extern "C" void run_regions(const short* disp, u32* hist, u32* counter, double* result, int rows, float fb, double pct, double minv, double maxd, int gx, int nt) {
  RegArgs a{disp, hist, counter, result, rows, fb, pct, minv, maxd}; emu_launch({(unsigned)gx,1,1},{(unsigned)nt,1,1}, reg_thunk, &a); }
struct NaiveArgs { const u8* rl; const u8* rr; short* disp; u32 uniq, texmin; };
static void naive_thunk(void* p) { NaiveArgs* a = (NaiveArgs*)p; sad_naive(a->rl, a->rr, a->disp, a->uniq, a->texmin); }
extern "C" void run_naive(const u8* rl, const u8* rr, short* disp, u32 uniq, u32 texmin, int gx, int gy, int bx) {
  NaiveArgs a{rl, rr, disp, uniq, texmin}; emu_launch({(unsigned)gx,(unsigned)gy,1},{(unsigned)bx,1,1}, naive_thunk, &a); }
struct GreyArgs { const u8* f; u8* l; u8* r; int ch; int yoff; };
static void grey_thunk(void* p) { GreyArgs* a = (GreyArgs*)p; if (a->ch == 1) grey_c1(a->f, a->l, a->r, a->yoff); else if (a->ch == 2) grey_c2(a->f, a->l, a->r, a->yoff); else if (a->ch == 3) grey_c3(a->f, a->l, a->r, a->yoff); else if (a->ch == 4) grey_c4(a->f, a->l, a->r, a->yoff); else if (a->ch == 13) grey_c3_rgb(a->f, a->l, a->r, a->yoff); else grey_c4_rgb(a->f, a->l, a->r, a->yoff); }
extern "C" void run_grey(int ch, const u8* f, u8* l, u8* r, int gx, int bx, int yoff, int rows) {
  GreyArgs a{f, l, r, ch, yoff}; emu_launch({(unsigned)gx,(unsigned)rows,2},{(unsigned)bx,1,1}, grey_thunk, &a); }
struct RemapArgs { const u8 *rl, *rr; const float *a, *b, *c, *d; u8 *ol, *orr; int yoff; };
static void remap_thunk(void* p) { RemapArgs* x = (RemapArgs*)p; remap_linear(x->rl, x->rr, x->a, x->b, x->c, x->d, x->ol, x->orr, x->yoff); }
extern "C" void run_remap(const u8* rl, const u8* rr, const float* a, const float* b, const float* c, const float* d, u8* ol, u8* orr, int gx, int bx, int yoff, int rows) {
  RemapArgs x{rl, rr, a, b, c, d, ol, orr, yoff}; emu_launch({(unsigned)gx,(unsigned)rows,2},{(unsigned)bx,1,1}, remap_thunk, &x); }
struct PrevArgs { const short* d; float* o; int f, ow, oh; };
static void prev_thunk(void* p) { PrevArgs* a = (PrevArgs*)p; preview_max(a->d, a->o, a->f, a->ow, a->oh, 1.0f); }
extern "C" void run_preview(const short* d, float* o, int f, int ow, int oh, int gx, int bx) {
  PrevArgs a{d, o, f, ow, oh}; emu_launch({(unsigned)gx,(unsigned)oh,1},{(unsigned)bx,1,1}, prev_thunk, &a); }
struct MemArgs { const short* d; float* o; int f, ow, oh, k; };
static void mem_thunk(void* p) { MemArgs* a = (MemArgs*)p; memory_max(a->d, a->o, a->f, a->ow, a->oh, 1.0f, a->k); }
extern "C" void run_memory(const short* d, float* o, int f, int ow, int oh, int k, int gx, int bx) {
  MemArgs a{d, o, f, ow, oh, k}; emu_launch({(unsigned)gx,(unsigned)oh,1},{(unsigned)bx,1,1}, mem_thunk, &a); }
