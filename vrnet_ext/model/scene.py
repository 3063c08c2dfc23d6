"""VRNet's head on rotation-invariant descriptors: the learned path for real scans.

The ModelNet40 network sees raw coordinates, so it is neither rotation invariant nor at home on a
room-sized scan. :class:`SceneVRNet` keeps VRNet's head and swaps its features:

1. features: FPFH descriptors (33-d, rotation invariant; :mod:`vrnet_ext.registration.ransac`) ->
   a per-point MLP -> one EdgeConv-style round of context over the 3-D kNN graph (the graph and the
   features are invariant, so the embedding is too) -> unit vectors Φ (B, N, c);
2. soft matching M = softmax(t Φx Φyᵀ) with a learned temperature t, streamed by ``ops.soft_match``
   (no N x M matrix): VCPs = M Y, matched features M Φy, each row's peak and entropy;
3. the correction walk, made rotation equivariant: from [Φx, M Φy, peak, entropy] it predicts per
   point a sharpening τ_i in [e^-3, e^3] (1 at the start) and a confidence. The RCP is the VCP of the sharpened row,
   softmax(τ_i t φ_i Φyᵀ) Y: it moves each VCP from the soft average towards the row's best
   matches (a learned offset vector would not turn with the scan);
4. the estimate: RANSAC over the most confident (source, RCP) pairs, or a weighted Procrustes.

Coordinates are in voxel units (points / voxel edge), so one model serves a 5 cm kitchen and a
30 cm LiDAR scan.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import nn
from torch.nn import functional as F

from vrnet_ext import ops
from vrnet_ext.ops.soft_match import soft_match


SCENE_FORMAT = "vrnet_ext.scene/1"  # the "format" key of scene-model files (runs and shipped weights)
# Inclusive bounds on what a file may ask for (sizes are read from untrusted checkpoints).
SCENE_LIMITS = {"descriptor_dims": (33, 33), "hidden": (1, 1024), "emb_dims": (1, 1024), "neighbours": (0, 64),
                "walk_hidden": (1, 1024)}
# How a model reads ``ops.fpfh``'s descriptors: "open3d" as they are; "mirrored-100" with the theta
# and alpha bins in reverse order and every block halved to sum 100 (the layout some weights were
# trained on).
FPFH_LAYOUTS = ("open3d", "mirrored-100")


@dataclass
class SceneConfig:
    """Sizes of :class:`SceneVRNet` (every field is checked against limits when read from a file)."""

    descriptor_dims: int = 33   # FPFH
    hidden: int = 64
    emb_dims: int = 32
    neighbours: int = 16        # context graph on the 3-D points
    walk_hidden: int = 64
    fpfh_layout: str = "open3d"  # one of FPFH_LAYOUTS

    def to_dict(self) -> dict:
        return asdict(self)

    def values_per_point(self) -> int:
        """Floats the forward pass holds per point at its peak, about: the context graph's edge
        tensors (neighbours x hidden, several of them) dominate."""
        return 5 * self.neighbours * self.hidden + 4 * self.hidden + 2 * self.emb_dims + 2 * self.walk_hidden

    @classmethod
    def from_dict(cls, values: dict) -> "SceneConfig":
        """A config from untrusted ``values``: ValueError naming the field outside SCENE_LIMITS."""
        unknown = set(values) - set(SCENE_LIMITS) - {"fpfh_layout"}
        if unknown:
            raise ValueError(f"unknown scene-model fields {sorted(unknown)}")
        if values.get("fpfh_layout", "open3d") not in FPFH_LAYOUTS:
            raise ValueError(f"scene model fpfh_layout = {values['fpfh_layout']!r} is not one of {FPFH_LAYOUTS}")
        for name, value in values.items():
            if name == "fpfh_layout":
                continue
            low, high = SCENE_LIMITS[name]
            if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
                raise ValueError(f"scene model {name} = {value!r} is outside [{low}, {high}]")
        return cls(**values)


@dataclass
class SceneOutput:
    """One forward pass for N source and M target points (coordinates in the input's unit)."""

    vcp: torch.Tensor                # (B, N, 3) M Y
    rcp: torch.Tensor                # (B, N, 3) the sharpened rows' VCPs
    confidence_logits: torch.Tensor  # (B, N) logit of "this RCP lies at the source point's true position"
    src_embedding: torch.Tensor      # (B, N, c) unit vectors
    tgt_embedding: torch.Tensor      # (B, M, c)
    temperature: torch.Tensor        # () t: scores are t φ_i . ψ_j


def _mlp(widths: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(widths) - 1):
        layers.append(nn.Linear(widths[i], widths[i + 1]))
        if i < len(widths) - 2:
            layers += [nn.LayerNorm(widths[i + 1]), nn.ReLU()]
    return nn.Sequential(*layers)


class SceneVRNet(nn.Module):
    """The scene model: a per-point MLP over FPFH descriptors and an edge MLP over each point's
    neighbours give unit embeddings; soft matching at a learned temperature gives VCPs; a small walk
    reads each point's match (its embedding, the matched embedding, the peak weight and the
    entropy) and returns a sharpening of that point's matching, which gives its RCP, and a
    confidence logit. Points are in voxel units (see :meth:`embed`)."""

    def __init__(self, config: SceneConfig | None = None) -> None:
        super().__init__()
        self.config = config or SceneConfig()
        cfg = self.config
        self.point_mlp = _mlp([cfg.descriptor_dims, cfg.hidden, cfg.hidden])
        self.edge_mlp = _mlp([2 * cfg.hidden, cfg.hidden, cfg.hidden])
        self.projection = _mlp([2 * cfg.hidden, cfg.hidden, cfg.emb_dims])
        self.log_temperature = nn.Parameter(torch.tensor(math.log(10.0)))
        self.walk = _mlp([2 * cfg.emb_dims + 2, cfg.walk_hidden, cfg.walk_hidden, 2])
        nn.init.zeros_(self.walk[-1].weight)
        nn.init.zeros_(self.walk[-1].bias)

    def embed(self, points: torch.Tensor, descriptors: torch.Tensor, backend: str = "ext") -> torch.Tensor:
        """points (B, N, 3) in voxel units, descriptors (B, N, 33) FPFH -> unit embeddings (B, N, c)."""
        if self.config.fpfh_layout == "mirrored-100":
            blocks = descriptors.unflatten(-1, (3, 11))
            descriptors = torch.cat([blocks[..., :2, :].flip(-1), blocks[..., 2:, :]], -2).flatten(-2) / 2
        h = self.point_mlp(torch.log1p(descriptors))
        k = min(self.config.neighbours, points.shape[1] - 1)
        if k >= 1:
            _, knn_idx = ops.knn(points, points, k, exclude_self=True, backend=backend)
            batch = torch.arange(h.shape[0], device=h.device)[:, None, None]
            neighbours = h[batch, knn_idx]  # (B, N, k, hidden)
            edges = self.edge_mlp(torch.cat([neighbours - h.unsqueeze(2), h.unsqueeze(2).expand_as(neighbours)], -1))
            context = edges.amax(dim=2)
        else:
            context = torch.zeros_like(h)
        return F.normalize(self.projection(torch.cat([h, context], -1)), dim=-1)

    def forward(self, src: torch.Tensor, src_descriptors: torch.Tensor, tgt: torch.Tensor,
                tgt_descriptors: torch.Tensor, backend: str = "ext") -> SceneOutput:
        """src (B, N, 3), tgt (B, M, 3) in voxel units with their FPFH (B, N | M, 33) -> SceneOutput."""
        phi_x = self.embed(src, src_descriptors, backend)
        phi_y = self.embed(tgt, tgt_descriptors, backend)
        temperature = self.log_temperature.exp()
        query = phi_x * temperature
        first = soft_match(query, phi_y, torch.cat([tgt, phi_y], -1), 1.0, backend=backend, return_stats=True)
        vcp, matched = first.out[..., :3], first.out[..., 3:]
        peak_key = phi_y.gather(1, first.argmax.unsqueeze(-1).expand_as(phi_x))
        peak = torch.exp((query * peak_key).sum(-1) - first.lse)
        entropy = first.lse - (query * matched).sum(-1)
        walk = self.walk(torch.cat([phi_x, matched, peak.unsqueeze(-1), entropy.unsqueeze(-1)], -1))
        sharpening = walk[..., 0].clamp(-3.0, 3.0).exp()  # 1 at initialisation
        rcp = soft_match(query * sharpening.unsqueeze(-1), phi_y, tgt, 1.0, backend=backend)
        return SceneOutput(vcp, rcp, walk[..., 1], phi_x, phi_y, temperature)

    def scores(self, out: SceneOutput) -> torch.Tensor:
        """(B, N, M) matching logits t φ_i . ψ_j of a pass (training: the InfoNCE term)."""
        return out.temperature * out.src_embedding @ out.tgt_embedding.mT
