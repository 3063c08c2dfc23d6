"""VRNet: soft matching -> virtual corresponding points -> correction walk -> weighted Procrustes."""
from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass, fields, replace

import torch
from torch import nn

from vrnet_ext.geometry.alignment import TurnPrior, multistart_icp, nearest_median, robust_icp
from vrnet_ext.geometry.metrics import correct_match_ratio
from vrnet_ext.geometry.transforms import compose, move, search_starts, spread_rotations
from vrnet_ext.model.config import VRNetConfig
from vrnet_ext.model.correction_walk import CorrectionWalk
from vrnet_ext.model.dgcnn import DGCNN
from vrnet_ext.model.transformer import Transformer
from vrnet_ext.ops import robust_kabsch, soft_match
from vrnet_ext.ops._checks import check_all_finite, check_float, check_same, check_shape, trusted_values
from vrnet_ext.runtime import cpu_has_native_bf16

SEARCH_POINTS = 2 ** 16  # source points the rotation search registers per batch (bounds its memory)
# The ICP search's estimate replaces a pair's only where its nearest-point median is below this share of
# the estimate's: on noisy partial views a flip of a round shape can lie a few per cent nearer than the truth.
ICP_SEARCH_NEARER = 0.85


@dataclass
class VRNetOutput:
    """Everything a forward pass produces (shapes for src (B, N, 3), tgt (B, M, 3))."""

    rotation: torch.Tensor     # (B, 3, 3): R src + t ~ tgt
    translation: torch.Tensor  # (B, 3)
    matching: torch.Tensor | None  # (B, N, M) row-stochastic soft matching M, only when asked for
    vcp: torch.Tensor          # (B, N, 3) virtual corresponding points Y' = M Y
    rcp: torch.Tensor          # (B, N, 3) rectified points Y'' = Y' + offset
    offset: torch.Tensor       # (B, N, 3) correction walk (zeros without it)
    src_embedding: torch.Tensor  # (B, c, N) Phi_X
    tgt_embedding: torch.Tensor  # (B, c, M) Phi_Y
    gate_logits: torch.Tensor | None = None        # (B, N) walk gate (VCP needs correcting), or None
    confidence_logits: torch.Tensor | None = None  # (B, N) RCP confidence, or None (unweighted)
    consistency: torch.Tensor | None = None  # (B,) share of RCPs within consistency_radius of R src + t
    second_pass: torch.Tensor | None = None  # (B,) bool: the estimate comes from the second pass
    start_rotation: torch.Tensor | None = None  # (B, 3, 3) the turn of src the estimate's passes began from
    polished: torch.Tensor | None = None  # (B,) bool: the geometric polish moved the estimate
    searched: torch.Tensor | None = None  # (B,) bool: the rotation search took the pair on
    icp_search: torch.Tensor | None = None  # (B,) bool: the estimate comes from the multi-start ICP

    @property
    def weights(self) -> torch.Tensor | None:
        """(B, N) Procrustes weights sigmoid(confidence_logits), or None (uniform)."""
        if self.confidence_logits is None:
            return None
        return procrustes_weights(self.confidence_logits).to(self.rcp.dtype)


@dataclass
class CloudMatch:
    """The soft matching of src features against tgt (shapes for N source and M target points)."""

    vcp: torch.Tensor                # (B, N, 3) M Y
    matched_features: torch.Tensor   # (B, c, N) (M Phi_Y^T)^T
    peak: torch.Tensor               # (B, N) max_j M_ij
    entropy: torch.Tensor            # (B, N) -sum_j M_ij log M_ij
    matching: torch.Tensor | None    # (B, N, M) M, only when asked for


