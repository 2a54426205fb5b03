// Host-emulation entry point of the OBSTACLE_DISTANCE kernel (kernels/obstacle.cu; see __init__.py).
#include "cuda_emu.h"
#include KERNEL_FILE
struct OdArgs { const short* disp; int w, h; float inv; const float *thr, *fbk; const int* cols; double pct; int minp; double minv; float maxm; int mincm, maxcm; unsigned* hist; unsigned* cnt; unsigned short* out; };
static void od_thunk(void* p) { OdArgs* a = (OdArgs*)p; obstacle_bins(a->disp, a->w, a->h, a->inv, a->thr, a->fbk, a->cols, a->pct, a->minp, a->minv, a->maxm, a->mincm, a->maxcm, a->hist, a->cnt, a->out); }
extern "C" void run_obstacle(const short* disp, int w, int h, float inv, const float* thr, const float* fbk, const int* cols, double pct, int minp, double minv, float maxm, int mincm, int maxcm, unsigned* hist, unsigned* cnt, unsigned short* out, int nt, int slices) {
  OdArgs a{disp, w, h, inv, thr, fbk, cols, pct, minp, minv, maxm, mincm, maxcm, hist, cnt, out}; emu_launch({72, (unsigned)slices, 1}, {(unsigned)nt, 1, 1}, od_thunk, &a); }
