"""Back-projection of a volume by sub-arrays, for radar positions whose channels lie on a line.

The MMWCAS virtual array is a line of 86 phase centres. The matched filter of a group of channels
on a line depends only on a voxel's coordinates about that line, u along it and rho from it
(the sum over channels of MF(sqrt((u - a_k)^2 + rho^2))). So for each radar position and each
group of adjacent channels the group's sum is evaluated once, exactly (the kernel of
:mod:`twinfocus.imaging.backprojection.numba_backend`), on a (u, rho) table that covers the volume, with the carrier
at the group's centre divided out so that what is tabulated is smooth; each voxel then reads
the table by bilinear interpolation and puts its carrier back. Work per position: K channels on
the table's nodes plus G groups per voxel, against K channels per voxel directly -- an order
of magnitude less on a 100 x 100 x 40 volume.

Accuracy: the table's steps are set from the fastest variation the tabulated sum can have (the
group's half length A over the nearest distance rho_min in u, half that in rho, plus the
chirp's baseband B / c), so that the bilinear error of each term stays below
:data:`TABLE_ERROR` of its amplitude; tests compare against the direct back-projection and the
brute-force sum.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from twinfocus.imaging.backprojection.numba_backend import (
    _accumulate_channel,
    _channel_scratch,
    _interpolation_table,
    _kernel_constants,
    pixel_block,
    prepare_profiles,
)
from twinfocus.imaging.grid import VolumeGrid
from twinfocus.imaging.range_geometry import DEFAULT_OVERSAMPLE, local_frame, turns_per_m
from twinfocus.radar.fmcw import C_M_PER_S, Chirp

#: bound on the bilinear interpolation error of the table, relative to each term's amplitude
TABLE_ERROR = 1e-2
#: channels off their position's best-fit line by more than this (metres) rule the method out: the
#: carrier's phase would err by 4 pi fc / c times it (0.003 rad at 77 GHz)
LINE_TOLERANCE_M = 1e-6
#: relative cost of one group read per voxel against one channel evaluated per voxel (measured: the
#: bilinear gather of two 16-byte pairs and the carrier)
VOXEL_COST = 1.5
#: bytes of tables held at once (a chunk of positions), besides the range profiles
TABLE_BYTES = 64 * 2**20


def _line_frames(positions_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Each position's channels as points on a line: (centre float64 (M, 3), unit direction
    float64 (M, 3), a float64 (M, K) metres along it), or None when any channel is off its line
    by more than :data:`LINE_TOLERANCE_M`. Directions share one sense (position 0's), so that a
    channel keeps its place in the order along the line."""
    centre = positions_m.mean(axis=1)
    rel = positions_m - centre[:, None, :]
    _, _, vt = np.linalg.svd(rel, full_matrices=False)
    w = vt[:, 0, :]
    w = w * np.sign(np.einsum("mc,c->m", w, w[0]))[:, None]
    a = np.einsum("mkc,mc->mk", rel, w)
    off = rel - a[..., None] * w[:, None, :]
    if not np.isfinite(a).all() or np.sqrt((off**2).sum(axis=-1)).max() > LINE_TOLERANCE_M:
        return None
    return centre, w, a


def _box_extent(grid: VolumeGrid, centre: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, ...]:
    """Bounds over the volume's voxels of u (along each position's line) and rho (from it): four
    float64 (M,) arrays u_min, u_max, rho_min, rho_max, metres. u is exact (linear, so at the
    corners); rho from a 17^3 sub-lattice, widened by that lattice's half cell diagonal (rho moves
    by at most the distance moved)."""
    p = grid.plane
    axes = [np.linspace(p.x0, p.x1, 17), np.linspace(p.y0, p.y1, 17), np.linspace(grid.z0, grid.z1, 17)]
    pad = 0.5 * math.sqrt(sum(((ax[-1] - ax[0]) / 16) ** 2 for ax in axes))
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    u_min = np.empty(len(centre))
    u_max, r_min, r_max = np.empty_like(u_min), np.empty_like(u_min), np.empty_like(u_min)
    for lo in range(0, len(centre), 256):
        d = pts[None] - centre[lo : lo + 256, None, :]
        u = np.einsum("mpc,mc->mp", d, w[lo : lo + 256])
        rho = np.sqrt(np.maximum((d**2).sum(axis=-1) - u**2, 0.0))
        u_min[lo : lo + 256], u_max[lo : lo + 256] = u.min(axis=1), u.max(axis=1)
        r_min[lo : lo + 256] = np.maximum(rho.min(axis=1) - pad, 0.0)
        r_max[lo : lo + 256] = rho.max(axis=1) + pad
    return u_min, u_max, r_min, r_max


