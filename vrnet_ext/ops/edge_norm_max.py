"""EdgeConv's tail after its one projection: BatchNorm over the edges, LeakyReLU, max over neighbours.

``projections`` (B, 2O, N) holds ``a = W1 x`` in its first O channels and ``b = (W2 - W1) x`` in
its last O, so edge (n, j) of the graph ``idx`` (B, N, k) has the value ``z = a[idx[n, j]] + b[n]``
(DGCNN's ``W [x_j - x_i; x_i]``). The op returns

    out[b, o, n] = leaky_relu(max_j (weight_o * (z - mean_o) / sqrt(var_o + eps) + bias_o))

with the statistics of the (B, N, k) edges of each channel (batch statistics, biased variance), or
``running_mean`` / ``running_var`` when given, without the (B, O, N, k) edge tensor: per channel
the normalisation and the LeakyReLU are monotone, so the max over j is taken of ``a`` where
``weight_o >= 0`` and the min where it is negative; the batch statistics follow from per-point sums.

Two implementations: the compiled kernels (on the CPU two or three parallel regions per call with
tasks the threads claim, so it keeps its speed beside a busy process; on CUDA three launches
forward and three backward, per-tile sums in double combined in tile order; both read
``projections`` fastest point-major, i.e. stored as (B, N, 2O), and return point-major outputs),
and the materialising reference.
"""
from __future__ import annotations

import torch
from torch.nn import functional as F

from vrnet_ext._extension import has_extension, use_extension
from vrnet_ext.ops._checks import check_float, first_order_only, float32_region, promote_low_precision
from vrnet_ext.ops.edge_features import gather_neighbours, validate_graph

