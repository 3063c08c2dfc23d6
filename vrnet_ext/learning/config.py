"""What a training run is: :class:`TrainConfig`, the presets and the help text of every option.

Free of torch, so that ``vrnet train --help`` answers at once; :mod:`vrnet_ext.learning.train` runs it.
"""
from __future__ import annotations

import math
from dataclasses import MISSING, asdict, dataclass, field, fields

from vrnet_ext.model.config import VRNetConfig
from vrnet_ext.names import (AUTO_DEVICE, DEFAULT_BACKEND, DEFAULT_MAX_ANGLE, DEFAULT_ROTATION_RANGE, DEFAULT_SETTING,
                             DEFAULT_SPLIT, ROTATION_RANGES)


def trained_model(config: VRNetConfig) -> dict:
    """A model configuration to train, as a dict without the rotation search's centre: that follows
    the rotations the run draws (:func:`vrnet_ext.model.checkpoints.model_values`) unless a run sets
    it."""
    values = config.to_dict()
    del values["rotation_search_centre"]
    return values


PRESETS = {
    "paper": dict(model=trained_model(VRNetConfig()), batch_size=28, stage1_epochs=100, stage2_epochs=100,
                  num_points=1024, num_subsampled=768),
    "small": dict(model=trained_model(VRNetConfig.small()), batch_size=8, stage1_epochs=3, stage2_epochs=2,
                  num_points=512, num_subsampled=384, max_train_items=480, max_val_items=96),
    "cpu": dict(model=trained_model(VRNetConfig.small()), batch_size=16, stage1_epochs=30, stage2_epochs=10,
                num_points=1024, num_subsampled=768, lr_milestones=[20]),
    "tiny": dict(model=trained_model(VRNetConfig.small(k=8, dgcnn_channels=(16, 16), emb_dims=32, heads=2,
                                                       ff_dims=64, walk_channels=(32, 16, 3))),
                 batch_size=4, stage1_epochs=1, stage2_epochs=1, num_points=96, num_subsampled=64,
                 max_train_items=16, max_val_items=8),
}


PRECISIONS = ("auto", "bf16", "fp32")
MODELNET_POINTS = 1024  # points per shape in the ModelNet40 HDF5 files
L4_FORMS = ("rmse", "log")

# What each training option means (``vrnet train --help`` adds every preset's value).
FIELD_HELP = {
    "data_dir": "folder holding modelnet40_1024_{train,test}.h5",
    "out_dir": "where checkpoints, metrics.jsonl/csv and curves.png go",
    "setting": "CO | PV | RS | PV+RS | mixed (one of the four per pair: one model for every setting)",
    "split": "UPC | UC | ND",
    "batch_size": "pairs per step (per process under DDP)",
    "stage1_epochs": "epochs of stage 1 (features, L0)",
    "stage2_epochs": "epochs of stage 2 (correction walk, hybrid loss; features frozen unless --lr-features-stage2)",
    "lr_stage1": "Adam learning rate of stage 1",
    "lr_stage2": "Adam learning rate of stage 2",
    "lr_features_stage2": "stage 2 also fine-tunes the feature extractor's weights (DGCNN + Transformer; its "
                          "BatchNorm statistics stay as they are) with the hybrid loss at this Adam learning rate, end "
                          "to end through the matching (0: frozen, the paper's schedule; not in the paper)",
    "weight_decay": "Adam weight decay",
    "lr_milestones": "the learning rate is multiplied by lr_gamma after each of these many epochs, counted within "
                     "each stage (2: the first two epochs at the full rate)",
    "lr_gamma": "learning-rate factor at each milestone",
    "num_points": "points per shape before the crop",
    "num_subsampled": "points per cloud after the PV / RS crop",
    "classes": "keep only these ModelNet40 labels (default: all forty)",
    "max_train_items": "use at most this many training shapes (None: all)",
    "max_val_items": "validate on at most this many held-out shapes (None: all)",
    "val_fraction": "share of the training shapes held out for validation",
    "train_max_angle": "largest rotation about each axis of the training pairs, in degrees (validation pairs keep "
                       "the protocol's 45: a wider range trains the features on the large motions where the errors "
                       "of a 45-degree test concentrate)",
    "rotation_range": "how the rotations of the training and validation pairs are drawn: protocol = each Euler angle "
                      "in [0, max] degrees (the paper's); symmetric = in [-max, max]; so3 = uniform over all rotations",
    "seed": "seed of the training pairs, batch order and initialisation (every run validates on the same held-out "
            "shapes and pairs)",
    "device": "auto | cpu | cuda",
    "backend": "ext (compiled ops) | torch (pure PyTorch)",
    "num_workers": "DataLoader worker processes",
    "loss_l4": "weight of L4 (amendment offset) in the hybrid loss",
    "loss_l4_form": "rmse: the paper's L4 (outliers dominate) | log: mean log(1 + error / 0.01) per point "
                    "(small errors count as much as large ones)",
    "far_points": "partial views (PV, PV+RS) for training and validation: prnet = the paper's: one far point near the "
                  "diagonal cuts both clouds; sphere = in a random direction for each cloud; mixed = one of the two "
                  "per pair; symmetric = the target's far point mirrors the source's (the paper's ablations)",
    "loss_motion": "weight of LM, the supervised motion loss rmse(R^T R_gt, I) + rmse(t, t_gt) of the network's "
                   "estimate (DCP's; not in the paper; 0: off)",
    "loss_motion_translation": "weight of LM's translation term rmse(t, t_gt) against its rotation term (1: DCP's; "
                               "a rotation error of 1 degree weighs about as much as a translation error of 0.014)",
    "precision": "auto: bf16 where the device multiplies bfloat16 in hardware (AVX512-BF16 / AMX CPUs, bf16 GPUs), "
                 "fp32 elsewhere (emulated bfloat16 is several times slower) | bf16: forward and loss under bfloat16 "
                 "autocast (ops, matching and Procrustes stay float32) | fp32. A run records what auto chose; "
                 "--resume keeps it",
    "checkpoint_minutes": "also write last.pt every this many minutes inside an epoch",
    "resume": "continue from this last.pt (same model options as the run that wrote it; a larger epoch count "
              "extends a finished stage, and this run's --lr-milestones apply)",
    "features_from": "start from the feature extractor of this checkpoint or shipped model (e.g. stage 2 on another "
                     "run's features)",
    "walk_from": "start the correction walk from this checkpoint's or shipped model's walk (a shared-trunk walk is "
                 "split in two when this run has --walk-confidence-trunk)",
    "freeze_confidence": "stage 2 leaves the walk's confidence MLP as it is (weights and BatchNorm statistics; "
                         "needs --walk-confidence-trunk): train the offsets on a trained walk's confidences "
                         "(with --walk-from)",
    "progress": "progress bars",
    "flush_denormal": "flush denormal floats to zero (much faster soft matching on x86)",
}