class LinePlan:
    """How a volume is formed by sub-arrays (module docstring): the groups, the table steps and
    extents, and the estimated cost against the direct back-projection (channel evaluations).

    frames : :func:`_line_frames`' (centres, directions, a); extent : :func:`_box_extent`'s;
    groups : channel groups per position (adjacent channels along the line, as even as they split)."""

    def __init__(self, chirp: Chirp, grid: VolumeGrid, frames, extent, groups: int):
        centre, w, a = frames
        n_pos, n_ch = a.shape
        order = np.argsort(a[0])
        self.group_of = np.empty(n_ch, np.int64)
        for g, members in enumerate(np.array_split(order, groups)):
            self.group_of[members] = g
        self.groups = groups
        lo = np.full((n_pos, groups), np.inf)
        hi = np.full((n_pos, groups), -np.inf)
        for g in range(groups):
            sel = a[:, self.group_of == g]
            lo[:, g], hi[:, g] = sel.min(axis=1), sel.max(axis=1)
        self.group_centre = 0.5 * (lo + hi)  # (M, G) metres along the line
        half = float(0.5 * (hi - lo).max())
        self.offset = a - self.group_centre[:, self.group_of]  # (M, K) each channel from its group's centre
        u_min, u_max, r_min, r_max = extent
        rho_near = max(float(r_min.min()), chirp.range_resolution_m)
        k_carrier = 2 * np.pi * turns_per_m(chirp)
        k_base = 2 * np.pi * chirp.bandwidth_hz / C_M_PER_S
        step = math.sqrt(8 * TABLE_ERROR)
        self.du = step / (k_carrier * half / rho_near + k_base)
        self.drho = step / (k_carrier * half / (2 * rho_near) + k_base)
        span_u = float((u_max - u_min).max())
        self.n_u = int(math.ceil(span_u / self.du)) + 3
        self.n_rho = int(math.ceil(float((r_max - r_min).max()) / self.drho)) + 3
        # table origins: one node of slack below, so that a voxel at the edge has a cell
        self.u0 = u_min[:, None] - self.group_centre - self.du  # (M, G)
        self.rho0 = np.maximum(r_min - self.drho, 0.0)  # (M,)
        self.centre, self.direction = centre, w
        voxels = int(np.prod(grid.shape))
        self.cost = n_pos * (n_ch * self.n_u * self.n_rho + VOXEL_COST * groups * voxels)
        self.direct_cost = float(n_pos * n_ch * voxels)

    @property
    def table_bytes_per_position(self) -> int:
        return 8 * self.groups * self.n_u * self.n_rho


