"""DCP-v2 style Transformer that makes the two clouds' features co-contextual."""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from vrnet_ext.nn.autocast_weights import AutocastLinear, autocast_parameter
from vrnet_ext.ops import attention

# Pairs per pass through the Transformer on the compiled backend on a CPU. On a 2-core AMD EPYC
# (768-point clouds, float32) slices of 4 pairs took 27 ms per pair at B = 64 against 38 for the
# batch in one pass (its activations, ~150 MB per layer, spill out of the caches), and 29 against 31
# at B = 16; slices of 2 or 8 were within a few per cent of 4.
PAIRS_PER_PASS = 4


class MultiHeadAttention(nn.Module):
    """Batch-first multi-head attention on :func:`vrnet_ext.ops.attention`.

    The same function and parameters (names, shapes, initialisation) as
    ``nn.MultiheadAttention(dims, heads, batch_first=True)``, so checkpoints load in either, but
    without that module's sequence-first transposes: the packed projections are viewed per head
    and handed to the fused attention kernel as strided tensors.
    """

    def __init__(self, dims: int, heads: int, dropout: float) -> None:
        super().__init__()
        if dims % heads:
            raise ValueError(f"dims ({dims}) must be divisible by heads ({heads})")
        self.heads = heads
        self.dropout = dropout
        self.in_proj_weight = nn.Parameter(torch.empty(3 * dims, dims))
        self.in_proj_bias = nn.Parameter(torch.zeros(3 * dims))
        self.out_proj = AutocastLinear(dims, dims)
        nn.init.xavier_uniform_(self.in_proj_weight)
        nn.init.zeros_(self.out_proj.bias)

    def _heads(self, projected: torch.Tensor, parts: int) -> tuple[torch.Tensor, ...]:
        """(B, L, parts * dims) -> ``parts`` views (B, heads, L, dims / heads)."""
        batch, length, width = projected.shape
        return projected.view(batch, length, parts, self.heads, width // (parts * self.heads)).permute(2, 0, 3, 1, 4)

    def forward(self, queries: torch.Tensor, memory: torch.Tensor | None = None, backend: str = "ext") -> torch.Tensor:
        """queries (B, N, dims), memory (B, M, dims) or None (self-attention) -> (B, N, dims)."""
        weight, bias = autocast_parameter(self, "in_proj_weight"), autocast_parameter(self, "in_proj_bias")
        if memory is None:
            q, k, v = self._heads(F.linear(queries, weight, bias), 3)
        else:
            dims = queries.shape[-1]
            (q,) = self._heads(F.linear(queries, weight[:dims], bias[:dims]), 1)
            k, v = self._heads(F.linear(memory, weight[dims:], bias[dims:]), 2)
        attended = attention(q, k, v, dropout_p=self.dropout if self.training else 0.0, backend=backend)
        return self.out_proj(attended.transpose(1, 2).flatten(2))


class _AttentionBlock(nn.Module):
    """Pre-norm residual multi-head attention."""

    def __init__(self, dims: int, heads: int, dropout: float) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(dims)
        self.attention = MultiHeadAttention(dims, heads, dropout)

    def forward(self, x: torch.Tensor, memory: torch.Tensor | None = None, backend: str = "ext") -> torch.Tensor:
        return x + self.attention(self.norm(x), memory, backend)


class _FeedForward(nn.Module):
    def __init__(self, dims: int, ff_dims: int, dropout: float) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.LayerNorm(dims), AutocastLinear(dims, ff_dims), nn.ReLU(),
                                 nn.Dropout(dropout), AutocastLinear(ff_dims, dims))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.net(x)


class _EncoderLayer(nn.Module):
    def __init__(self, dims: int, heads: int, ff_dims: int, dropout: float) -> None:
        super().__init__()
        self.self_attention = _AttentionBlock(dims, heads, dropout)
        self.feed_forward = _FeedForward(dims, ff_dims, dropout)

    def forward(self, x: torch.Tensor, backend: str = "ext") -> torch.Tensor:
        return self.feed_forward(self.self_attention(x, backend=backend))


class _DecoderLayer(nn.Module):
    def __init__(self, dims: int, heads: int, ff_dims: int, dropout: float) -> None:
        super().__init__()
        self.self_attention = _AttentionBlock(dims, heads, dropout)
        self.cross_attention = _AttentionBlock(dims, heads, dropout)
        self.feed_forward = _FeedForward(dims, ff_dims, dropout)

    def forward(self, x: torch.Tensor, memory: torch.Tensor, backend: str = "ext") -> torch.Tensor:
        return self.feed_forward(self.cross_attention(self.self_attention(x, backend=backend), memory, backend))


class Transformer(nn.Module):
    """eta(A, B) = Decoder(A, Encoder(B)), shared by both directions:
    Phi_X = F_X + eta(F_X, F_Y), Phi_Y = F_Y + eta(F_Y, F_X)."""

    def __init__(self, dims: int, heads: int, ff_dims: int, encoder_layers: int, decoder_layers: int,
                 dropout: float) -> None:
        super().__init__()
        self.encoder = nn.ModuleList(_EncoderLayer(dims, heads, ff_dims, dropout) for _ in range(encoder_layers))
        self.encoder_norm = nn.LayerNorm(dims)
        self.decoder = nn.ModuleList(_DecoderLayer(dims, heads, ff_dims, dropout) for _ in range(decoder_layers))
        self.decoder_norm = nn.LayerNorm(dims)

    def _eta(self, queries: torch.Tensor, context: torch.Tensor, backend: str) -> torch.Tensor:
        memory = context
        for layer in self.encoder:
            memory = layer(memory, backend)
        memory = self.encoder_norm(memory)
        x = queries
        for layer in self.decoder:
            x = layer(x, memory, backend)
        return self.decoder_norm(x)

    def forward(self, src_features: torch.Tensor, tgt_features: torch.Tensor, backend: str = "ext"):
        """(B, c, N), (B, c, M) -> Phi_X (B, c, N), Phi_Y (B, c, M). ``backend`` is the attention's
        (:func:`vrnet_ext.ops.attention`).

        With N == M both directions run as one batch of 2B (larger matrix products, half the
        kernel calls). With ``backend="ext"`` on a CPU a batch of more than ``PAIRS_PER_PASS`` pairs
        goes through in slices of that many pairs, whose activations stay in the CPU's caches (a
        GPU keeps the whole batch); the function is the same either way.
        """
        if (backend == "torch" or src_features.device.type != "cpu"
                or src_features.shape[0] <= PAIRS_PER_PASS):
            return self._both_directions(src_features, tgt_features, backend)
        slices = [self._both_directions(src_features[start:start + PAIRS_PER_PASS],
                                        tgt_features[start:start + PAIRS_PER_PASS], backend)
                  for start in range(0, src_features.shape[0], PAIRS_PER_PASS)]
        return torch.cat([phi_x for phi_x, _ in slices]), torch.cat([phi_y for _, phi_y in slices])

    def _both_directions(self, src_features: torch.Tensor, tgt_features: torch.Tensor,
                         backend: str) -> tuple[torch.Tensor, torch.Tensor]:
        fx, fy = src_features.transpose(1, 2), tgt_features.transpose(1, 2)
        if fx.shape == fy.shape:
            both = torch.cat([fx, fy])
            phi_x, phi_y = (both + self._eta(both, torch.cat([fy, fx]), backend)).chunk(2)
        else:
            phi_x = fx + self._eta(fx, fy, backend)
            phi_y = fy + self._eta(fy, fx, backend)
        return phi_x.transpose(1, 2), phi_y.transpose(1, 2)
