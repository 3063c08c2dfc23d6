"""DCP-v2 style Transformer that makes the two clouds' features co-contextual."""
from __future__ import annotations

import torch
from torch import nn


class _AttentionBlock(nn.Module):
    """Pre-norm residual multi-head attention."""

    def __init__(self, dims: int, heads: int, dropout: float) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(dims)
        self.attention = nn.MultiheadAttention(dims, heads, dropout=dropout, batch_first=True)

    def forward(self, x: torch.Tensor, memory: torch.Tensor | None = None) -> torch.Tensor:
        q = self.norm(x)
        kv = q if memory is None else memory
        return x + self.attention(q, kv, kv, need_weights=False)[0]


class _FeedForward(nn.Module):
    def __init__(self, dims: int, ff_dims: int, dropout: float) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.LayerNorm(dims), nn.Linear(dims, ff_dims), nn.ReLU(),
                                 nn.Dropout(dropout), nn.Linear(ff_dims, dims))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.net(x)


class _EncoderLayer(nn.Module):
    def __init__(self, dims: int, heads: int, ff_dims: int, dropout: float) -> None:
        super().__init__()
        self.self_attention = _AttentionBlock(dims, heads, dropout)
        self.feed_forward = _FeedForward(dims, ff_dims, dropout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.feed_forward(self.self_attention(x))


class _DecoderLayer(nn.Module):
    def __init__(self, dims: int, heads: int, ff_dims: int, dropout: float) -> None:
        super().__init__()
        self.self_attention = _AttentionBlock(dims, heads, dropout)
        self.cross_attention = _AttentionBlock(dims, heads, dropout)
        self.feed_forward = _FeedForward(dims, ff_dims, dropout)

    def forward(self, x: torch.Tensor, memory: torch.Tensor) -> torch.Tensor:
        return self.feed_forward(self.cross_attention(self.self_attention(x), memory))


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

    def _eta(self, queries: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        memory = context
        for layer in self.encoder:
            memory = layer(memory)
        memory = self.encoder_norm(memory)
        x = queries
        for layer in self.decoder:
            x = layer(x, memory)
        return self.decoder_norm(x)

    def forward(self, src_features: torch.Tensor, tgt_features: torch.Tensor):
        """(B, c, N), (B, c, M) -> Phi_X (B, c, N), Phi_Y (B, c, M)."""
        fx, fy = src_features.transpose(1, 2), tgt_features.transpose(1, 2)
        phi_x = fx + self._eta(fx, fy)
        phi_y = fy + self._eta(fy, fx)
        return phi_x.transpose(1, 2), phi_y.transpose(1, 2)
