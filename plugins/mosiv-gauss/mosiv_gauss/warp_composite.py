"""Front-to-back compositing of screen Gaussians in Warp kernels, one thread per pixel.

The fast path of ``rasterizer.rasterize`` (option ``backend="warp"``): projection and tile
binning stay in torch (``project_isotropic``, ``bin_to_tiles``), and this module replaces the
torch slices of ``_composite_slice`` with two kernels that walk each pixel's tile list:

    forward:  w_g = alpha_g T_g,  T_{g+1} = T_g (1 - alpha_g),  out_f = sum_g w_g c_gf
    backward: dL/dalpha_g = T_g sum_f dL/dout_f c_gf - S_g / (1 - alpha_g) with
              S_g = sum_f dL/dout_f sum_{h behind g} w_h c_hf (3D Gaussian splatting's backward),
              walking the list front to back as the forward does: T_g is recomputed the same
              way and S_g = sum_f dL/dout_f out_f - (the same sum over g and those in front).

Why front to back: 3D Gaussian splatting walks the list back to front, recovering
T_g = T_{g+1} / (1 - alpha_g) from the final transmittance. Behind a few thousand overlapping
Gaussians the forward's T sticks at float32's smallest subnormal (rounding no longer lowers it),
and dividing it back up through the same Gaussians overflows to inf, giving NaN gradients
(dense liquids after densification did this). Recomputing T forwards never divides.

with alpha_g = min(o_g exp(-q/2), max_alpha) inside the cut-off q <= cutoff^2, exactly the
torch model, so the torch path is the reference it is tested against. Gradients reach the
Gaussians' screen centres, inverse variances, opacities and features by atomic adds; torch's
autograd carries them on through the projection. Runs on CPU and CUDA (on torch's stream).
"""

from __future__ import annotations

import torch
import warp as wp

_READY = False


def _init() -> None:
    global _READY
    if not _READY:
        wp.config.quiet = True
        wp.init()
        _READY = True