EdgeNormMaxResult = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def _validate(projections: torch.Tensor, idx: torch.Tensor, channel_tensors: dict[str, torch.Tensor | None],
              eps: float, negative_slope: float) -> None:
    validate_graph(projections, idx, "projections")
    if projections.shape[1] % 2 or projections.shape[1] == 0:
        raise ValueError("projections must have shape (B, 2O, N) (neighbour terms, then centre terms), "
                         f"got {tuple(projections.shape)}")
    if idx.shape[1] != projections.shape[2]:
        raise ValueError(f"idx must have shape (B, N, k) with N = {projections.shape[2]}, got {tuple(idx.shape)}")
    if (channel_tensors["running_mean"] is None) != (channel_tensors["running_var"] is None):
        raise ValueError("running_mean and running_var must be given together")
    if not (eps > 0 and eps < float("inf")):
        raise ValueError(f"eps must be a finite number > 0, got {eps}")
    if not (0 <= negative_slope < float("inf")):
        raise ValueError(f"negative_slope must be a finite number >= 0 (the max is taken before the activation), "
                         f"got {negative_slope}")
    for name, t in channel_tensors.items():
        if t is not None:
            check_float(t, name)
            if t.shape != (projections.shape[1] // 2,):
                raise ValueError(f"{name} must have shape ({projections.shape[1] // 2},), got {tuple(t.shape)}")
            if t.device != projections.device:
                raise ValueError(f"{name} is on {t.device} but projections is on {projections.device}")
    if channel_tensors["running_mean"] is None and idx.numel() <= 1:
        raise ValueError(f"batch statistics need more than one edge per channel, got idx of shape {tuple(idx.shape)}")


def _normalise(z: torch.Tensor, mean: torch.Tensor, var: torch.Tensor, weight: torch.Tensor | None,
               bias: torch.Tensor | None, eps: float) -> torch.Tensor:
    """z (B, O, ...) -> weight * (z - mean) / sqrt(var + eps) + bias, per channel."""
    shape = (1, -1) + (1,) * (z.dim() - 2)
    scale = torch.rsqrt(var + eps)
    if weight is not None:
        scale = scale * weight
    out = (z - mean.view(shape)) * scale.view(shape)
    return out + bias.view(shape) if bias is not None else out


def edge_norm_max_reference(projections: torch.Tensor, idx: torch.Tensor, weight: torch.Tensor | None = None,
                            bias: torch.Tensor | None = None, running_mean: torch.Tensor | None = None,
                            running_var: torch.Tensor | None = None, eps: float = 1e-5,
                            negative_slope: float = 0.2) -> EdgeNormMaxResult:
    """Pure PyTorch on the materialised (B, O, N, k) edge tensor."""
    channels = projections.shape[1] // 2
    z = gather_neighbours(projections[:, :channels], idx) + projections[:, channels:].unsqueeze(-1)
    if running_mean is None:
        var, mean = torch.var_mean(z, dim=(0, 2, 3), correction=0)
    else:
        mean, var = running_mean, running_var
    out = F.leaky_relu(_normalise(z, mean, var, weight, bias, eps), negative_slope)
    return out.max(dim=-1).values, mean.detach(), var.detach()


def edge_norm_max(projections: torch.Tensor, idx: torch.Tensor, weight: torch.Tensor | None = None,
                  bias: torch.Tensor | None = None, running_mean: torch.Tensor | None = None,
                  running_var: torch.Tensor | None = None, eps: float = 1e-5, negative_slope: float = 0.2,
                  backend: str = "ext") -> EdgeNormMaxResult:
    """BatchNorm over the edges of a kNN graph, LeakyReLU, max over each point's neighbours.

    Args:
        projections: (B, 2O, N): ``W1 x`` in channels [0, O), ``(W2 - W1) x`` in [O, 2O)
            (bfloat16/float16 are promoted to float32).
        idx: (B, N, k) int64 neighbour indices into the N points.
        weight, bias: (O,) BatchNorm affine parameters, or None (1 and 0).
        running_mean, running_var: (O,) statistics to normalise with, or None for the batch
            statistics of the B * N * k edges (then more than one edge is needed).
        eps: added to the variance; negative_slope: of the LeakyReLU.
        backend: ``"ext"`` or ``"torch"``.

    Returns:
        out (B, O, N) and the per-channel mean and biased variance (O,) it normalised with (for a
        running-statistics update; not differentiable). ``weight`` and ``bias`` (and projections) get
        gradients; the max routes them to the first neighbour holding it.
    """
    projections = promote_low_precision(projections)
    channel_tensors = {"weight": weight, "bias": bias, "running_mean": running_mean, "running_var": running_var}
    _validate(projections, idx, channel_tensors, eps, negative_slope)
    weight, bias, running_mean, running_var = (
        None if t is None else t.to(projections.dtype) for t in channel_tensors.values())
    args = (projections, idx, weight, bias, running_mean, running_var, float(eps), float(negative_slope))
    if use_extension(backend, projections.device):
        out, mean, var, _ = torch.ops.vrnet_ext.edge_norm_max(*args)  # float64 statistics (for the backward)
        return out, mean.to(projections.dtype), var.to(projections.dtype)
    with float32_region(projections):
        return edge_norm_max_reference(*args)


if has_extension():

    @torch.library.register_fake("vrnet_ext::edge_norm_max")
    def _edge_norm_max_fake(projections, idx, weight, bias, running_mean, running_var, eps, negative_slope):
        B, O, N = projections.shape[0], projections.shape[1] // 2, projections.shape[2]
        # point-major like the kernel's: (B, N, O) storage seen as (B, O, N)
        return (projections.new_empty((B, N, O)).mT, projections.new_empty((O,), dtype=torch.float64),
                projections.new_empty((O,), dtype=torch.float64), projections.new_empty((B, N, O), dtype=torch.int32).mT)

    @torch.library.register_fake("vrnet_ext::edge_norm_max_backward")
    def _edge_norm_max_backward_fake(grad_out, projections, idx, arg, weight, bias, mean, var, batch_stats, eps,
                                     negative_slope):
        channels = projections.shape[1] // 2
        return (projections.new_empty((projections.shape[0], projections.shape[2], 2 * channels)).mT,
                projections.new_empty((channels,)), projections.new_empty((channels,)))

    def _edge_norm_max_setup_context(ctx, inputs, output):
        projections, idx, weight, bias, running_mean, _, eps, negative_slope = inputs
        _, mean, var, arg = output
        ctx.mark_non_differentiable(mean, var, arg)
        ctx.save_for_backward(projections, idx, arg, weight, bias, mean, var)
        ctx.batch_stats = running_mean is None
        ctx.eps, ctx.negative_slope = eps, negative_slope

    def _edge_norm_max_backward(ctx, grad_out, _grad_mean, _grad_var, _grad_arg):
        projections, idx, arg, weight, bias, mean, var = ctx.saved_tensors
        first_order_only("edge_norm_max", grad_out, projections, weight, bias)
        grad_projections, grad_weight, grad_bias = torch.ops.vrnet_ext.edge_norm_max_backward(
            grad_out, projections, idx, arg, weight, bias, mean, var, ctx.batch_stats, ctx.eps, ctx.negative_slope)
        return (grad_projections, None, grad_weight if weight is not None else None,
                grad_bias if bias is not None else None, None, None, None, None)

    torch.library.register_autograd(
        "vrnet_ext::edge_norm_max", _edge_norm_max_backward, setup_context=_edge_norm_max_setup_context
    )
