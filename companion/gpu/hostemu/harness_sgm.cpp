// Host-emulation entry points of the SGM kernels (kernels/sgm.cu): one C function per kernel launch
// (development tool and CI check, see __init__.py).
#include "cuda_emu.h"
#include KERNEL_FILE
struct CensusArgs { const u8 *rl, *rr; u64 *cl, *cr; };
static void census_thunk(void* p) { CensusArgs* a = (CensusArgs*)p; sgm_census(a->rl, a->rr, a->cl, a->cr); }
extern "C" void run_census(const u8* rl, const u8* rr, u64* cl, u64* cr, int gx, int bx) {
  CensusArgs a{rl, rr, cl, cr}; emu_launch({(unsigned)gx, (unsigned)IMG_H, 2}, {(unsigned)bx, 1, 1}, census_thunk, &a); }
struct FirstArgs { const u64 *cl, *cr; u8* vols; u32 p1, p2; };
static void first_thunk(void* p) { FirstArgs* a = (FirstArgs*)p; sgm_paths_first(a->cl, a->cr, a->vols, a->p1, a->p2); }
extern "C" void run_paths_first(const u64* cl, const u64* cr, u8* vols, u32 p1, u32 p2, int gx) {
  FirstArgs a{cl, cr, vols, p1, p2}; emu_launch({(unsigned)gx, 1, 1}, {128, 1, 1}, first_thunk, &a); }
struct FinalArgs { const u64 *cl, *cr; const u8* vols; int* dl; u8* dr; short* dchk; u32 p1, p2, uniq; int lr; };
static void final_thunk(void* p) { FinalArgs* a = (FinalArgs*)p; sgm_final(a->cl, a->cr, a->vols, a->dl, a->dr, a->dchk, a->p1, a->p2, a->uniq, a->lr); }
extern "C" void run_final(const u64* cl, const u64* cr, const u8* vols, int* dl, u8* dr, short* dchk, u32 p1, u32 p2, u32 uniq, int lr, int gx) {
  FinalArgs a{cl, cr, vols, dl, dr, dchk, p1, p2, uniq, lr}; emu_launch({(unsigned)gx, 1, 1}, {128, 1, 1}, final_thunk, &a); }
struct PostArgs { const short* dchk; short* disp; u32* hist; u32* counter; double* result; int median; float fb; double pct, minv, maxd; };
static void post_thunk(void* p) { PostArgs* a = (PostArgs*)p; sgm_post(a->dchk, a->disp, a->hist, a->counter, a->result, a->median, a->fb, a->pct, a->minv, a->maxd); }
extern "C" void run_post(const short* dchk, short* disp, u32* hist, u32* counter, double* result, int median, float fb, double pct, double minv, double maxd, int gx) {
  PostArgs a{dchk, disp, hist, counter, result, median, fb, pct, minv, maxd}; emu_launch({(unsigned)gx, 1, 1}, {256, 1, 1}, post_thunk, &a); }