@wp.func
def pixel_centre(pid: int, width: int) -> wp.vec2:
    """Centre (u, v) of the thread's pixel, row-major (pixel centres at integer + 0.5)."""
    return wp.vec2(float(pid % width) + 0.5, float(pid // width) + 0.5)


@wp.func
def tile_of(pid: int, width: int, tile: int, tiles_x: int) -> int:
    """Index of the tile holding the thread's pixel (as in ``bin_to_tiles``)."""
    return ((pid // width) // tile) * tiles_x + (pid % width) // tile


@wp.kernel
def composite_forward(
    tile_start: wp.array(dtype=wp.int32),
    tile_count: wp.array(dtype=wp.int32),
    pair_gaussian: wp.array(dtype=wp.int32),
    uv: wp.array2d(dtype=float),
    inv_var: wp.array2d(dtype=float),
    opacity: wp.array(dtype=float),
    features: wp.array2d(dtype=float),
    width: int,
    tile: int,
    tiles_x: int,
    cutoff2: float,
    max_alpha: float,
    out: wp.array2d(dtype=float),
):
    pid = wp.tid()
    t = tile_of(pid, width, tile, tiles_x)
    p = pixel_centre(pid, width)
    trans = float(1.0)  # noqa: UP018 (Warp: a variable the loop changes)
    n_feat = features.shape[1]
    for j in range(tile_start[t], tile_start[t] + tile_count[t]):
        g = pair_gaussian[j]
        du = p[0] - uv[g, 0]
        dv = p[1] - uv[g, 1]
        q = du * du * inv_var[g, 0] + dv * dv * inv_var[g, 1]  # squared Mahalanobis distance
        if q <= cutoff2:
            alpha = wp.min(opacity[g] * wp.exp(-0.5 * q), max_alpha)
            w = alpha * trans  # eq. 3 of 3D Gaussian splatting
            for f in range(n_feat):
                out[pid, f] = out[pid, f] + w * features[g, f]
            trans = trans * (1.0 - alpha)


@wp.kernel
def composite_backward(
    tile_start: wp.array(dtype=wp.int32),
    tile_count: wp.array(dtype=wp.int32),
    pair_gaussian: wp.array(dtype=wp.int32),
    uv: wp.array2d(dtype=float),
    inv_var: wp.array2d(dtype=float),
    opacity: wp.array(dtype=float),
    features: wp.array2d(dtype=float),
    width: int,
    tile: int,
    tiles_x: int,
    cutoff2: float,
    max_alpha: float,
    out: wp.array2d(dtype=float),
    grad_out: wp.array2d(dtype=float),
    grad_uv: wp.array2d(dtype=float),
    grad_inv_var: wp.array2d(dtype=float),
    grad_opacity: wp.array(dtype=float),
    grad_features: wp.array2d(dtype=float),
):
    pid = wp.tid()
    t = tile_of(pid, width, tile, tiles_x)
    p = pixel_centre(pid, width)
    n_feat = features.shape[1]
    # sum_f dL/dout_f out_f: every Gaussian's share, w_h sum_f dL/dout_f c_hf, summed
    total = float(0.0)  # noqa: UP018 (Warp: a variable the loop changes)
    for f in range(n_feat):
        total = total + grad_out[pid, f] * out[pid, f]
    trans = float(1.0)  # noqa: UP018 (transmittance in front of the current Gaussian)
    upto = float(0.0)  # noqa: UP018 (the shares of the current Gaussian and those in front)
    for j in range(tile_start[t], tile_start[t] + tile_count[t]):
        g = pair_gaussian[j]
        du = p[0] - uv[g, 0]
        dv = p[1] - uv[g, 1]
        q = du * du * inv_var[g, 0] + dv * dv * inv_var[g, 1]
        if q <= cutoff2:
            raw = opacity[g] * wp.exp(-0.5 * q)
            alpha = wp.min(raw, max_alpha)
            w = alpha * trans
            dot = float(0.0)  # noqa: UP018 (Warp: a variable the loop changes)
            for f in range(n_feat):
                go = grad_out[pid, f]
                wp.atomic_add(grad_features, g, f, w * go)
                dot = dot + go * features[g, f]
            upto = upto + w * dot
            behind = total - upto  # S_g: the shares of the Gaussians behind g
            d_alpha = trans * dot - behind / (1.0 - alpha)
            trans = trans * (1.0 - alpha)
            if raw < max_alpha:  # the clamp passes no gradient
                wp.atomic_add(grad_opacity, g, d_alpha * wp.exp(-0.5 * q))
                d_q = d_alpha * raw * -0.5
                wp.atomic_add(grad_uv, g, 0, d_q * -2.0 * du * inv_var[g, 0])
                wp.atomic_add(grad_uv, g, 1, d_q * -2.0 * dv * inv_var[g, 1])
                wp.atomic_add(grad_inv_var, g, 0, d_q * du * du)
                wp.atomic_add(grad_inv_var, g, 1, d_q * dv * dv)


def _warp(tensor: torch.Tensor, dtype) -> wp.array:
    return wp.from_torch(tensor.contiguous(), dtype=dtype)


class _Stream:
    """Launch on torch's current CUDA stream, so no extra synchronisation is needed."""

    def __init__(self, device: torch.device):
        self.scope = None
        if device.type == "cuda":
            self.scope = wp.ScopedStream(wp.stream_from_torch(torch.cuda.current_stream(device)))

    def __enter__(self):
        if self.scope is not None:
            self.scope.__enter__()

    def __exit__(self, *exc):
        if self.scope is not None:
            self.scope.__exit__(*exc)


class WarpComposite(torch.autograd.Function):
    """(uv [N, 2], inv_var [N, 2], opacity [N], features [N, F]) -> composited [H*W, F]."""

    @staticmethod
    def forward(ctx, uv, inv_var, opacity, features, bins, layout):
        _init()
        width, height, tile, tiles_x, cutoff2, max_alpha = layout
        device = uv.device
        dev = wp.device_from_torch(device)
        f32 = [x.detach().float() for x in (uv, inv_var, opacity, features)]
        lists = [x.to(torch.int32) for x in (bins.start, bins.count, bins.gaussian)]
        out = torch.zeros(width * height, features.shape[1], dtype=torch.float32, device=device)
        scalars = [width, tile, tiles_x, float(cutoff2), float(max_alpha)]
        with _Stream(device):
            wp.launch(
                composite_forward,
                dim=width * height,
                inputs=[_warp(lists[0], wp.int32), _warp(lists[1], wp.int32)]
                + [_warp(lists[2], wp.int32), _warp(f32[0], wp.float32), _warp(f32[1], wp.float32)]
                + [_warp(f32[2], wp.float32), _warp(f32[3], wp.float32), *scalars],
                outputs=[_warp(out, wp.float32)],
                device=dev,
            )
        ctx.save_for_backward(*f32, *lists, out)
        ctx.layout, ctx.dtype = layout, uv.dtype
        return out.to(uv.dtype)

    @staticmethod
    def backward(ctx, grad_out):
        uv, inv_var, opacity, features, start, count, gaussian, out = ctx.saved_tensors
        width, height, tile, tiles_x, cutoff2, max_alpha = ctx.layout
        device = uv.device
        grads = [torch.zeros_like(x) for x in (uv, inv_var, opacity, features)]
        scalars = [width, tile, tiles_x, float(cutoff2), float(max_alpha)]
        with _Stream(device):
            wp.launch(
                composite_backward,
                dim=width * height,
                inputs=[_warp(start, wp.int32), _warp(count, wp.int32), _warp(gaussian, wp.int32)]
                + [_warp(uv, wp.float32), _warp(inv_var, wp.float32), _warp(opacity, wp.float32)]
                + [_warp(features, wp.float32), *scalars, _warp(out, wp.float32)]
                + [_warp(grad_out.float(), wp.float32)],
                outputs=[_warp(g, wp.float32) for g in grads],
                device=wp.device_from_torch(device),
            )
        g_uv, g_iv, g_op, g_feat = (g.to(ctx.dtype) for g in grads)
        return g_uv, g_iv, g_op, g_feat, None, None


def composite(
    screen, bins, *, width: int, height: int, tile: int, tiles_x: int, cutoff2, max_alpha
):
    """Composited features [height, width, F] of ``screen`` Gaussians binned into ``bins``."""
    layout = (width, height, tile, tiles_x, cutoff2, max_alpha)
    flat = WarpComposite.apply(
        screen.uv, screen.inv_var, screen.opacity, screen.features, bins, layout
    )
    return flat.reshape(height, width, -1)
