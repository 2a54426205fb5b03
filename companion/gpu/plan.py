"""Launch plan of the CUDA kernels: tile shapes, compile-time constants and shared-memory budget.

Pure Python (no CuPy): everything here can be computed and checked on a machine without a GPU. The
kernels in ``kernels/stereo.cu`` are compiled with these values prepended as ``#define`` lines, so
every loop bound is a compile-time constant and the compiler keeps per-thread arrays in registers.

The fast disparity kernel (see the comment above ``sad_fast_body`` in ``stereo.cu``) tiles the valid
area into blocks of ``tx`` output columns × ``rows`` output rows; a block keeps vertical column sums for
``cpad = tx + 2·r`` columns and all ``D`` disparities. Shape choices, in order:

* ``cpad`` is the largest of 128, 64, 32 whose block fits the static shared-memory budget (48 KB,
  what every Jetson allows without opting in) with at least 8 output columns;
* threads: ``nt = cpad · D/4 / gq`` where each thread of phase V handles ``gq`` quads of disparities
  (8 when D/4 allows, so 16 packed sums stay in registers);
* phase H: ``D/2`` disparity pairs × ``hruns`` runs of ``hk`` columns; phase M: ``ms`` threads per
  column (a power of two, at most 32, so they share a warp);
* padded row strides (``roww``, ``cstr``) so that the vector shared-memory accesses of a warp hit
  distinct banks (checked by :func:`bank_wavefronts`).

The fast kernel needs every window cost below 2**16 (``255·b² < 65535``, i.e. ``b <= 15``) and ``D``
a multiple of 4; otherwise the plan falls back to the simple exact kernel ``sad_naive``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from companion.core.disparity.sgm import NEAR_SCALE

#: Static shared memory one block may use on every supported device (Jetson TX1 ... Orin), bytes.
SMEM_BUDGET_BYTES = 48 * 1024

_CPAD_CHOICES = (128, 64, 32)
_N_REGIONS = 9


@dataclass(frozen=True)
class DisparityPlan:
    """Shape of the disparity kernels for one (size, D, b) and the #defines that fix it.

    Attributes:
        width_px, height_px: eye image size, px.
        num_disparities, block_size: ``D`` and ``b``.
        fast: True when the tiled kernel applies; False: ``sad_naive`` + ``regions_from_disp``.
        pitch_bytes: row pitch of the rectified grey buffers (multiple of 16, with room for the
            last tile's reads past the image width).
        x_start, x_end, y_start, y_end: the valid area (reference rule 2), half-open, px.
        cpad, tx, nt, gq, hruns, hk, ms, msw, roww, cstr, lww, rww, ldpt: fast-kernel tile shape
            (0 when not fast); see the module doc and ``stereo.cu``.
        smem_bytes: static shared memory of one fast block, bytes (0 when not fast).
    """

    width_px: int
    height_px: int
    num_disparities: int
    block_size: int
    fast: bool
    pitch_bytes: int
    x_start: int
    x_end: int
    y_start: int
    y_end: int
    cpad: int = 0
    tx: int = 0
    nt: int = 0
    gq: int = 0
    hruns: int = 0
    hk: int = 0
    ms: int = 0
    msw: int = 0
    roww: int = 0
    cstr: int = 0
    lww: int = 0
    rww: int = 0
    ldpt: int = 0
    smem_bytes: int = 0

    @property
    def radius(self) -> int:
        return self.block_size // 2

    @property
    def valid_cols(self) -> int:
        return max(0, self.x_end - self.x_start)

    @property
    def valid_rows(self) -> int:
        return max(0, self.y_end - self.y_start)

    @property
    def tiles_x(self) -> int:
        """Blocks across the valid columns (at least 1, so the region finaliser always runs)."""
        if not self.fast or self.valid_cols == 0:
            return 1
        return -(-self.valid_cols // self.tx)

    def tiles_y(self, rows_per_block: int) -> int:
        if self.valid_rows == 0:
            return 1
        return -(-self.valid_rows // rows_per_block)

    def choose_rows_per_block(
        self, sm_count: int, blocks_per_sm: int, requested: int = 0, rows: int | None = None
    ) -> int:
        """Rows per block for a launch over ``rows`` output rows (default: all valid rows).

        ``requested`` if > 0, else as few blocks as fill every SM once: one full wave of equal blocks
        wastes no SM at the tail, and taller blocks pay the ``b - 1`` warm-up rows of the running
        column sums less often.
        """
        rows = max(1, self.valid_rows if rows is None else rows)
        if requested > 0:
            return min(requested, rows)
        slots = max(1, sm_count * max(1, blocks_per_sm))
        ty = max(1, slots // self.tiles_x)
        return max(4, -(-rows // ty))


def _smem_bytes(cpad: int, tx: int, D: int, b: int, roww: int, cstr: int) -> tuple[int, int, int]:
    lww = cpad // 4 + 2
    rww = (cpad + D) // 4 + 2
    nr = b + 1
    words = nr * (lww + rww) + cpad * roww + tx * cstr + cpad + _N_REGIONS * D + 1 + 8  # + alignment
    return 4 * words, lww, rww


def bank_wavefronts(addresses: Sequence[int], width_words: int) -> int:
    """Shared-memory wavefronts for one warp-wide access (32 lanes, word addresses, 1/2/4 words each).

    The hardware serves 32-bit accesses per warp, 64-bit per half-warp and 128-bit per quarter-warp;
    within each group a bank (word address mod 32) holding several distinct words costs one extra pass.
    """
    lanes_per_phase = {1: 32, 2: 16, 4: 8}[width_words]
    total = 0
    for p in range(0, len(addresses), lanes_per_phase):
        banks: dict[int, set[int]] = {}
        for a in addresses[p : p + lanes_per_phase]:
            for w in range(width_words):
                banks.setdefault((a + w) % 32, set()).add(a + w)
        total += max(len(s) for s in banks.values())
    return total


def _warps(nt: int) -> Iterable[range]:
    return (range(w, min(w + 32, nt)) for w in range(0, nt, 32))


def _conflicts_roww(roww: int, cpad: int, gq: int, nt: int, D: int, hk: int, hruns: int) -> int:
    dp2 = D // 2
    vec = 4 if (2 * gq) % 4 == 0 else 2
    cost = 0
    for lanes in _warps(nt):  # phase V: vector stores of the column sums
        cost += bank_wavefronts([(t % cpad) * roww + 2 * (t // cpad) * gq for t in lanes], vec)
    for lanes in _warps(min(nt, dp2 * hruns)):  # phase H: the first load of each run
        cost += bank_wavefronts([(t // dp2) * hk * roww + t % dp2 for t in lanes], 1)
    return cost


def _conflicts_cstr(cstr: int, tx: int, ms: int, nt: int, D: int, hk: int, hruns: int) -> int:
    dp2 = D // 2
    cost = 0
    for lanes in _warps(nt):  # phase M: 16-byte loads, k = 0
        cost += bank_wavefronts([min(t // ms, tx - 1) * cstr + 4 * (t % ms) for t in lanes], 4)
    for lanes in _warps(min(nt, dp2 * hruns)):  # phase H stores
        cost += bank_wavefronts([(t // dp2) * hk * cstr + t % dp2 for t in lanes], 1)
    return cost


def _fast_shape(D: int, b: int, cpad: int) -> dict[str, int] | None:
    r = b // 2
    tx = cpad - 2 * r
    if tx < 8 or D % 4:
        return None
    dq = D // 4
    gq = 8 if dq % 8 == 0 else (4 if dq % 4 == 0 else dq if dq <= 16 else 0)
    if gq == 0:
        return None
    nt = cpad * (dq // gq)
    if nt > 512 and dq % 16 == 0:
        gq = 16
        nt = cpad * (dq // gq)
    if nt > 1024 or nt % 32:
        return None
    dp2 = D // 2
    hruns = nt // dp2
    if hruns < 1:
        return None
    hk = -(-tx // hruns)
    ms = 1
    while ms * 2 <= 32 and ms * 2 * tx <= nt and dp2 % (4 * ms * 2) == 0:
        ms *= 2
    if dp2 % (4 * ms):
        return None
    msw = dp2 // ms
    roww = min(
        (dp2 + p for p in range(0, 32, 4)),
        key=lambda w: (_conflicts_roww(w, cpad, gq, nt, D, hk, hruns), w),
    )
    cstr = min(
        (dp2 + p for p in range(0, 32, 4)),
        key=lambda w: (_conflicts_cstr(w, tx, ms, nt, D, hk, hruns), w),
    )
    smem, lww, rww = _smem_bytes(cpad, tx, D, b, roww, cstr)
    if smem > SMEM_BUDGET_BYTES:
        return None
    ldpt = -(-(lww + rww) // nt)
    return dict(
        cpad=cpad, tx=tx, nt=nt, gq=gq, hruns=hruns, hk=hk, ms=ms, msw=msw, roww=roww, cstr=cstr,
        lww=lww, rww=rww, ldpt=ldpt, smem_bytes=smem,
    )


def plan_disparity(width_px: int, height_px: int, num_disparities: int, block_size: int) -> DisparityPlan:
    """The kernel shape for one eye size and matcher setting.

    Raises:
        ValueError: a parameter the reference matcher would also reject (D < 2, even or < 1 block).
    """
    D, b = int(num_disparities), int(block_size)
    if D < 2 or b < 1 or b % 2 == 0 or width_px < 1 or height_px < 1:
        raise ValueError(f"bad matcher shape: {width_px}x{height_px}, D={D}, b={b}")
    r = b // 2
    x_start, x_end = r + D - 1, max(r + D - 1, width_px - r)
    y_start, y_end = r, max(r, height_px - r)
    shape = None
    if 255 * b * b < 0xFFFF:
        for cpad in _CPAD_CHOICES:
            shape = _fast_shape(D, b, cpad)
            if shape is not None:
                break
    if shape is None:
        pitch = _round_up(width_px + 16, 16)
        return DisparityPlan(width_px, height_px, D, b, False, pitch, x_start, x_end, y_start, y_end)
    tiles_x = max(1, -(-max(0, x_end - x_start) // shape["tx"]))
    last_x0_col = x_start + (tiles_x - 1) * shape["tx"] - r  # X0 of the last tile
    pitch = _round_up(max(width_px, last_x0_col + shape["cpad"] + 16), 16)
    return DisparityPlan(width_px, height_px, D, b, True, pitch, x_start, x_end, y_start, y_end, **shape)


def _round_up(n: int, m: int) -> int:
    return -(-n // m) * m


def sgm_pitch_bytes(width_px: int) -> int:
    """Row pitch (bytes) of the grey rows an SGM module reads when no SAD plan sets it (the near-range
    check's coarse pair, the host emulation): the width with 16 bytes of room, a multiple of 16."""
    return _round_up(int(width_px) + 16, 16)


def kernel_defines(plan: DisparityPlan, row_edges: Sequence[int], col_edges: Sequence[int]) -> str:
    """The ``#define`` block that specialises ``stereo.cu`` for this plan (prepended to the source)."""
    b = plan.block_size
    values: dict[str, int] = {
        "IMG_W": plan.width_px,
        "IMG_H": plan.height_px,
        "PITCH": plan.pitch_bytes,
        "NDISP": plan.num_disparities,
        "BLK": b,
        "RAD": b // 2,
        "X_START": plan.x_start,
        "X_END": plan.x_end,
        "Y_START": plan.y_start,
        "Y_END": plan.y_end,
        "RE1": int(row_edges[1]),
        "RE2": int(row_edges[2]),
        "CE1": int(col_edges[1]),
        "CE2": int(col_edges[2]),
    }
    if plan.fast:
        values.update(
            CPAD=plan.cpad, TXO=plan.tx, NT=plan.nt, GQ=plan.gq, DP2=plan.num_disparities // 2,
            HRUNS=plan.hruns, HK=plan.hk, MS=plan.ms, MSW=plan.msw, ROWW=plan.roww, CSTR=plan.cstr,
            LWW=plan.lww, RWW=plan.rww, NR=b + 1, LDPT=plan.ldpt,
        )
    else:
        # The fast kernel is still compiled (one module); give it a harmless small shape.
        values.update(
            CPAD=32, TXO=8, NT=32, GQ=1, DP2=2, HRUNS=1, HK=8, MS=1, MSW=4, ROWW=4, CSTR=4,
            LWW=10, RWW=10, NR=b + 1, LDPT=1,
        )
    return "".join(f"#define {k} {v}\n" for k, v in values.items())


# --------------------------------------------------------------------------------------------------
# OBSTACLE_DISTANCE (kernels/obstacle.cu)

#: OBSTACLE_DISTANCE kernel (``kernels/obstacle.cu``): threads per block, centimetre bins of a block's
#: histogram, and rows per block (each 5-degree bin is a column of blocks over row slices, so that its
#: ~70 columns by every row keep enough of the GPU busy).
OBSTACLE_THREADS = 256
OBSTACLE_HIST_BINS = 4096
OBSTACLE_ROWS_PER_SLICE = 32


def obstacle_slices(height_px: int) -> int:
    """Row slices (the grid's second dimension) of the OBSTACLE_DISTANCE kernel for an image height."""
    return max(1, -(-int(height_px) // OBSTACLE_ROWS_PER_SLICE))


def obstacle_defines(threads: int = OBSTACLE_THREADS) -> str:
    """The ``#define``s that ``obstacle.cu`` needs: threads per block and histogram bins."""
    return f"#define OD_THREADS {int(threads)}\n#define OD_HIST {OBSTACLE_HIST_BINS}\n"


# --------------------------------------------------------------------------------------------------
# Semi-global matcher (kernels/sgm.cu)

#: Threads per block of the SGM path and winner kernels (4 warps) and of the post-processing kernel.
SGM_PATH_THREADS = 128
SGM_POST_THREADS = 256
#: Threads per block of the peak-removal kernels (PEAK_THREADS in sgm.cu): one thread per pixel.
SGM_PEAK_THREADS = 256
#: Census block (32 × 8 threads) and rows per thread: a block covers 32 × 32 pixels.
SGM_CENSUS_TILE = (32, 8)
SGM_CENSUS_ROWS_PER_THREAD = 4
#: Rows above and below a pixel that its 9×7 census reads (``CEN_HH`` in sgm.cu).
SGM_CENSUS_HALF_HEIGHT = 3
#: ``sgm_paths`` loads 4 steps ahead below this many warps per SM (:func:`plan_sgm`).
SGM_PREFETCH_WARPS_PER_SM = 16


@dataclass(frozen=True)
class SgmPlan:
    """Shape of the SGM kernels for one (size, D, paths) and the #defines that fix it.

    Attributes:
        width_px, height_px: eye image size, px.
        num_disparities: ``D``.
        paths: 4 or 8.
        lanes_per_line: lanes of a warp that own one line (``LPL``); a warp walks ``32 / LPL`` lines.
        words_per_lane: groups of 4 disparities per lane (``WPL``); ``4·LPL·WPL = DPAD >= D``.
        run_px: pixels of a row that one line of ``sgm_wta`` takes (``RUN``).
        nbins: bins of the region histograms, one per sub-pixel disparity value (``16·(D - 1) + 1``).
        slab_rows: rows of one post-processing block (``<= 65535 / W``: 16-bit shared counters; its
            shared memory, the checked rows and the histogram, within 48 KB).
        slabs: post-processing blocks in each of the three region row bands.
        prefetch_steps: steps between a step's census loads and its path recurrence in ``sgm_paths``
            (``SGM_PF``: 2 or 4; the same results).
    """

    width_px: int
    height_px: int
    num_disparities: int
    paths: int
    lanes_per_line: int
    words_per_lane: int
    run_px: int
    nbins: int
    slab_rows: int
    slabs: tuple[int, int, int]
    prefetch_steps: int = 2

    @property
    def dpad(self) -> int:
        return 4 * self.lanes_per_line * self.words_per_lane

    @property
    def lines_per_warp(self) -> int:
        return 32 // self.lanes_per_line

    @property
    def census_pad_px(self) -> int:
        """Zero columns left of each census image (``CEN_PAD`` = ``DPAD``): ``sgm_paths`` reads the right
        census of ``x - d`` for every ``d < DPAD`` without a bounds test."""
        return self.dpad

    @property
    def census_stride_px(self) -> int:
        """Elements per census row (``CEN_STR``): the padding, the image and one more column for the
        shifted copy of the right eye, rounded up to even (16-byte aligned rows)."""
        return (self.width_px + self.census_pad_px + 2) // 2 * 2

    @property
    def volume_bytes(self) -> int:
        """Bytes of one path's cost volume (``H·W·DPAD`` uint8)."""
        return self.height_px * self.width_px * self.dpad

    @property
    def path_tasks(self) -> int:
        """Warp tasks of ``sgm_paths`` (2 × rows, 2 × columns, 4 × diagonals with 8 paths)."""
        lpw = self.lines_per_warp
        th = -(-self.height_px // lpw)
        tv = -(-self.width_px // lpw)
        td = -(-(self.width_px + self.height_px - 1) // lpw)
        return 2 * th + 2 * tv + (4 * td if self.paths == 8 else 0)

    @property
    def wta_tasks(self) -> int:
        """Warp tasks of ``sgm_wta`` (runs of ``run_px`` pixels, ``32 / LPL`` per warp)."""
        runs = -(-self.width_px // self.run_px) * self.height_px
        return -(-runs // self.lines_per_warp)

    def census_grid(self, rows: int) -> tuple[int, int, int]:
        """``sgm_census``'s grid for ``rows`` image rows: tiles of ``SGM_CENSUS_TILE`` threads, each
        thread ``SGM_CENSUS_ROWS_PER_THREAD`` rows, both eyes."""
        tw, th = SGM_CENSUS_TILE
        return -(-self.width_px // tw), max(1, -(-int(rows) // (th * SGM_CENSUS_ROWS_PER_THREAD))), 2

    @property
    def post_blocks(self) -> int:
        return sum(self.slabs)

    def device_bytes(self) -> dict[str, int]:
        """Device memory of the matcher's buffers, bytes, by buffer (what ``CupyRegionEstimator`` allocates)."""
        hw = self.height_px * self.width_px
        return {
            "path_volumes": self.paths * self.volume_bytes,
            "census_left_right": 3 * 8 * self.height_px * self.census_stride_px,  # the right eye twice
            "left_winner_int32": 4 * hw,
            "right_keys_uint32": 4 * hw,
            "disparity_int16": 2 * hw,
            "region_histogram": 9 * self.nbins * 4,
        }

    def shared_bytes(self) -> int:
        """Static shared memory of the largest SGM block (``sgm_post``), bytes."""
        return _sgm_post_smem(self.nbins, self.slab_rows, self.width_px)


def _sgm_post_smem(nbins: int, slab_rows: int, width_px: int) -> int:
    words = (3 * nbins + 1) // 2
    return 4 * words + 2 * (slab_rows + 2) * width_px + 4 * (SGM_POST_THREADS // 32) + 8


def plan_sgm(width_px: int, height_px: int, num_disparities: int, paths: int, row_edges: Sequence[int],
             lanes_per_line: int = 0, prefetch_steps: int = 0, sm_count: int = 0) -> SgmPlan:
    """The SGM kernels' shape for one eye size, disparity count and path count.

    ``lanes_per_line`` 0 picks ``min(32, DPAD/4)`` lanes, ``DPAD`` the power of two >= D (at least 16),
    each with ``DPAD / (4·lanes)`` groups of 4 disparities (64 disparities: 16 lanes of 1 group; 128: 32
    of 1; 256: 32 of 2): the layouts verified bit-exact on the device. 16 lanes of 2 groups at 128
    disparities measured 12 % faster kernels on an H100 (``gpu.sgm_lanes_per_line = 16``; docs/gpu_notes.md).

    ``prefetch_steps`` 0 (``gpu.sgm_prefetch_steps``) picks 4 where ``sgm_paths`` has fewer than
    :data:`SGM_PREFETCH_WARPS_PER_SM` warps per SM of a GPU with ``sm_count`` SMs (too few warps per
    scheduler to hide the census loads' latency: 672×376/64 on an H100, 8 warps per SM, measured 0.163 →
    0.142 ms), else 2 (more registers only cost occupancy there: 1280×720/128, 30 warps per SM, measured
    0.460 → 0.507 ms with 4); 2 when ``sm_count`` is 0 (unknown).

    Raises:
        ValueError: a parameter the reference would also reject, or a shape that does not fit.
    """
    D = int(num_disparities)
    w, h = int(width_px), int(height_px)
    if not 2 <= D <= 256 or paths not in (4, 8) or w < 1 or h < 3:
        raise ValueError(f"bad SGM shape: {w}x{h}, D={D}, paths={paths}")
    if lanes_per_line:
        lpl = int(lanes_per_line)
        if lpl not in (4, 8, 16, 32):
            raise ValueError(f"lanes_per_line must be 4, 8, 16 or 32, got {lpl}")
        wpl = max(1, -(-D // (4 * lpl)))
    else:
        dpad = 16
        while dpad < D:
            dpad *= 2
        lpl = min(32, dpad // 4)
        wpl = max(1, dpad // (4 * lpl))
    nbins = 16 * (D - 1) + 1
    # about 384 post blocks: one wave on a large GPU (1280x720: 2 rows, 361 blocks, measured best of 1/2/4)
    slab = max(1, min(65535 // w, 8, -(-h // 384)))
    while slab > 1 and _sgm_post_smem(nbins, slab, w) > SMEM_BUDGET_BYTES:
        slab -= 1
    if _sgm_post_smem(nbins, slab, w) > SMEM_BUDGET_BYTES:
        raise ValueError(
            f"SGM post block needs {_sgm_post_smem(nbins, slab, w)} bytes of shared memory (> {SMEM_BUDGET_BYTES}) "
            f"at {w} px and {D} disparities"
        )
    bands = [int(row_edges[1]) - int(row_edges[0]), int(row_edges[2]) - int(row_edges[1]),
             int(row_edges[3]) - int(row_edges[2])]
    slabs = tuple(-(-b // slab) for b in bands)
    # sgm_wta's runs: 32 px with 4 paths (H100: 0.219 -> 0.211 ms at 1280x720/128, 0.049 -> 0.044 at
    # 672x376/64), 64 with 8 (0.368 -> 0.365); every length gives the same results
    run = 32 if paths == 4 else 64
    plan = SgmPlan(w, h, D, int(paths), lpl, wpl, run, nbins, slab, slabs)  # type: ignore[arg-type]
    pf = int(prefetch_steps)
    if pf == 0:
        few_warps = 0 < plan.path_tasks < SGM_PREFETCH_WARPS_PER_SM * int(sm_count)
        pf = 4 if few_warps else 2
    if pf not in (2, 4):
        raise ValueError(f"prefetch_steps must be 0, 2 or 4, got {prefetch_steps}")
    return dataclasses.replace(plan, prefetch_steps=pf)


def sgm_defines(plan: SgmPlan, pitch_bytes: int, row_edges: Sequence[int], col_edges: Sequence[int]) -> str:
    """The ``#define`` block that specialises ``sgm.cu`` for this plan (prepended to the source)."""
    values = {
        "IMG_W": plan.width_px,
        "IMG_H": plan.height_px,
        "PITCH": int(pitch_bytes),
        "NDISP": plan.num_disparities,
        "LPL": plan.lanes_per_line,
        "WPL": plan.words_per_lane,
        "NPATHS": plan.paths,
        "SGM_PF": plan.prefetch_steps,
        "RUN": plan.run_px,
        "CT_W": SGM_CENSUS_TILE[0],
        "CT_H": SGM_CENSUS_TILE[1],
        "CT_R": SGM_CENSUS_ROWS_PER_THREAD,
        "NBINS": plan.nbins,
        "SLAB_ROWS": plan.slab_rows,
        "NSLAB0": plan.slabs[0],
        "NSLAB1": plan.slabs[1],
        "NSLAB2": plan.slabs[2],
        "RE1": int(row_edges[1]),
        "RE2": int(row_edges[2]),
        "CE1": int(col_edges[1]),
        "CE2": int(col_edges[2]),
        "NEAR_S": NEAR_SCALE,
    }
    return "".join(f"#define {k} {v}\n" for k, v in values.items())