def match_clouds(phi_x: torch.Tensor, phi_y: torch.Tensor, tgt: torch.Tensor, backend: str,
                 return_matching: bool) -> CloudMatch:
    """M = softmax(Phi_X^T Phi_Y / sqrt(c)) applied to [Y | Phi_Y^T] in one streamed pass.

    The row statistics need no matrix either: with s_ij = scale phi_i . psi_j and lse_i the row's
    log-normaliser, peak_i = exp(s_i,argmax - lse_i) and entropy_i = lse_i - sum_j M_ij s_ij =
    lse_i - scale phi_i . (M Phi_Y^T)_i. All are differentiable in both feature sets.
    """
    channels = phi_x.shape[1]
    scale = 1.0 / math.sqrt(channels)
    query, key = phi_x.transpose(1, 2), phi_y.transpose(1, 2)
    if return_matching:
        matching = torch.softmax(torch.bmm(query, phi_y) * scale, dim=-1)
        matched = torch.bmm(matching, torch.cat([tgt, key], dim=-1))
        peak = matching.max(dim=-1).values
        entropy = -(matching * matching.clamp_min(1e-30).log()).sum(dim=-1)
    else:
        out, lse, argmax = soft_match(query, key, torch.cat([tgt, key], dim=-1), scale, backend=backend,
                                      return_stats=True)
        matched, matching = out, None
        peak_key = key.gather(1, argmax.unsqueeze(-1).expand(-1, -1, channels))
        peak = torch.exp(scale * (query * peak_key).sum(-1) - lse)
        entropy = lse - scale * (query * out[..., 3:]).sum(-1)
    return CloudMatch(matched[..., :3], matched[..., 3:].transpose(1, 2), peak, entropy, matching)


def _rows_of(out: VRNetOutput, rows: torch.Tensor) -> VRNetOutput:
    """The rows ``rows`` of every batch-first field of ``out``."""
    values = {f.name: getattr(out, f.name) for f in fields(VRNetOutput)}
    return VRNetOutput(**{name: None if value is None else value[rows] for name, value in values.items()})


def _rows(values: torch.Tensor | None, rows: torch.Tensor) -> torch.Tensor | None:
    """``values[rows]``, or None for None."""
    return None if values is None else values[rows]


def _replace_rows(out: VRNetOutput, rows: torch.Tensor, candidate: VRNetOutput,
                  better: torch.Tensor | None = None) -> None:
    """Where ``better`` (R,) holds (default: where ``candidate``, one row per entry of ``rows``,
    agrees more with its RCPs than ``out``'s rows ``rows`` do), the candidate's rows replace them
    (every field is batch-first; in place; chosen on the device, no host read)."""
    if better is None:
        better = candidate.consistency > out.consistency[rows]
    for field in fields(VRNetOutput):
        value = getattr(out, field.name)
        if value is not None:
            new = getattr(candidate, field.name)
            chosen = torch.where(better.view(-1, *[1] * (new.dim() - 1)), new, value.index_select(0, rows))
            setattr(out, field.name, value.index_copy(0, rows, chosen))


def procrustes_weights(confidence_logits: torch.Tensor) -> torch.Tensor:
    """(B, N) logits -> positive weights (floored so that no pair's weights all vanish)."""
    return torch.sigmoid(confidence_logits).clamp_min(1e-6)