def plan(positions_m: np.ndarray, chirp: Chirp, grid: VolumeGrid) -> LinePlan | None:
    """The cheapest :class:`LinePlan` over the group counts whose tables fit :data:`TABLE_BYTES`,
    or None when the channels are not on lines or the plan would not save at least half of the
    direct back-projection's work.

    positions_m : float64 (M, K, 3) phase centres, metres."""
    positions_m = np.asarray(positions_m, dtype=np.float64)
    if positions_m.shape[1] < 4:
        return None
    frames = _line_frames(positions_m)
    if frames is None:
        return None
    extent = _box_extent(grid, frames[0], frames[1])
    best = None
    n_ch = positions_m.shape[1]
    for groups in sorted({max(1, n_ch // s) for s in (4, 6, 8, 11, 16, 22, 29, 43, n_ch)}):
        p = LinePlan(chirp, grid, frames, extent, groups)
        if p.table_bytes_per_position > TABLE_BYTES:  # one position's tables would not fit the bound
            continue
        if best is None or p.cost < best.cost:
            best = p
    return best if best is not None and best.cost < 0.5 * best.direct_cost else None


@njit(parallel=True, fastmath=True, cache=True)
def _tables_kernel(tab, offset, group_of, u0, rho0, du, drho, n_u, n_rho, groups, r0, inv_dr, tpm, kc, out):
    """out[m, g, iu, ir] (re, im) = sum over channels k of group g of MF_mk at (u, rho) =
    (u0[m, g] + iu du, rho0[m] + ir drho) about the group's centre, times exp(+j 2 pi tpm (R - r0))
    with R = sqrt(u^2 + rho^2) (the group's carrier divided out). Parallel over positions."""
    n_pos, n_ch = offset.shape
    n = n_u * n_rho
    half = kc[1]
    for m in prange(n_pos):
        px = np.empty(n, tab.dtype)
        py = np.empty(n, tab.dtype)
        pz = np.zeros(n, tab.dtype)
        acc_re = np.empty(n, tab.dtype)
        acc_im = np.empty(n, tab.dtype)
        idx, frac, cos_buf, sin_buf = _channel_scratch(n, tab)
        for g in range(groups):
            for iu in range(n_u):
                for ir in range(n_rho):
                    px[iu * n_rho + ir] = u0[m, g] + iu * du
                    py[iu * n_rho + ir] = rho0[m] + ir * drho
            acc_re[:] = 0
            acc_im[:] = 0
            for k in range(n_ch):
                if group_of[k] == g:
                    _accumulate_channel(
                        tab[m, k],
                        offset[m, k],
                        kc[0],
                        kc[0],
                        px,
                        py,
                        pz,
                        r0,
                        inv_dr,
                        tpm,
                        kc,
                        acc_re,
                        acc_im,
                        0,
                        n,
                        idx,
                        frac,
                        cos_buf,
                        sin_buf,
                    )
            for q in range(n):
                t = (math.sqrt(px[q] * px[q] + py[q] * py[q]) - r0) * tpm
                r = t - np.floor(t + half)
                c, s = _cis(r, kc)
                out[m, g, q // n_rho, q % n_rho, 0] = acc_re[q] * c - acc_im[q] * s
                out[m, g, q // n_rho, q % n_rho, 1] = acc_re[q] * s + acc_im[q] * c


@njit(inline="always", fastmath=True)
def _cis(r, kc):
    """(cos 2 pi r, sin 2 pi r) for r in [-1/2, 1/2] with :func:`_kernel_constants`' typed
    polynomial coefficients."""
    r2 = r * r
    s = r * (kc[3] + r2 * (kc[4] + r2 * (kc[5] + r2 * (kc[6] + r2 * (kc[7] + r2 * (kc[8] + r2 * kc[9]))))))
    c = kc[10] + r2 * (
        kc[11] + r2 * (kc[12] + r2 * (kc[13] + r2 * (kc[14] + r2 * (kc[15] + r2 * (kc[16] + r2 * kc[17])))))
    )
    return c, s


@njit(parallel=True, fastmath=True, cache=True)
def _voxels_kernel(
    tables, centre, direction, gcentre, u0, rho0, inv_du, inv_drho, px, py, pz, r0, tpm, kc, block, out_re, out_im
):
    """out[p] += sum over positions m and groups g of the bilinear read of tables[m, g] at the
    voxel's (u - gcentre[m, g], rho) times exp(-j 2 pi tpm (R - r0)). Parallel over voxel blocks."""
    n_pos, groups = gcentre.shape
    n_u, n_rho = tables.shape[2], tables.shape[3]
    umax = tables.dtype.type(n_u - 1.0001)
    rmax = tables.dtype.type(n_rho - 1.0001)
    zero, half = kc[0], kc[1]
    n_pix = px.shape[0]
    n_blocks = (n_pix + block - 1) // block
    for b in prange(n_blocks):
        lo = b * block
        hi = min(lo + block, n_pix)
        n = hi - lo
        acc_re = np.zeros(n, px.dtype)
        acc_im = np.zeros(n, px.dtype)
        u = np.empty(n, px.dtype)
        rho2 = np.empty(n, px.dtype)
        ir = np.empty(n, np.int32)
        fr = np.empty(n, px.dtype)
        iu = np.empty(n, np.int32)
        fu = np.empty(n, px.dtype)
        cos_buf = np.empty(n, px.dtype)
        sin_buf = np.empty(n, px.dtype)
        for m in range(n_pos):
            cx, cy, cz = centre[m, 0], centre[m, 1], centre[m, 2]
            wx, wy, wz = direction[m, 0], direction[m, 1], direction[m, 2]
            for q in range(n):
                dx = px[lo + q] - cx
                dy = py[lo + q] - cy
                dz = pz[lo + q] - cz
                uq = dx * wx + dy * wy + dz * wz
                r2 = max(dx * dx + dy * dy + dz * dz - uq * uq, zero)
                u[q] = uq
                rho2[q] = r2
                v = min(max((math.sqrt(r2) - rho0[m]) * inv_drho, zero), rmax)
                fl = np.floor(v)
                ir[q] = np.int32(fl)
                fr[q] = v - fl
            for g in range(groups):
                gc = gcentre[m, g]
                ug0 = u0[m, g]
                for q in range(n):
                    ug = u[q] - gc
                    v = min(max((ug - ug0) * inv_du, zero), umax)
                    fl = np.floor(v)
                    iu[q] = np.int32(fl)
                    fu[q] = v - fl
                    t = (math.sqrt(ug * ug + rho2[q]) - r0) * tpm
                    c, s = _cis(t - np.floor(t + half), kc)
                    cos_buf[q] = c
                    sin_buf[q] = s
                tg = tables[m, g]
                for q in range(n):
                    i = iu[q]
                    j = ir[q]
                    a = fu[q]
                    e = fr[q]
                    re0 = tg[i, j, 0] + e * (tg[i, j + 1, 0] - tg[i, j, 0])
                    im0 = tg[i, j, 1] + e * (tg[i, j + 1, 1] - tg[i, j, 1])
                    re1 = tg[i + 1, j, 0] + e * (tg[i + 1, j + 1, 0] - tg[i + 1, j, 0])
                    im1 = tg[i + 1, j, 1] + e * (tg[i + 1, j + 1, 1] - tg[i + 1, j, 1])
                    vr = re0 + a * (re1 - re0)
                    vi = im0 + a * (im1 - im0)
                    c = cos_buf[q]
                    s = sin_buf[q]
                    acc_re[q] += vr * c + vi * s
                    acc_im[q] += vi * c - vr * s
        out_re[lo:hi] += acc_re
        out_im[lo:hi] += acc_im


def backproject_volume(
    data: np.ndarray,
    positions_m: np.ndarray,
    chirp: Chirp,
    grid: VolumeGrid,
    line_plan: LinePlan,
    *,
    oversample: int = DEFAULT_OVERSAMPLE,
    progress=None,
) -> np.ndarray:
    """The back-projected volume by sub-arrays (module docstring): complex64 ``grid.shape``, what
    :func:`twinfocus.imaging.backprojection.numba_backend.backproject` gives within :data:`TABLE_ERROR`.

    data : complex (M, K, N) samples; positions_m : float64 (M, K, 3) phase centres, metres;
    line_plan : :func:`plan`'s for these positions and grid. float32 arithmetic on the CPU."""
    dtype = np.float32
    positions_m = np.asarray(positions_m, dtype=np.float64)
    points = grid.points()
    origin = points.mean(axis=0)
    _, pts = local_frame(positions_m, points, dtype)
    centre = (line_plan.centre - origin).astype(dtype)
    direction = line_plan.direction.astype(dtype)
    px, py, pz = pts[:, 0].copy(), pts[:, 1].copy(), pts[:, 2].copy()
    out_re = np.zeros(pts.shape[0], dtype)
    out_im = np.zeros(pts.shape[0], dtype)
    block = pixel_block(pts.shape[0])
    n_pos = data.shape[0]
    chunk = max(
        1, min(int(4e6 // max(1, data.shape[1] * chirp.n_samples)), TABLE_BYTES // line_plan.table_bytes_per_position)
    )
    tpm = dtype(turns_per_m(chirp))
    # the tables' nodes lie within a cell of a voxel: the range window of the voxels' box grown by
    # a cell diagonal covers them (prepare_profiles keeps 2 range steps of margin besides)
    grow = math.hypot(line_plan.du, line_plan.drho)
    lo_box, hi_box = points.min(axis=0) - grow, points.max(axis=0) + grow
    corners = np.array(
        [[x, y, z] for x in (lo_box[0], hi_box[0]) for y in (lo_box[1], hi_box[1]) for z in (lo_box[2], hi_box[2])]
    )
    for lo in range(0, n_pos, chunk):
        hi = min(lo + chunk, n_pos)
        pre, pim, r0, dr = prepare_profiles(data[lo:hi], positions_m[lo:hi], chirp, corners, oversample, dtype)
        kc = _kernel_constants(dtype, pre.shape[2] - 1.0001)
        tables = np.empty((hi - lo, line_plan.groups, line_plan.n_u, line_plan.n_rho, 2), dtype)
        _tables_kernel(
            _interpolation_table(pre, pim),
            line_plan.offset[lo:hi].astype(dtype),
            line_plan.group_of,
            line_plan.u0[lo:hi].astype(dtype),
            line_plan.rho0[lo:hi].astype(dtype),
            dtype(line_plan.du),
            dtype(line_plan.drho),
            line_plan.n_u,
            line_plan.n_rho,
            line_plan.groups,
            dtype(r0),
            dtype(1.0 / dr),
            tpm,
            kc,
            tables,
        )
        _voxels_kernel(
            tables,
            centre[lo:hi],
            direction[lo:hi],
            line_plan.group_centre[lo:hi].astype(dtype),
            line_plan.u0[lo:hi].astype(dtype),
            line_plan.rho0[lo:hi].astype(dtype),
            dtype(1.0 / line_plan.du),
            dtype(1.0 / line_plan.drho),
            px,
            py,
            pz,
            dtype(r0),
            tpm,
            kc,
            block,
            out_re,
            out_im,
        )
        if progress is not None:
            progress(hi, n_pos)
    return (out_re + 1j * out_im).astype(np.complex64).reshape(grid.shape)
