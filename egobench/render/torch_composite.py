"""The torch oracle's compositing (step 4 of `torch_backend`'s pipeline): front-to-back compositing of the
depth-sorted intersections of each tile in chunks, with gsplat's rules (alpha = min(0.999, o exp(-s)), skipped
below 1/255, stopped at T <= 1e-4), and its backward (back to front, recovering T by division), as one
`torch.autograd.Function` (`composite`)."""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor


ALPHA_MIN = 1.0 / 255.0  # Gaussians with alpha below this are skipped for a pixel
ALPHA_MAX = 0.999  # alpha is clamped to this
T_STOP = 1e-4  # compositing stops before T * (1 - alpha) <= T_STOP
SIGMA_CAP = 50.0  # exponents above this give alpha < 1/255 anyway; capped to keep exp() off denormals


# coefficient columns: 3DGS 7 (6 polynomial + log o), 2DGS 14 (9 cross + 4 filter + log o)
LOG_OPACITY_COLUMN = {"3dgs": 6, "2dgs": 13}


@dataclass
class _Plan:
    """Everything `_Composite` needs besides the differentiable inputs."""

    mode: str
    starts: Tensor  # [NB]
    lengths: Tensor  # [NB]
    T_init: Tensor  # [NB, P] 1 for pixels to render, 0 for pixels not taken from this bin
    phi: Tensor  # [P, 6]: 1, x, y, x^2, xy, y^2 of tile-local pixel centres
    depth_channel: int  # feature channel holding the depth (used by the 2DGS distortion)
    chunk: int  # candidates per step
    max_pairs: int  # pixel-candidate pairs per step (memory bound)
    store_elems: int = 1 << 24  # forward intermediates kept for the backward (elements, upper bound);
    # above it the backward recomputes each chunk instead (as gsplat's CUDA kernels do)


def _tile_phi(tile_size: int, dtype: torch.dtype, device) -> Tensor:
    """[P, 6] monomials of tile-local pixel centres (tile centre at 0), row-major pixels."""
    c = torch.arange(tile_size, dtype=dtype, device=device) + 0.5 - 0.5 * tile_size
    py, px = torch.meshgrid(c, c, indexing="ij")
    px, py = px.reshape(-1), py.reshape(-1)
    return torch.stack([torch.ones_like(px), px, py, px * px, px * py, py * py], dim=-1)


class _ChunkEval:
    """Exponent sigma' = sigma - log(o) of every (pixel, candidate) pair of a chunk."""

    def __init__(self, mode: str, phi: Tensor):
        self.mode = mode
        self.phi6 = phi  # [P, 6]
        self.phi3 = phi[:, :3].contiguous()  # [P, 3]
        self.phi4 = torch.cat([phi[:, :3], phi[:, 3:4] + phi[:, 5:6]], dim=1)  # [P, 4]: 1, x, y, x^2+y^2

    def sigma(self, cf: Tensor) -> tuple[Tensor, tuple]:
        A, S, _ = cf.shape
        if self.mode == "3dgs":
            s = torch.bmm(self.phi6.expand(A, -1, -1), cf[..., :6].transpose(1, 2))  # [A, P, S]
            return s, ()
        P = self.phi3.shape[0]
        c9 = cf[..., :9].reshape(A, S, 3, 3).permute(0, 3, 1, 2).reshape(A, 3, S * 3)
        xyz = torch.bmm(self.phi3.expand(A, -1, -1), c9).reshape(A, P, S, 3)
        X, Y, Z = xyz.unbind(-1)
        nz = Z != 0
        Zs = torch.where(nz, Z, torch.ones_like(Z))
        g3 = torch.where(nz, (X * X + Y * Y) / (Zs * Zs), torch.full_like(Z, float("inf")))
        g2 = torch.bmm(self.phi4.expand(A, -1, -1), cf[..., 9:13].transpose(1, 2))  # [A, P, S]
        use3 = g3 <= g2
        s = 0.5 * torch.where(use3, g3, g2) - cf[:, None, :, 13]
        return s, (X, Y, Zs, g3, use3)

    def coef_grad(self, G: Tensor, cf: Tensor, saved: tuple) -> Tensor:
        """G = dL/dsigma' [A, P, S] -> dL/dcoef [A, S, Kg] (3DGS: Kg = 6, the log(o) column's
        gradient is zero (folded into c0) and is added by the caller; 2DGS: Kg = Kc)."""
        A, P, S = G.shape
        if self.mode == "3dgs":
            return torch.bmm(G.transpose(1, 2), self.phi6.expand(A, -1, -1))  # [A, S, 6]
        X, Y, Zs, g3, use3 = saved
        G3 = torch.where(use3, 0.5 * G, torch.zeros_like(G))
        G2 = 0.5 * G - G3
        inv_z2 = 1.0 / (Zs * Zs)
        g_xyz = torch.stack([G3 * 2 * X * inv_z2, G3 * 2 * Y * inv_z2, -G3 * 2 * torch.where(use3, g3, 0) / Zs], -1)
        gc9 = torch.bmm(g_xyz.reshape(A, P, S * 3).transpose(1, 2), self.phi3.expand(A, -1, -1))  # [A, S*3, 3]
        gc4 = torch.bmm(G2.transpose(1, 2), self.phi4.expand(A, -1, -1))  # [A, S, 4]
        glo = -G.sum(1)  # [A, S]
        return torch.cat([gc9.reshape(A, S, 9), gc4, glo[..., None]], dim=-1)