class VRNet(nn.Module):
    """VRNet (Zhang et al.). ``VRNet()`` is the paper's configuration; see :class:`VRNetConfig`."""

    def __init__(self, config: VRNetConfig | None = None) -> None:
        super().__init__()
        self.config = config or VRNetConfig()
        cfg = self.config
        self.features = DGCNN(cfg.dgcnn_channels, cfg.emb_dims, cfg.k, cfg.negative_slope)
        self.transformer = Transformer(cfg.emb_dims, cfg.heads, cfg.ff_dims, cfg.encoder_layers,
                                       cfg.decoder_layers, cfg.dropout)
        walk_inputs = 2 * cfg.emb_dims + (6 if cfg.walk_coordinates else 0) + (2 if cfg.walk_match_stats else 0)
        self.walk = (CorrectionWalk(walk_inputs, cfg.walk_channels, cfg.walk_zero_init, cfg.walk_gate,
                                    cfg.walk_confidence, cfg.walk_confidence_trunk) if cfg.correction_walk else None)

    def feature_modules(self) -> list[nn.Module]:
        """The feature extractor (DGCNN + Transformer): trained in stage 1, frozen in stage 2."""
        return [self.features, self.transformer]

    def forward(self, src: torch.Tensor, tgt: torch.Tensor, backend: str | None = None,
                return_matching: bool = False) -> VRNetOutput:
        """src (B, N, 3), tgt (B, M, 3) -> :class:`VRNetOutput` with R src + t ~ tgt.

        The VCPs and the matched target features come from the streamed ``ops.soft_match``
        (memory O((N + M) c)); the (B, N, M) matching matrix is built only with
        ``return_matching=True`` (L0 in training, pictures). Both clouds are checked for NaN / Inf
        with one host synchronisation on a GPU (none inside ``vrnet_ext.ops.trusted_values()``, where
        the caller vouches for them); everything after runs inside ``trusted_values``, without one
        (but for the data-dependent second look and rotation search, where configured).
        """
        check_float(src, "src")
        check_float(tgt, "tgt")
        check_shape(src, "src", 3, "(B, N, 3)", last=3)
        check_shape(tgt, "tgt", 3, "(B, M, 3)", last=3)
        check_same({"src": src, "tgt": tgt})
        if src.shape[0] != tgt.shape[0]:
            raise ValueError(f"src and tgt batch sizes differ: {src.shape[0]} vs {tgt.shape[0]}")
        weight_dtype = self.features.projection.weight.dtype
        if src.dtype != weight_dtype:
            raise TypeError(f"src has dtype {src.dtype} but the model's weights are {weight_dtype}: "
                            f"pass src.to({weight_dtype}) or convert the model with model.to({src.dtype})")
        check_all_finite({"src": src, "tgt": tgt})
        backend = backend or self.config.backend
        if torch.compiler.is_compiling():
            return self._estimate(src, tgt, backend, return_matching)
        with trusted_values():  # every tensor below comes from the checked clouds through the ops
            return self._estimate(src, tgt, backend, return_matching)

    def _estimate(self, src: torch.Tensor, tgt: torch.Tensor, backend: str, return_matching: bool) -> VRNetOutput:
        """The forward on checked clouds: the passes, then in eval mode the second look, the
        rotation search and the polish where configured."""
        out, tgt_features = self._passes(src, tgt, backend, return_matching)
        out.start_rotation = torch.eye(3, dtype=src.dtype, device=src.device).expand(src.shape[0], 3, 3)
        out.second_pass = torch.zeros(src.shape[0], dtype=torch.bool, device=src.device)
        out.polished = out.searched = out.icp_search = torch.zeros_like(out.second_pass)
        if self.training:
            return out
        if self.config.second_pass_below > 0:
            capturing = src.is_cuda and torch.cuda.is_current_stream_capturing()  # a CUDA graph: no branch on data
            self._second_looks(src, tgt, out, backend, return_matching, tgt_features, every=capturing)
        if self.config.rotation_search_below > 0:
            self._rotation_search(src, tgt, out, backend, return_matching, tgt_features)
        if self.config.polish_iterations > 0:
            out = self.polished(src, tgt, out, self.config.polish_iterations, backend)
        if self.config.rotation_search_icp_starts > 0 and out.searched.any():
            self._icp_search(src, tgt, out, out.searched.nonzero().squeeze(1), backend)
        return out

    def _passes(self, src: torch.Tensor, tgt: torch.Tensor, backend: str, return_matching: bool,
                tgt_features: torch.Tensor | None = None) -> tuple[VRNetOutput, torch.Tensor | None]:
        """The ``iterations`` passes from src as it is: the output with the composed motion and its
        consistency, and the target's features for later passes over the same tgt."""
        rotation = torch.eye(3, dtype=src.dtype, device=src.device).expand(src.shape[0], 3, 3)
        translation = src.new_zeros(src.shape[0], 3)
        moved = src
        for _ in range(self.config.iterations):
            out, tgt_features = self._single_pass(moved, tgt, backend, return_matching, tgt_features)
            with torch.autocast(src.device.type, enabled=False):  # compose the motions in src's dtype
                rotation, translation = compose(out.rotation, out.translation, rotation, translation)
                moved = move(src, rotation, translation)
        out.rotation, out.translation = rotation, translation
        out.consistency = self._consistency(src, rotation, translation, out.rcp)
        return out, tgt_features

    def _consistency(self, src: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor,
                     rcp: torch.Tensor) -> torch.Tensor:
        """(B,) share of the source points whose RCP lies within ``consistency_radius`` of R src + t:
        how far a pair's RCPs agree with its estimate."""
        return correct_match_ratio(rcp, src, rotation, translation, self.config.consistency_radius).to(src.dtype)

    def _second_looks(self, src: torch.Tensor, tgt: torch.Tensor, out: VRNetOutput, backend: str,
                      return_matching: bool, tgt_features: torch.Tensor | None, *, every: bool) -> None:
        """The pairs whose consistency is below ``second_pass_below`` take a second look, kept where
        it agrees more (in place). ``every``: all pairs look again and the choice is made on the
        device (no host read of which pairs are due; the cost of a look for every pair)."""
        due = out.consistency < self.config.second_pass_below
        if every:
            rows = torch.arange(src.shape[0], device=src.device)
            again = self._second_look(src, tgt, out, backend, return_matching, tgt_features)
            _replace_rows(out, rows, again, better=(again.consistency > out.consistency) & due)
            return
        retry = due.nonzero().squeeze(1)
        if retry.numel():
            _replace_rows(out, retry, self._second_look(src[retry], tgt[retry], _rows_of(out, retry), backend,
                                                        return_matching, _rows(tgt_features, retry)))

    def _second_look(self, src: torch.Tensor, tgt: torch.Tensor, out: VRNetOutput, backend: str,
                     return_matching: bool, tgt_features: torch.Tensor | None) -> VRNetOutput:
        """One more pass over each pair from the source moved by ``out``'s estimate (the target's
        features reused where given), its motion composed with ``out``'s, marked ``second_pass``."""
        with torch.autocast(src.device.type, enabled=False):
            moved = move(src, out.rotation, out.translation)
        again, _ = self._single_pass(moved, tgt, backend, return_matching, tgt_features)
        with torch.autocast(src.device.type, enabled=False):
            again.rotation, again.translation = compose(again.rotation, again.translation, out.rotation,
                                                        out.translation)
        again.consistency = self._consistency(src, again.rotation, again.translation, again.rcp)
        again.start_rotation, again.searched = out.start_rotation, out.searched
        again.second_pass = torch.ones(src.shape[0], dtype=torch.bool, device=src.device)
        again.polished = again.icp_search = torch.zeros_like(again.second_pass)
        return again

    def _rotation_search(self, src: torch.Tensor, tgt: torch.Tensor, out: VRNetOutput, backend: str,
                         return_matching: bool, tgt_features: torch.Tensor | None) -> None:
        """Registers the pairs whose consistency is still below ``rotation_search_below`` again from
        the source turned by each start of :func:`search_starts` (about ``rotation_search_centre``),
        a few pairs' turns per batch, each start followed by a second look (kept where its RCPs agree
        more); the start whose estimate brings the source closest to the target (:func:`nearest_median`)
        replaces ``out``'s rows (in place) where it brings it closer than ``out``'s (between starts,
        the RCPs' agreement misjudges noisy pairs). With ``rotation_search_polish`` steps, every
        start's estimate and the pair's own are polished (:meth:`polished`) before they are compared.
        The distances are weighed by :meth:`turn_prior`: under ``max_rotation`` a pair whose estimate
        turns further is searched too, and estimates that turn further count as infinitely far.
        ``searched`` marks the pairs it takes on."""
        prior = self.turn_prior()
        out.searched = (out.consistency < self.config.rotation_search_below) | prior.beyond(out.rotation)
        retry = out.searched.nonzero().squeeze(1)
        if not retry.numel():
            return
        starts = torch.as_tensor(search_starts(self.config.rotation_search_centre), dtype=src.dtype,
                                 device=src.device)  # (S, 3, 3)
        count = starts.shape[0]
        for chunk in retry.split(max(1, SEARCH_POINTS // (count * src.shape[1]))):
            rows = chunk.repeat_interleave(count)  # pair of each (pair, start), start fastest
            turns = starts.repeat(chunk.numel(), 1, 1)
            features = _rows(tgt_features, rows)
            with torch.autocast(src.device.type, enabled=False):
                turned = move(src[rows], turns, src.new_zeros(rows.numel(), 3))
            found, _ = self._passes(turned, tgt[rows], backend, return_matching, features)
            with torch.autocast(src.device.type, enabled=False):  # R' (g src) + t = (R' g) src + t
                found.rotation = found.rotation @ turns
            found.start_rotation = turns
            found.second_pass = found.polished = found.icp_search = torch.zeros_like(rows, dtype=torch.bool)
            found.searched = torch.ones_like(found.second_pass)
            every = torch.arange(rows.numel(), device=src.device)
            _replace_rows(found, every, self._second_look(src[rows], tgt[rows], found, backend, return_matching,
                                                          features))
            own = _rows_of(out, chunk)
            if self.config.rotation_search_polish:  # each candidate polished before they are compared
                found, distance = self._polish(src[rows], tgt[rows], found, self.config.rotation_search_polish,
                                               backend)
                own, so_far = self._polish(src[chunk], tgt[chunk], own, self.config.rotation_search_polish, backend)
                _replace_rows(out, chunk, own, better=own.polished)
            else:
                distance = nearest_median(src[rows], tgt[rows], found.rotation, found.translation, backend)
                so_far = nearest_median(src[chunk], tgt[chunk], own.rotation, own.translation, backend)
            distance, so_far = prior.score(found.rotation, distance), prior.score(own.rotation, so_far)
            best = distance.view(chunk.numel(), count).argmin(dim=1)
            chosen = torch.arange(chunk.numel(), device=src.device) * count + best
            _replace_rows(out, chunk, _rows_of(found, chosen), better=distance[chosen] < so_far)

    def turn_prior(self) -> TurnPrior:
        """How the rotation search and its ICP search weigh an estimate's turn: ``max_rotation`` and
        ``rotation_search_turn_penalty``."""
        return TurnPrior(self.config.max_rotation, self.config.rotation_search_turn_penalty)

    def _icp_search(self, src: torch.Tensor, tgt: torch.Tensor, out: VRNetOutput, rows: torch.Tensor,
                    backend: str) -> None:
        """The rows ``rows`` (the pairs the rotation search took on) registered by :func:`multistart_icp`
        from ``rotation_search_icp_starts`` rotations spread over SO(3) (``rotation_search_icp_slides``
        translations each, ``rotation_search_icp``'s ICP); its result replaces ``out``'s
        rows (in place) where it brings the source clearly nearer the target (:data:`ICP_SEARCH_NEARER`;
        both distances weighed by :meth:`turn_prior`), marked ``icp_search``."""
        prior = self.turn_prior()
        starts = torch.as_tensor(spread_rotations(self.config.rotation_search_icp_starts), dtype=src.dtype,
                                 device=src.device)
        own = _rows_of(out, rows)
        with torch.autocast(src.device.type, enabled=False):
            rotation, translation, distance = multistart_icp(src[rows], tgt[rows], starts, backend,
                                                             self.config.rotation_search_icp_slides,
                                                             self.config.rotation_search_icp,
                                                             prior=prior)
            so_far = prior.score(own.rotation, nearest_median(src[rows], tgt[rows], own.rotation, own.translation,
                                                              backend))
        found = replace(own, rotation=rotation, translation=translation,
                        consistency=self._consistency(src[rows], rotation, translation, own.rcp), second_pass=torch.zeros_like(own.second_pass), polished=torch.zeros_like(own.polished),
                        icp_search=torch.ones_like(own.icp_search))
        _replace_rows(out, rows, found, better=distance < ICP_SEARCH_NEARER * so_far)

    def polished(self, src: torch.Tensor, tgt: torch.Tensor, out: VRNetOutput, steps: int,
                 backend: str | None = None) -> VRNetOutput:
        """``out`` (this model's output for src (B, N, 3), tgt (B, M, 3)) after ``steps`` steps of
        :func:`robust_icp` from each pair's estimate, kept where they bring the source nearer the target
        (:func:`nearest_median`; chosen on the device): the eval forward's last step where
        ``polish_iterations`` > 0. ``polished`` marks the pairs it moved; ``consistency`` then measures
        the kept estimate against the same RCPs. ``out`` itself is left as it is. ``backend``: the
        ops' (default: ``config.backend``)."""
        for name, cloud in (("src", src), ("tgt", tgt)):
            check_float(cloud, name)
            check_shape(cloud, name, 3, "(B, N, 3)", last=3)
        if not src.shape[0] == tgt.shape[0] == out.rotation.shape[0] or src.shape[1] != out.rcp.shape[1]:
            raise ValueError(f"src {tuple(src.shape)} and tgt {tuple(tgt.shape)} are not the clouds of out "
                             f"(rcp {tuple(out.rcp.shape)}, rotation {tuple(out.rotation.shape)})")
        return self._polish(src, tgt, out, steps, backend or self.config.backend)[0]

    def _polish(self, src: torch.Tensor, tgt: torch.Tensor, out: VRNetOutput, steps: int,
                backend: str) -> tuple[VRNetOutput, torch.Tensor]:
        """:meth:`polished` on checked clouds, with the kept estimates' :func:`nearest_median` (B,)."""
        with torch.autocast(src.device.type, enabled=False):
            rotation, translation = robust_icp(src, tgt, out.rotation, out.translation, steps, backend)
            distance = nearest_median(src, tgt, rotation, translation, backend)
            before = nearest_median(src, tgt, out.rotation, out.translation, backend)
        nearer = distance < before
        rotation = torch.where(nearer[:, None, None], rotation, out.rotation)
        translation = torch.where(nearer[:, None], translation, out.translation)
        return (replace(out, rotation=rotation, translation=translation, polished=nearer,
                        consistency=self._consistency(src, rotation, translation, out.rcp)),
                torch.where(nearer, distance, before))

    def _features(self, src: torch.Tensor, tgt: torch.Tensor, backend: str,
                  tgt_features: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """DGCNN features of both clouds, (B, c, N) and (B, c, M): with the DGCNN in eval mode, clouds
        of one size go through as one batch of 2B (BatchNorm then uses its running statistics, so
        each cloud's features are its own). ``tgt_features``, the target's from an earlier pass over
        the same ``tgt``, are taken as they are."""
        if tgt_features is not None:
            return self.features(src, backend), tgt_features
        if not self.features.training and src.shape == tgt.shape:
            return self.features(torch.cat([src, tgt]), backend).chunk(2)
        return self.features(src, backend), self.features(tgt, backend)

    def transformer_in_bf16(self, src: torch.Tensor) -> bool:
        """Whether this forward runs the Transformer's products in bfloat16 (see
        ``VRNetConfig.transformer_precision``); False inside an enclosing autocast region."""
        precision = self.config.transformer_precision
        if precision == "fp32" or torch.is_autocast_enabled(src.device.type):
            return False
        if precision == "bf16":
            return True
        return (src.device.type == "cpu" and src.dtype == torch.float32 and not self.transformer.training
                and cpu_has_native_bf16())

    def features_need_grad(self, src: torch.Tensor, tgt: torch.Tensor) -> bool:
        """Whether autograd has to record the features and the matching: grad mode is on and the
        clouds or a parameter of the feature extractor require a gradient (not when it is frozen
        and the clouds are data, as in stage 2 of training)."""
        if not torch.is_grad_enabled():
            return False
        return (src.requires_grad or tgt.requires_grad
                or any(p.requires_grad for module in self.feature_modules() for p in module.parameters()))

    def _single_pass(self, src: torch.Tensor, tgt: torch.Tensor, backend: str, return_matching: bool,
                     tgt_features: torch.Tensor | None = None) -> tuple[VRNetOutput, torch.Tensor | None]:
        """One registration of src to tgt, and the target's DGCNN features for a later pass over the
        same tgt (None while the DGCNN trains: its batch statistics then belong to each pass)."""
        # Where nothing upstream of the walk needs a gradient, no_grad changes no value; it lets the
        # feature modules reuse their inference-time weights (nn.inference_cache).
        with contextlib.nullcontext() if self.features_need_grad(src, tgt) else torch.no_grad():
            features = self._features(src, tgt, backend, tgt_features)
            bf16 = self.transformer_in_bf16(src)
            with torch.autocast(src.device.type, dtype=torch.bfloat16) if bf16 else contextlib.nullcontext():
                phi_x, phi_y = self.transformer(*features, backend=backend)
            # The soft matching decides where every VCP lands: it runs in float32 even under autocast
            # (a bfloat16 score carries ~3 significant digits, a visible error on sharp softmax rows).
            with torch.autocast(src.device.type, enabled=False):
                phi_x, phi_y = phi_x.to(src.dtype), phi_y.to(src.dtype)
                match = match_clouds(phi_x, phi_y, tgt, backend, return_matching)
        if self.walk is None:
            offset, gate_logits, confidence_logits = torch.zeros_like(match.vcp), None, None
        else:
            # Seeds built point-major, (B, N, C) in memory: the walk's folded eval-mode products
            # then read them as plain rows.
            seeds = [phi_x.transpose(1, 2), match.matched_features.transpose(1, 2)]
            if self.config.walk_coordinates:
                seeds += [src, match.vcp]
            if self.config.walk_match_stats:
                seeds += [torch.stack([match.peak, match.entropy], dim=-1).to(phi_x.dtype)]
            walk = self.walk(torch.cat(seeds, dim=-1).transpose(1, 2))
            offset, gate_logits, confidence_logits = walk.offset, walk.gate_logits, walk.confidence_logits
        vcp, matching = match.vcp, match.matching
        rcp = vcp + offset
        weights = None if confidence_logits is None else procrustes_weights(confidence_logits).to(src.dtype)
        aligned_to = rcp if self.config.procrustes_points == "rcp" else vcp
        rotation, translation = robust_kabsch(src, aligned_to, weights, self.config.irls_iterations,
                                              self.config.irls_kernel, self.config.irls_scale,
                                              self.config.irls_min_scale, backend=backend)
        out = VRNetOutput(rotation, translation, matching, vcp, rcp, offset, phi_x, phi_y, gate_logits,
                          confidence_logits)
        return out, None if self.features.training else features[1]
