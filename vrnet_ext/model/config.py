"""VRNet hyper-parameters. Defaults are the paper's configuration (Sec. III-D)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from vrnet_ext.names import (ANY_ROTATION, BACKENDS, DEFAULT_SEARCH_ICP, MAX_SEARCH_ICP_SLIDES, MAX_TURN_PENALTY,
                             PROCRUSTES_POINTS, ROTATION_RANGES, SEARCH_ICPS, TRANSFORMER_PRECISIONS)

# The robust weights of the IRLS steps (vrnet_ext.ops.kabsch.ROBUST_KERNELS, named here too so that
# this module stays free of torch: the CLI builds its parsers from it).
IRLS_KERNELS = ("cauchy", "geman_mcclure", "welsch")
MAX_POLISH_ITERATIONS = 1000  # the most ICP steps of VRNetConfig.polish_iterations and rotation_search_polish
MAX_ICP_STARTS = 4096  # the most starts of VRNetConfig.rotation_search_icp_starts


@dataclass
class VRNetConfig:
    """Architecture of :class:`vrnet_ext.VRNet`.

    Choices where the paper is vague (documented here, all configurable):

    * ``dgcnn_channels`` + ``emb_dims``: four EdgeConv layers [64, 64, 128, 256] whose outputs are
      concatenated (512) and projected to ``emb_dims`` = c = 512 by a 1x1 conv, as in DCP's DGCNN
      (the paper's "five layers [64, 64, 128, 256, 512]" with the last one the projection).
    * ``negative_slope``: LeakyReLU(0.2) after each BatchNorm (DGCNN; ReLU is slope 0).
    * ``walk_coordinates``: the correction walk sees the paper's seeds E = [Phi_X ; M Phi_Y]
      only (False, the default) or additionally the coordinates [X ; Y'] (True).
    * ``iterations``: > 1 runs the ICP-like mode of the paper's "VRNet with iteration": the source
      is moved by the running estimate and the increments are composed.
    * ``walk_zero_init``: the walk's last (linear) layer starts at zero, so the RCPs start equal to
      the VCPs and stage 2 starts from stage 1's estimate instead of from random offsets of about
      the objects' size (True, the default; the paper does not say; False: PyTorch's default init).
    * ``walk_gate``: the walk's offset is multiplied by a learned per-point gate in (0, 1), so
      points whose VCP is already right can keep it exactly (not in the paper; False: the paper's
      ungated walk).
    * ``walk_confidence``: the walk also predicts a per-point confidence in (0, 1) that weights the
      final Procrustes (not in the paper, whose Procrustes is unweighted; False: unweighted).
    * ``walk_confidence_trunk``: the confidence comes from its own MLP of the walk's widths instead
      of a fourth output of the offsets' MLP, so the loss on the offsets (L4) does not shape the
      features the confidence is read from (needs ``walk_confidence``; not in the paper).
    * ``walk_match_stats``: the walk also sees two statistics of each point's row of the soft
      matching, its largest entry and its entropy (how sure the match is; not in the paper).
    * ``procrustes_points``: the final Procrustes aligns the source with its RCPs (``"rcp"``, the
      paper) or with its VCPs (``"vcp"``), weighted by the walk's confidences either way; the walk's
      offsets then only shape the confidences (through training) and ``out.rcp``.
    * ``irls_iterations``: after the (weighted) Procrustes, this many reweighting steps: each point's
      weight is multiplied by a robust weight w(r / s) of its residual r under the current estimate,
      s = ``irls_scale`` x the median residual of the pair (at least ``irls_min_scale``), and
      Procrustes is solved again (not in the paper; 0: a single solve). ``irls_kernel`` names w
      (:func:`vrnet_ext.ops.kabsch.robust_weights`: ``"cauchy"``, ``"geman_mcclure"``,
      ``"welsch"``). A smaller scale and a steeper kernel trust fewer points: right where most RCPs
      sit on their counterparts and a minority is far off.
    * ``second_pass_below``: after the last pass, a pair whose estimate agrees with fewer than this
      share of its RCPs (its ``consistency``: RCPs within ``consistency_radius`` of the moved source
      point, in the clouds' units) is registered once more from the moved source, as a pass of
      ``iterations`` would, and the pass whose RCPs agree more with its own estimate is kept (not in
      the paper; 0: never). Only in eval mode; training losses see the passes of
      ``iterations`` alone. A pair the passes register well has most RCPs on its estimate; one that
      failed (a large rotation, a symmetric shape) has almost none, and a second look from closer
      usually fixes it.
    * ``rotation_search_below``: after the second pass, a pair whose consistency is still below this
      share is registered again from its source turned by each start of
      :func:`vrnet_ext.geometry.transforms.search_starts` (the 23 other rotations of a cube: every
      rotation lies within 63 degrees of one of them; 24 more about ``rotation_search_centre``), a
      few pairs' starts per batch, each start followed by a second look from its estimate (kept
      where its RCPs agree more); the start whose estimate brings the source closest to the target
      (the median distance to the nearest target point) is kept where it brings it closer than the
      estimate so far (not in the paper; 0: never; eval mode only). A model trained on the
      protocol's rotations (each Euler angle in [0, 45] degrees) fails on most other motions; with
      the search it registers rotations from all of SO(3), at S x (iterations + 1) more passes for
      each pair it searches (S = 23 starts, 47 with a centre other than the identity) and none for
      the others.
    * ``rotation_search_centre``: the Euler angles (z, y, x in degrees; scipy's ``"zyx"``) of the
      centre of the rotations the model was trained on (:func:`training_rotations_centre`). Where it
      is not the identity, the rotation search also starts from the source turned by each cube
      rotation followed by this rotation's inverse, so that for any motion one of these starts
      leaves a motion within 62.8 degrees of the centre, among the rotations the model learned (a
      model trained on the protocol's octant registers few of the motions the cube's starts leave
      about the identity). Loading a file sets it from the rotations its training pairs were drawn
      from (:func:`vrnet_ext.model.checkpoints.model_values`).
    * ``rotation_search_polish``: in the rotation search, this many steps of the polish below from
      every start's estimate and from the pair's own before the nearest is kept (0: none; eval mode
      only). The network may leave a searched pair 10-15 degrees off from its best start, too far for
      the nearest-distance choice to see (a flip of a round shape lies nearer), yet near enough for
      ICP; where the pairs' points have exact counterparts (noise-free pairs) the polished truth lies
      far nearer than any polished flip. Under noise a polished flip of a round shape can lie as near
      as the polished truth: choose it on validation. Each step costs a nearest-neighbour search per
      start of each searched pair.
    * ``rotation_search_icp_starts``: after the rotation search (and the polish below), each pair
      the search took on is also registered by ICP alone (robust unless ``rotation_search_icp``
      says) from this many rotations spread evenly over SO(3) (:func:`vrnet_ext.geometry.alignment.multistart_icp`,
      :func:`vrnet_ext.geometry.transforms.spread_rotations`), and the nearest result replaces the
      estimate where it brings the source clearly nearer the target (the median distance to the
      nearest target point below 0.85 of the estimate's: on noisy partial views a flip of a round
      shape can lie a few per cent nearer than the truth); not in the paper; 0: never; eval mode only. For the nearly round shapes from
      which no start of the network registers a pair, while the geometry says the estimate is wrong.
      512 starts cost about 0.3-1.2 s per searched pair of 768 points on one CPU core.
    * ``rotation_search_icp_slides`` and ``rotation_search_icp``: the multi-start ICP above starts
      from each rotation with this many translations (1: the one that puts the centroids together;
      more: spread along the target's longest axis, :func:`vrnet_ext.geometry.alignment.slides`), and
      runs this ICP (:data:`vrnet_ext.names.SEARCH_ICPS`: ``"robust"``, the polish's, or
      ``"trimmed"``, on the nearer half of the nearest-point pairs). Two partial views of an
      elongated shape cut from different sides put their centroids apart along it, beyond ICP's
      reach; on such noisy views robust ICP drifts off the truth where trimmed ICP holds it. The
      cost grows with the slides (17 slides of 512 starts, trimmed: 4.5-4.9 s per searched pair of
      768 points on two CPU threads).
    * ``max_rotation``: a bound the caller knows on the motion, in degrees (the angle by which R turns
      the source; 180, the default: none). With the rotation search, a pair whose estimate turns
      further is searched whatever its consistency, and the search, its polish and its ICP search
      keep only estimates within the bound (the ICP search runs only its starts near it); a pair none
      of whose estimates is within it keeps the one it had. Not in the paper; eval mode only. For
      motions known to be moderate (e.g. each Euler angle within 45 degrees turns by at most 85.8):
      a flip of a nearly round shape, which the geometry cannot tell from the truth under noise, is
      then not taken.
    * ``rotation_search_turn_penalty`` p: the rotation search and its ICP search weigh each
      estimate's distance by (1 + p x turn / 180), the turn in degrees by which it turns the source
      (:class:`vrnet_ext.geometry.alignment.TurnPrior`; 0, the default: every turn alike): of two
      estimates the geometry can hardly tell apart the smaller motion is kept, while one clearly
      nearer still wins, whatever the turn. Not a bound: no motion is ruled out. Not in the paper;
      eval mode only.
    * ``polish_iterations``: last, this many steps of a robust point-to-point ICP from each pair's
      estimate (:func:`vrnet_ext.geometry.alignment.robust_icp`: the nearest target point of each
      moved source point, Cauchy-reweighted Procrustes), kept where they bring the source nearer the
      target (the median distance to the nearest target point); not in the paper; 0: never; eval
      mode only. The network's estimate of a noisy pair is often a fraction of a degree to a few
      degrees off; ICP from there uses every point, not only the matches, and rarely leaves a pair
      worse (never by that distance). It does not rescue an estimate far off (ICP finds the nearest
      local minimum). Each step costs a nearest-neighbour search and four small Procrustes solves per pair.
    * ``correction_walk=False`` gives DCP-v2 (VCPs only) for the ablation.

    Run-time choices (no effect on the weights):

    * ``backend``: ``"ext"`` (compiled ops) or ``"torch"`` (the pure-PyTorch references).
    * ``transformer_precision``: the Transformer's matrix products (attention, projections) in
      ``"bf16"`` (bfloat16 with float32 accumulation; its residual stream and LayerNorms stay float32,
      as under autocast) or ``"fp32"``; ``"auto"`` (the default) takes bf16 for float32 inputs on a
      CPU that multiplies bfloat16 in hardware (AVX512-BF16 / AMX) while the Transformer is in eval
      mode (inference, and stage 2 of training, which freezes it), and fp32 otherwise. The shipped
      models' features were trained under bfloat16 autocast, so ``"auto"`` computes the Transformer
      as in training. The DGCNN, the soft matching, the walk and the Procrustes solve stay in the
      input's dtype; an enclosing autocast region decides for itself.
    """

    k: int = 20
    dgcnn_channels: tuple[int, ...] = (64, 64, 128, 256)
    emb_dims: int = 512
    negative_slope: float = 0.2
    heads: int = 4
    ff_dims: int = 1024
    encoder_layers: int = 1
    decoder_layers: int = 1
    dropout: float = 0.0
    walk_channels: tuple[int, ...] = (512, 256, 512, 256, 128, 16, 3)
    walk_coordinates: bool = False
    walk_zero_init: bool = True
    walk_gate: bool = False
    walk_confidence: bool = False
    walk_match_stats: bool = False
    walk_confidence_trunk: bool = False
    correction_walk: bool = True
    procrustes_points: str = "rcp"
    irls_iterations: int = 0
    irls_kernel: str = "cauchy"
    irls_scale: float = 3.0
    irls_min_scale: float = 1e-3
    iterations: int = 1
    second_pass_below: float = 0.0
    rotation_search_below: float = 0.0
    rotation_search_centre: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation_search_polish: int = 0
    rotation_search_icp_starts: int = 0
    rotation_search_icp_slides: int = 1
    rotation_search_icp: str = DEFAULT_SEARCH_ICP
    max_rotation: float = ANY_ROTATION
    rotation_search_turn_penalty: float = 0.0
    polish_iterations: int = 0
    consistency_radius: float = 0.02
    backend: str = "ext"
    transformer_precision: str = "auto"

    def __post_init__(self) -> None:
        self.dgcnn_channels = tuple(int(c) for c in self.dgcnn_channels)
        self.walk_channels = tuple(int(c) for c in self.walk_channels)
        if self.walk_channels[-1] != 3:
            raise ValueError(f"walk_channels must end with 3 (an xyz offset), got {self.walk_channels}")
        if self.emb_dims % self.heads:
            raise ValueError(f"emb_dims ({self.emb_dims}) must be divisible by heads ({self.heads})")
        if self.k < 1 or self.iterations < 1:
            raise ValueError("k and iterations must be >= 1")
        if self.walk_confidence_trunk and not self.walk_confidence:
            raise ValueError("walk_confidence_trunk needs walk_confidence=True")
        if self.procrustes_points not in PROCRUSTES_POINTS:
            raise ValueError(f"procrustes_points must be one of {PROCRUSTES_POINTS}, got {self.procrustes_points!r}")
        if self.irls_iterations < 0 or not self.irls_min_scale > 0 or not self.irls_scale > 0:
            raise ValueError("irls_iterations must be >= 0, irls_scale and irls_min_scale > 0")
        if not 0 <= self.second_pass_below <= 1 or not 0 < self.consistency_radius < float("inf"):
            raise ValueError(f"second_pass_below must be in [0, 1] and consistency_radius a positive finite "
                             f"distance, got {self.second_pass_below} and {self.consistency_radius}")
        self.rotation_search_centre = tuple(float(a) for a in self.rotation_search_centre)
        if len(self.rotation_search_centre) != 3 or not all(-180 <= a <= 180 for a in self.rotation_search_centre):
            raise ValueError(f"rotation_search_centre must be three Euler angles in [-180, 180] degrees, "
                             f"got {self.rotation_search_centre}")
        for name, low, high in (("rotation_search_polish", 0, MAX_POLISH_ITERATIONS),
                                ("polish_iterations", 0, MAX_POLISH_ITERATIONS),
                                ("rotation_search_icp_starts", 0, MAX_ICP_STARTS),
                                ("rotation_search_icp_slides", 1, MAX_SEARCH_ICP_SLIDES)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise ValueError(f"{name} must be an integer in [{low}, {high}], got {value!r}")
        if self.rotation_search_icp not in SEARCH_ICPS:
            raise ValueError(f"rotation_search_icp must be one of {SEARCH_ICPS}, got {self.rotation_search_icp!r}")
        if not 0 <= self.rotation_search_below <= 1:
            raise ValueError(f"rotation_search_below must be in [0, 1], got {self.rotation_search_below}")
        if (isinstance(self.max_rotation, bool) or not isinstance(self.max_rotation, (int, float))
                or not 0 < self.max_rotation <= ANY_ROTATION):
            raise ValueError(f"max_rotation must be in (0, {ANY_ROTATION:g}] degrees, got {self.max_rotation!r}")
        self.max_rotation = float(self.max_rotation)
        penalty = self.rotation_search_turn_penalty
        if isinstance(penalty, bool) or not isinstance(penalty, (int, float)) or not 0 <= penalty <= MAX_TURN_PENALTY:
            raise ValueError(f"rotation_search_turn_penalty must be in [0, {MAX_TURN_PENALTY:g}], got {penalty!r}")
        self.rotation_search_turn_penalty = float(penalty)
        if self.irls_kernel not in IRLS_KERNELS:
            raise ValueError(f"irls_kernel must be one of {IRLS_KERNELS}, got {self.irls_kernel!r}")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {self.backend!r}")
        if self.transformer_precision not in TRANSFORMER_PRECISIONS:
            raise ValueError(f"transformer_precision must be one of {TRANSFORMER_PRECISIONS}, "
                             f"got {self.transformer_precision!r}")

    def to_dict(self) -> dict:
        """Plain-type dict (lists, not tuples): safe for ``torch.load(weights_only=True)`` and JSON."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, values: dict) -> "VRNetConfig":
        known = {f.name for f in fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"unknown VRNetConfig fields: {sorted(unknown)}")
        return cls(**values)

    @classmethod
    def small(cls, **overrides) -> "VRNetConfig":
        """A CPU-sized model (about 1/16 of the paper's FLOPs) for quick experiments and tests."""
        values = dict(k=10, dgcnn_channels=(32, 32, 64, 64), emb_dims=128, ff_dims=256,
                      walk_channels=(128, 64, 32, 16, 3))
        values.update(overrides)
        return cls(**values)


def training_rotations_centre(rotation_range: str, max_angle: float) -> tuple[float, float, float]:
    """The Euler angles (z, y, x, degrees) at the centre of the rotations drawn as ``rotation_range``
    says with ``max_angle`` (:func:`vrnet_ext.data.protocol.random_motion`): half of it about every
    axis for the protocol's (each angle in [0, max_angle]), the identity for the ranges centred on it."""
    if rotation_range not in ROTATION_RANGES:
        raise ValueError(f"rotation_range must be one of {ROTATION_RANGES}, got {rotation_range!r}")
    half = max_angle / 2 if rotation_range == "protocol" else 0.0
    return (half, half, half)


__all__ = ["VRNetConfig", "training_rotations_centre"]
