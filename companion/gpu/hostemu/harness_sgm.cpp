// Host-emulation entry points of the SGM kernels (kernels/sgm.cu): one C function per kernel launch
// (development tool and CI check, see __init__.py).
#include "cuda_emu.h"
#include KERNEL_FILE
struct CensusArgs { const u8 *rl, *rr; u64* cen; u32* drkey; int y_lo, y_hi; };
static void census_thunk(void* p) { CensusArgs* a = (CensusArgs*)p; sgm_census(a->rl, a->rr, a->cen, a->drkey, a->y_lo, a->y_hi); }
extern "C" void run_census(const u8* rl, const u8* rr, u64* cen, u32* drkey, int y_lo, int y_hi, int gx, int gy) {
  CensusArgs a{rl, rr, cen, drkey, y_lo, y_hi}; emu_launch({(unsigned)gx, (unsigned)gy, 2}, {CT_W, CT_H, 1}, census_thunk, &a); }
struct PathArgs { const u64* cen; u8* vols; u32 p1, p2; };
static void path_thunk(void* p) { PathArgs* a = (PathArgs*)p; sgm_paths(a->cen, a->vols, a->p1, a->p2); }
extern "C" void run_paths(const u64* cen, u8* vols, u32 p1, u32 p2, int gx) {
  PathArgs a{cen, vols, p1, p2}; emu_launch({(unsigned)gx, 1, 1}, {128, 1, 1}, path_thunk, &a); }
struct WtaArgs { const u8* vols; int* dl; u32* drkey; u32 uniq; };
static void wta_thunk(void* p) { WtaArgs* a = (WtaArgs*)p; sgm_wta(a->vols, a->dl, a->drkey, a->uniq); }
extern "C" void run_wta(const u8* vols, int* dl, u32* drkey, u32 uniq, int gx) {
  WtaArgs a{vols, dl, drkey, uniq}; emu_launch({(unsigned)gx, 1, 1}, {128, 1, 1}, wta_thunk, &a); }
struct PostArgs { const int* dl; const u32* drkey; short* disp; u32* hist; u32* counter; double* result; int lr, median; float fb; double pct, minv, maxd; const short* near; int nw, nh, stage; const u32 *lab, *cnt; int peak_max; };
static void post_thunk(void* p) { PostArgs* a = (PostArgs*)p; sgm_post(a->dl, a->drkey, a->disp, a->hist, a->counter, a->result, a->lr, a->median, a->fb, a->pct, a->minv, a->maxd, a->near, a->nw, a->nh, a->stage, a->lab, a->cnt, a->peak_max); }
extern "C" void run_post(const int* dl, const u32* drkey, short* disp, u32* hist, u32* counter, double* result, int lr, int median, float fb, double pct, double minv, double maxd, const short* near, int nw, int nh, int stage, const u32* lab, const u32* cnt, int peak_max, int gx) {
  PostArgs a{dl, drkey, disp, hist, counter, result, lr, median, fb, pct, minv, maxd, near, nw, nh, stage, lab, cnt, peak_max}; emu_launch({(unsigned)gx, 1, 1}, {256, 1, 1}, post_thunk, &a); }
struct PeakArgs { const short* disp; u32 *lab, *cnt; int tol; };
static void peaks_init_thunk(void* p) { PeakArgs* a = (PeakArgs*)p; sgm_peaks_init(a->lab, a->cnt); }
static void peaks_link_thunk(void* p) { PeakArgs* a = (PeakArgs*)p; sgm_peaks_link(a->disp, a->lab, a->tol); }
static void peaks_count_thunk(void* p) { PeakArgs* a = (PeakArgs*)p; sgm_peaks_count(a->disp, a->lab, a->cnt); }
extern "C" void run_peaks(const short* disp, u32* lab, u32* cnt, int tol, int gx) {
  PeakArgs a{disp, lab, cnt, tol};
  emu_launch({(unsigned)gx, 1, 1}, {PEAK_THREADS, 1, 1}, peaks_init_thunk, &a);
  emu_launch({(unsigned)gx, 1, 1}, {PEAK_THREADS, 1, 1}, peaks_link_thunk, &a);
  emu_launch({(unsigned)gx, 1, 1}, {PEAK_THREADS, 1, 1}, peaks_count_thunk, &a); }
struct ShrinkArgs { const u8 *rl, *rr; u8 *cl, *cr; int wc, hc, pitch; };
static void shrink_thunk(void* p) { ShrinkArgs* a = (ShrinkArgs*)p; sgm_shrink(a->rl, a->rr, a->cl, a->cr, a->wc, a->hc, a->pitch); }
extern "C" void run_shrink(const u8* rl, const u8* rr, u8* cl, u8* cr, int wc, int hc, int pitch) {
  ShrinkArgs a{rl, rr, cl, cr, wc, hc, pitch}; emu_launch({(unsigned)((wc + 63) / 64), (unsigned)hc, 2}, {64, 1, 1}, shrink_thunk, &a); }