def preset_values(name: str) -> dict[str, object]:
    """Every preset's value of one training option (``preset -> value``)."""
    section = SECTIONS[SECTION_OF[name]]
    default = {f.name: (f.default if f.default_factory is MISSING else f.default_factory())
               for f in fields(section)}[name]
    return {preset: values.get(name, default) for preset, values in PRESETS.items()}


def _finite(options, names: tuple[str, ...], positive: bool) -> None:
    """Refuses any of ``options``' fields ``names`` that is not a finite number > 0 (``positive``) or >= 0."""
    for name in names:
        value = getattr(options, name)
        if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value)
                                           and (value > 0 if positive else value >= 0)):
            raise ValueError(f"{name} must be a finite number {'>' if positive else '>='} 0, got {value!r}")


def _integers(options, smallest: dict[str, int]) -> None:
    """Refuses any of ``options``' fields (name -> smallest allowed) that is not an integer that large."""
    for name, least in smallest.items():
        value = getattr(options, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < least:
            raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")


@dataclass
class DataOptions:
    """Which pairs a run trains and validates on (``vrnet train``'s data options)."""

    data_dir: str | None = None
    setting: str = DEFAULT_SETTING
    split: str = DEFAULT_SPLIT
    num_points: int = 1024
    num_subsampled: int = 768
    far_points: str = "prnet"
    classes: list[int] | None = None
    max_train_items: int | None = None
    max_val_items: int | None = None
    val_fraction: float = 0.1
    train_max_angle: float = DEFAULT_MAX_ANGLE
    rotation_range: str = DEFAULT_ROTATION_RANGE
    seed: int = 1234

    def __post_init__(self) -> None:
        _finite(self, ("val_fraction",), positive=False)
        _integers(self, {"num_points": 1, "num_subsampled": 1, "seed": 0})
        if not (isinstance(self.train_max_angle, (int, float)) and 0 < self.train_max_angle <= 180):
            raise ValueError(f"train_max_angle must be in (0, 180] degrees, got {self.train_max_angle!r}")
        if self.rotation_range not in ROTATION_RANGES:
            raise ValueError(f"rotation_range must be one of {ROTATION_RANGES}, got {self.rotation_range!r}")
        if self.num_points > MODELNET_POINTS:
            raise ValueError(f"num_points must be at most {MODELNET_POINTS} (the ModelNet40 files hold "
                             f"{MODELNET_POINTS} points per shape), got {self.num_points}")
        if self.num_subsampled > self.num_points:
            raise ValueError(f"num_subsampled ({self.num_subsampled}) must be at most num_points "
                             f"({self.num_points})")


@dataclass
class ScheduleOptions:
    """How long and how fast each stage trains (``vrnet train``'s schedule options)."""

    batch_size: int = 28
    stage1_epochs: int = 100
    stage2_epochs: int = 100
    lr_stage1: float = 1e-3
    lr_stage2: float = 1e-4
    lr_features_stage2: float = 0.0
    weight_decay: float = 1e-4
    lr_milestones: list[int] = field(default_factory=lambda: [75])
    lr_gamma: float = 0.1

    def __post_init__(self) -> None:
        _finite(self, ("lr_stage1", "lr_stage2", "lr_gamma"), positive=True)
        _finite(self, ("weight_decay", "lr_features_stage2"), positive=False)
        _integers(self, {"stage1_epochs": 0, "stage2_epochs": 0, "batch_size": 1})
        if any(isinstance(m, bool) or not isinstance(m, int) or m < 1 for m in self.lr_milestones):
            raise ValueError(f"lr_milestones must be epochs >= 1, got {self.lr_milestones}")


@dataclass
class LossOptions:
    """The hybrid loss's weights and forms (``vrnet train``'s loss options)."""

    loss_l4: float = 100.0
    loss_l4_form: str = "rmse"
    loss_motion: float = 0.0
    loss_motion_translation: float = 1.0

    def __post_init__(self) -> None:
        _finite(self, ("loss_l4", "loss_motion", "loss_motion_translation"), positive=False)
        if self.loss_l4_form not in L4_FORMS:
            raise ValueError(f"loss_l4_form must be one of {L4_FORMS}, got {self.loss_l4_form!r}")


@dataclass
class StartOptions:
    """What a run starts from (``vrnet train``'s start options): a checkpoint to resume, warm starts."""

    resume: str | None = None
    features_from: str | None = None
    walk_from: str | None = None
    freeze_confidence: bool = False


@dataclass
class RuntimeOptions:
    """Where and how a run executes (``vrnet train``'s runtime options); none changes what is learned
    except ``precision``."""

    out_dir: str = "runs/vrnet"
    device: str = AUTO_DEVICE
    backend: str = DEFAULT_BACKEND
    num_workers: int = 0
    precision: str = "auto"
    flush_denormal: bool = True
    checkpoint_minutes: float = 10.0
    progress: bool = True

    def __post_init__(self) -> None:
        _integers(self, {"num_workers": 0})
        _finite(self, ("checkpoint_minutes",), positive=True)
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {self.precision!r}")


# The options in sections: ``vrnet train --help`` shows them so, and a TrainConfig holds one of each.
SECTIONS = {"data": DataOptions, "schedule": ScheduleOptions, "loss": LossOptions, "start": StartOptions,
            "runtime": RuntimeOptions}
SECTION_OF = {f.name: name for name, section in SECTIONS.items() for f in fields(section)}


@dataclass
class TrainConfig:
    """Everything a run needs: the preset it started from, the model's options (a
    :class:`~vrnet_ext.model.config.VRNetConfig` as a dict) and one object per section of
    :data:`SECTIONS`. Every section field is a ``vrnet train`` flag; checkpoints store
    :meth:`to_dict`'s flat form."""

    preset: str = "paper"
    model: dict = field(default_factory=lambda: trained_model(VRNetConfig()))
    data: DataOptions = field(default_factory=DataOptions)
    schedule: ScheduleOptions = field(default_factory=ScheduleOptions)
    loss: LossOptions = field(default_factory=LossOptions)
    start: StartOptions = field(default_factory=StartOptions)
    runtime: RuntimeOptions = field(default_factory=RuntimeOptions)

    @classmethod
    def from_flat(cls, values: dict) -> "TrainConfig":
        """A config from one flat dict of option names (``preset``, ``model`` and section fields), as
        :meth:`to_dict` writes; unknown names are refused."""
        unknown = set(values) - set(SECTION_OF) - {"preset", "model"}
        if unknown:
            raise ValueError(f"unknown training options: {sorted(unknown)}")
        sections = {name: section(**{key: value for key, value in values.items() if SECTION_OF.get(key) == name})
                    for name, section in SECTIONS.items()}
        top = {key: values[key] for key in ("preset", "model") if key in values}
        return cls(**top, **sections)

    @classmethod
    def from_preset(cls, preset: str, **overrides) -> "TrainConfig":
        """A preset's config with ``overrides`` (flat option names; None leaves the preset's value)."""
        if preset not in PRESETS:
            raise ValueError(f"preset must be one of {sorted(PRESETS)}, got {preset!r}")
        values = dict(PRESETS[preset], preset=preset)
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls.from_flat(values)

    def to_dict(self) -> dict:
        """The flat form (``preset``, ``model`` and every section's fields side by side), as checkpoints
        and ``config.json`` store it."""
        flat = {"preset": self.preset, "model": dict(self.model)}
        for name in SECTIONS:
            flat.update(asdict(getattr(self, name)))
        return flat

    def __post_init__(self) -> None:
        if self.start.freeze_confidence and not self.model.get("walk_confidence_trunk"):
            raise ValueError("freeze_confidence needs walk_confidence_trunk (a confidence MLP of its own)")


__all__ = ["FIELD_HELP", "L4_FORMS", "PRECISIONS", "PRESETS", "SECTIONS", "DataOptions", "LossOptions",
           "RuntimeOptions", "ScheduleOptions", "StartOptions", "TrainConfig", "preset_values"]