def _chunk_schedule(plan: _Plan, n_bins: int, P: int, device):
    """(number of candidate chunks, bins per group) of a plan; `done` filtering is applied by the caller."""
    max_len = int(plan.lengths.max()) if n_bins else 0
    n_chunks = (max_len + plan.chunk - 1) // plan.chunk
    group = max(1, plan.max_pairs // (P * plan.chunk))
    return n_chunks, group


def _pad_index(plan: _Plan, bins: Tensor, c: int, M: int) -> Tensor:
    ar = torch.arange(c * plan.chunk, (c + 1) * plan.chunk, device=plan.starts.device)
    idx = plan.starts[bins, None] + ar[None, :]
    return torch.where(ar[None, :] < plan.lengths[bins, None], idx, torch.full_like(idx, M))  # [A, S]


def _forward_step(ev: _ChunkEval, cf: Tensor, T_all: Tensor, backward: bool):
    """Front-to-back compositing of one chunk (in-place ops: this is the hot loop).

    T_all [A, P]: product of (1 - alpha) over every valid earlier candidate (composited, or the
    one that stopped the pixel). Returns alpha, 1 - alpha, T_inc (T after each candidate, as if
    composited) and w = alpha * T_exc for composited pairs (0 otherwise), all [A, P, S].
    """
    s, saved = ev.sigma(cf)
    # o * exp(-sigma); the exponent is capped at SIGMA_CAP (alpha ~ 2e-22, thresholded to 0 below
    # either way): exp of arguments below about -88 yields denormals, ~30x slower on CPU
    alpha = s.clamp_(max=SIGMA_CAP).neg_().exp_()
    # alpha reaches the clamp only where o >= 0.999: build the mask only for such chunks
    can_clamp = backward and bool((cf[..., LOG_OPACITY_COLUMN[ev.mode]] >= math.log(ALPHA_MAX)).any())
    clamped = (alpha >= ALPHA_MAX) if can_clamp else None
    alpha.clamp_(max=ALPHA_MAX)
    alpha = F.threshold_(alpha, ALPHA_MIN, 0.0)  # skip alpha < 1/255
    one_m = torch.rsub(alpha, 1.0)
    T_inc = torch.cumprod(one_m, dim=2).mul_(T_all[:, :, None])
    # gsplat's exclusive stop rule: composited while T_inc > 1e-4 (T_all carries the stopper)
    w = F.threshold(T_inc, T_STOP, 0.0).div_(one_m).mul_(alpha)
    return saved, clamped, alpha, one_m, T_inc, w


@contextlib.contextmanager
def _flush_denormal():
    """Flush denormals while compositing (exp of far pairs would otherwise slow CPU kernels)."""
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(False)


def _store_fits(plan: _Plan) -> bool:
    """Whether keeping every chunk's intermediates (upper bound over all chunks) fits plan.store_elems."""
    NB, P = plan.T_init.shape
    if NB == 0:
        return True
    n_chunks, _ = _chunk_schedule(plan, NB, P, plan.T_init.device)
    per_pair = 2 if plan.mode == "3dgs" else 14  # T_inc, w (+ 2DGS: X, Y, Z, g3, use3, 1 - alpha, distortion terms)
    return NB * P * n_chunks * plan.chunk * per_pair <= plan.store_elems


def _padded(coef: Tensor, feat: Tensor, mode: str) -> tuple[Tensor, Tensor]:
    """coef [M, Kc], feat [M, Cf] -> [M + 1, ...] with a padding row M: exponent +inf-like
    (alpha = 0), zero features."""
    Kc, Cf = coef.shape[1], feat.shape[1]
    pad = torch.zeros(1, Kc, dtype=coef.dtype, device=coef.device)
    if mode == "3dgs":
        pad[0, 0] = 1e30
        pad[0, 6] = -1e30
    else:
        pad[0, 13] = -1e30  # log(opacity) -> alpha = 0
    return torch.cat([coef.detach(), pad], 0), torch.cat([feat.detach(), feat.new_zeros(1, Cf)], 0)


def _composite_chunk(step: tuple, Fb: Tensor, T_comp: Tensor, Db: Tensor, want_dist: bool) -> None:
    """Forward: adds one chunk's weighted features to Fb [NB, P, Cf], its weights' sum off T_comp
    [NB, P] and (2DGS) its distortion to Db [NB, P], in place."""
    bins, idx_flat, cf, ft, saved, clamped, T_inc, w, dist_terms = step
    Fb[bins] += torch.bmm(w, ft)
    T_comp[bins] -= w.sum(-1)  # telescoping: sum of weights = drop of composited T
    if want_dist:
        z, wz, cwz, A_exc, W_exc = dist_terms
        Db[bins] += 2.0 * (wz * W_exc - w * A_exc).sum(-1)


@dataclass
class _BackwardState:
    """Output gradients, forward results and the accumulators of `_Composite`'s backward."""

    gF: Tensor  # [NB, P, Cf] dL/dF
    gT: Tensor  # [NB, P] dL/dT
    gD: Tensor  # [NB, P] dL/ddist
    Fb: Tensor  # [NB, P, Cf] forward features
    T_fin: Tensor  # [NB, P] forward composited transmittance
    Db: Tensor  # [NB, P] forward distortion
    gcoef: Tensor  # [M + 1, Kg] (row M: the discarded padding)
    gfeat: Tensor  # [M + 1, Cf]
    E_tot: Tensor  # [NB, P] sum_k e_k w_k
    gTT: Tensor  # [NB, P] dL/dT_final * T_final
    E_carry: Tensor  # [NB, P] sum of e_k w_k over the chunks done

    @staticmethod
    def start(grads: tuple, mode: str, Kc: int, Cf: int, M: int) -> "_BackwardState":
        gF, gT, gD, Fb, T_fin, Db = grads
        dtype, device = Fb.dtype, Fb.device
        Kg = 6 if mode == "3dgs" else Kc  # 3DGS: the log(o) column's gradient is zero
        gcoef = torch.zeros(M + 1, Kg, dtype=dtype, device=device)
        gfeat = torch.zeros(M + 1, Cf, dtype=dtype, device=device)
        E_tot = (gF * Fb).sum(-1) + 2.0 * gD * Db  # [NB, P]: sum_k e_k w_k
        gTT = gT * T_fin  # dL/dT_final * T_final
        E_carry = torch.zeros(T_fin.shape, dtype=dtype, device=device)
        return _BackwardState(gF, gT, gD, Fb, T_fin, Db, gcoef, gfeat, E_tot, gTT, E_carry)

    def finish(self, M: int, Kc: int) -> tuple[Tensor, Tensor]:
        """-> (dL/dcoef [M, Kc], dL/dfeat [M, Cf])."""
        Kg = self.gcoef.shape[1]
        if Kg < Kc:
            return F.pad(self.gcoef[:M], (0, Kc - Kg)), self.gfeat[:M]
        return self.gcoef[:M], self.gfeat[:M]


def _backward_chunk(step: tuple, ev: _ChunkEval, st: _BackwardState, dch: int, want_dist: bool) -> None:
    """Backward of one chunk: writes its candidates' rows of st.gcoef / st.gfeat and advances st.E_carry."""
    bins, idx_flat, cf, ft, saved, clamped, T_inc, w, dist_terms = step
    gFa = st.gF[bins]  # [A, P, Cf]
    e = torch.bmm(gFa, ft.transpose(1, 2))  # [A, P, S]: dL/dw_k through the features
    if want_dist:
        z, wz, cwz, A_exc, W_exc = dist_terms
        gDa = st.gD[bins][:, :, None]
        Z_tot = st.Fb[bins][:, :, dch][:, :, None]
        W_tot = (1.0 - st.T_fin[bins])[:, :, None]
        W_after = W_tot - W_exc - w  # sum_{j>k} w_j
        A_after = Z_tot - A_exc - wz  # sum_{j>k} w_j z_j
        e = e + 2.0 * gDa * ((z * W_exc - A_exc) + (A_after - z * W_after))
        g_z = (2.0 * gDa * w * (W_exc - W_after)).sum(1)  # [A, S]
    ew = e * w
    cum = torch.cumsum(ew, 2) + st.E_carry[bins][:, :, None]
    st.E_carry[bins] = cum[:, :, -1]
    suffix = st.E_tot[bins][:, :, None] - cum  # sum_{j>k} e_j w_j
    # dL/dsigma' = -alpha dL/dalpha, dL/dalpha = e T_exc - (suffix + gT T_final) / (1 - alpha);
    # for composited pairs alpha / (1 - alpha) = w / T_inc, for the others w = 0
    ratio = w / T_inc.clamp(min=1e-30)
    G = ratio.mul_(suffix.add_(st.gTT[bins][:, :, None])).sub_(ew)
    if clamped is not None:
        G.masked_fill_(clamped, 0.0)
    gc = ev.coef_grad(G, cf, saved)  # [A, S, Kg]
    gf = torch.bmm(w.transpose(1, 2), gFa)  # [A, S, Cf]
    if want_dist:
        gf[:, :, dch] += g_z
    # every intersection is visited once; duplicates are only the discarded padding row
    st.gcoef.index_copy_(0, idx_flat, gc.reshape(-1, st.gcoef.shape[1]))
    st.gfeat.index_copy_(0, idx_flat, gf.reshape(-1, st.gfeat.shape[1]))


class _Composite(torch.autograd.Function):
    """coef [M, Kc], feat [M, Cf] -> F [NB, P, Cf] (sum w f), T [NB, P] (composited transmittance),
    dist [NB, P] (2DGS depth distortion, zeros for 3DGS)."""

    @staticmethod
    def forward(ctx, coef: Tensor, feat: Tensor, plan: _Plan):
        steps = [] if (ctx.needs_input_grad[0] or ctx.needs_input_grad[1]) and _store_fits(plan) else None
        with _flush_denormal():
            Fb, Tb, Db = _Composite._run(coef, feat, plan, grads=None, steps=steps)
        ctx.plan = plan
        ctx.steps = steps  # per-chunk intermediates (None: the backward recomputes them)
        ctx.save_for_backward(coef, feat, Fb, Tb, Db)
        return Fb, Tb, Db

    @staticmethod
    def backward(ctx, gF: Tensor, gT: Tensor, gD: Tensor):
        coef, feat, Fb, Tb, Db = ctx.saved_tensors
        gF = torch.zeros_like(Fb) if gF is None else gF.contiguous()
        gT = torch.zeros_like(Tb) if gT is None else gT.contiguous()
        gD = torch.zeros_like(Db) if gD is None else gD.contiguous()
        with _flush_denormal():
            gcoef, gfeat = _Composite._run(coef, feat, ctx.plan, grads=(gF, gT, gD, Fb, Tb, Db), steps=ctx.steps)
        return gcoef, gfeat, None

    @staticmethod
    def _run(coef: Tensor, feat: Tensor, plan: _Plan, grads, steps: list | None = None):
        """Forward (grads None; appends each chunk's intermediates to `steps` if given) or backward
        (grads given; replays `steps` if given, else recomputes every chunk front to back)."""
        M = coef.shape[0]
        NB, P = plan.T_init.shape
        dtype, device = coef.dtype, coef.device
        ev = _ChunkEval(plan.mode, plan.phi.to(dtype))
        want_dist = plan.mode == "2dgs"

        T_all = plan.T_init.to(dtype).clone()
        if grads is None:
            Fb = torch.zeros(NB, P, feat.shape[1], dtype=dtype, device=device)
            T_comp = T_all.clone()
            Db = torch.zeros(NB, P, dtype=dtype, device=device)
        else:
            bw = _BackwardState.start(grads, plan.mode, coef.shape[1], feat.shape[1], M)
        A_carry = torch.zeros(NB, P, dtype=dtype, device=device) if want_dist else None

        if grads is not None and steps is not None:
            schedule = steps  # replay the forward's chunks: no recomputation
        else:
            coef_p, feat_p = _padded(coef, feat, plan.mode)
            schedule = _Composite._schedule(plan, coef_p, feat_p, ev, T_all, M, want_dist, A_carry,
                                            backward=grads is not None or steps is not None)
        for step in schedule:
            if grads is None:
                if steps is not None:
                    steps.append(step)
                _composite_chunk(step, Fb, T_comp, Db, want_dist)
            else:
                _backward_chunk(step, ev, bw, plan.depth_channel, want_dist)
        if grads is None:
            return Fb, T_comp.clamp_(min=0.0), Db
        return bw.finish(M, coef.shape[1])

    @staticmethod
    def _schedule(plan: _Plan, coef_p: Tensor, feat_p: Tensor, ev: _ChunkEval, T_all: Tensor, M: int,
                  want_dist: bool, A_carry: Tensor | None, backward: bool):
        """Front-to-back chunks: yields (bins, idx_flat, cf, ft, saved, clamped, T_inc, w,
        2DGS distortion terms); updates T_all [NB, P] (and A_carry) in place."""
        NB, P = T_all.shape
        Kc, Cf = coef_p.shape[1], feat_p.shape[1]
        n_chunks, group = _chunk_schedule(plan, NB, P, T_all.device)
        alive = None  # None: every bin (then bins are slices: views instead of gathers/scatters)
        for c in range(n_chunks):
            # bins with candidates left and at least one pixel not finished
            if alive is None:
                keep = (plan.lengths > c * plan.chunk) & (T_all > T_STOP).any(-1)
                if not bool(keep.all()):
                    alive = torch.nonzero(keep).reshape(-1)
            else:
                keep = (plan.lengths[alive] > c * plan.chunk) & (T_all[alive] > T_STOP).any(-1)
                alive = alive[keep]
            n_alive = NB if alive is None else alive.numel()
            if n_alive == 0:
                break
            for g0 in range(0, n_alive, group):
                bins = slice(g0, g0 + group) if alive is None else alive[g0 : g0 + group]
                idx = _pad_index(plan, bins, c, M)  # [A, S]
                idx_flat = idx.reshape(-1)
                cf = coef_p.index_select(0, idx_flat).reshape(idx.shape + (Kc,))  # index_select: ~5x faster than [idx]
                ft = feat_p.index_select(0, idx_flat).reshape(idx.shape + (Cf,))  # [A, S, Cf]
                saved, clamped, alpha, one_m, T_inc, w = _forward_step(ev, cf, T_all[bins], backward)
                T_all[bins] = T_inc[:, :, -1]
                dist_terms = None
                if want_dist:
                    z = ft[:, None, :, plan.depth_channel]  # [A, 1, S]
                    wz = w * z
                    cwz = torch.cumsum(wz, 2)
                    A_exc = A_carry[bins][:, :, None] + cwz - wz  # sum_{j<k} w_j z_j
                    W_exc = 1.0 - T_inc / one_m  # sum_{j<k} w_j (pixels start at T = 1)
                    A_carry[bins] += cwz[:, :, -1]
                    dist_terms = (z, wz, cwz, A_exc, W_exc)
                yield bins, idx_flat, cf, ft, saved, clamped, T_inc, w, dist_terms


def composite(coef: Tensor, feat: Tensor, plan: _Plan) -> tuple[Tensor, Tensor, Tensor]:
    """Differentiable compositing of depth-sorted tile bins (see `_Composite`)."""
    return _Composite.apply(coef, feat, plan)


# ------------------------------------------------------------------------------------------
# per-intersection coefficients
# ------------------------------------------------------------------------------------------
