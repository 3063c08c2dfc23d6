"""Two-stage VRNet training (paper Sec. III-D), single process or DDP under ``torchrun``.

Stage 1 trains the feature extractor (DGCNN + Transformer) with L0 (Adam, lr 1e-3); stage 2
freezes it (weights and BatchNorm statistics) and trains the correction walk with the hybrid
loss L (lr 1e-4). With ``lr_features_stage2`` > 0, stage 2 also fine-tunes the feature extractor
with L at that rate, end to end through the soft matching (not in the paper). Each epoch ends
with a validation pass on a split held out of TRAIN (model selection never looks at the test
set), a line in ``metrics.jsonl`` / ``metrics.csv`` and the checkpoints (``torch.load(...,
weights_only=True)`` compatible): ``last.pt``; ``best.pt``, the epoch with the lowest validation
RMSE(R) over both stages (stage 1 measures it with the VCPs, stage 2 with the RCPs);
``best_stage1.pt`` / ``best_stage2.pt``, each stage's best by its own criterion (validation L0 /
RMSE(R)). The validation shapes and pairs are the same in every run, whatever its seed.

Runs are reproducible: the train pairs of an epoch come from (seed, epoch, index), the batch
order from a seeded sampler and the L1 subsets from (seed, step), so ``--resume`` continues
bit-exactly. Besides the end of every epoch, ``last.pt`` is also written every
``checkpoint_minutes`` inside an epoch (with the number of batches done), so a run stopped at any
time loses at most that much work; ``--resume last.pt`` continues from the next batch.

``precision="bf16"`` runs forward and loss under ``torch.autocast(dtype=torch.bfloat16)``: the
Transformer, DGCNN projections and correction walk multiply in bfloat16 (AMX / AVX-512-BF16 on
x86), while the compiled ops, the soft matching, BatchNorm statistics and the Procrustes solve stay
in float32. Weights and optimizer state are float32 either way. ``precision="auto"`` (the default)
takes bf16 only where the device multiplies bfloat16 in hardware; a CPU without it emulates
bfloat16 products several times slower than float32 ones.
"""
from __future__ import annotations

import csv
import io
import json
import os
import signal
import threading
import time
import warnings
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, Dataset
from torch.utils.data.distributed import DistributedSampler
from tqdm import tqdm

from vrnet_ext.model.checkpoints import model_values, read_checkpoint, validate_model_config
from vrnet_ext.names import AUTO_DEVICE
from vrnet_ext.data import ModelNet40Pairs, PairSpec
from vrnet_ext.learning.evaluate import evaluate, to_device
from vrnet_ext.learning.losses import HybridLossWeights, correspondence_loss, hybrid_loss
from vrnet_ext.model import VRNet, VRNetConfig
from vrnet_ext.learning.curves import plot_metrics
from vrnet_ext.runtime import device_has_native_bf16, set_flush_denormal
from vrnet_ext.geometry.atomic import (read_json_lines, remove_leftovers, save_atomically, write_json_lines,
                                      write_text_atomically)
from vrnet_ext.learning.lineage import Lineage, lineage_before
from vrnet_ext.learning.warm_start import init_features_from, init_walk_from
from vrnet_ext.learning.config import TrainConfig

def resolve_device(name: str) -> str:
    """``AUTO_DEVICE`` ("auto"): ``"cuda"`` when a CUDA device is available, else ``"cpu"``; any other
    name as given."""
    if name == AUTO_DEVICE:
        return "cuda" if torch.cuda.is_available() else "cpu"
    return name


class _Run:
    """Distributed context: rank, world size, device."""

    def __init__(self, device: str) -> None:
        self.world = int(os.environ.get("WORLD_SIZE", "1"))
        self.rank = int(os.environ.get("RANK", "0"))
        local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        device = resolve_device(device)
        self.device = torch.device(f"cuda:{local_rank}" if device == "cuda" and self.world > 1 else device)
        if self.device.type == "cuda":
            torch.cuda.set_device(self.device)
        self.owns_group = self.world > 1 and not dist.is_initialized()
        if self.owns_group:
            dist.init_process_group("nccl" if self.device.type == "cuda" else "gloo")

    @property
    def main(self) -> bool:
        return self.rank == 0

    def barrier(self) -> None:
        if self.world > 1:
            dist.barrier()

    def close(self) -> None:
        """Ends the process group this run started: its communication threads must stop before the
        process exits (left running, a rank can abort at exit)."""
        if self.owns_group and dist.is_initialized():
            dist.destroy_process_group()


def _datasets(cfg: TrainConfig):
    data = cfg.data
    spec = dict(num_points=data.num_points, num_subsampled=data.num_subsampled, far_points=data.far_points,
                rotation_range=data.rotation_range)
    common = dict(root=data.data_dir, setting=data.setting, split=data.split, val_fraction=data.val_fraction,
                  classes=data.classes)
    # Validation pairs are the dataset's fixed ones: runs of different seeds are selected on the same pairs.
    train = ModelNet40Pairs(partition="train", max_items=data.max_train_items,
                            spec=PairSpec(**spec, max_angle_deg=data.train_max_angle), seed=data.seed, **common)
    val = ModelNet40Pairs(partition="val", max_items=data.max_val_items, spec=PairSpec(**spec), **common)
    return train, val


def _stage_modules(model: VRNet, stage: int, freeze_confidence: bool,
                   train_features: bool = False) -> tuple[list, list, list]:
    """(trainable, fine-tuned, frozen) modules of a stage: stage 1 trains the feature extractor;
    stage 2 the walk (without its confidence MLP when ``freeze_confidence``), and fine-tunes the
    feature extractor when ``train_features`` (frozen otherwise)."""
    walk = [model.walk] if model.walk is not None else []
    if stage == 1:
        return model.feature_modules(), [], walk
    features = model.feature_modules()
    trainable, frozen = (([model.walk.net], [model.walk.confidence_net]) if freeze_confidence else (walk, []))
    return (trainable, features, frozen) if train_features else (trainable, [], frozen + features)


def set_stage(model: VRNet, stage: int, freeze_confidence: bool = False,
              features_lr: float = 0.0) -> list[dict]:
    """The optimizer's parameter groups of a stage: its trainable modules (at the optimizer's own
    rate), then in stage 2 with ``features_lr`` > 0 the feature extractor at that rate. Frozen
    modules are put in eval mode by :func:`stage_train_mode`."""
    trainable, fine_tuned, frozen = _stage_modules(model, stage, freeze_confidence, features_lr > 0)
    for module in frozen:
        module.requires_grad_(False)
    for module in trainable + fine_tuned:
        module.requires_grad_(True)
    groups = [{"params": [p for m in trainable for p in m.parameters()]}]
    if fine_tuned:
        groups.append({"params": [p for m in fine_tuned for p in m.parameters()], "lr": features_lr})
    return groups


def stage_train_mode(model: VRNet, stage: int, freeze_confidence: bool = False, features_lr: float = 0.0) -> None:
    """Train mode for the modules a stage trains; in stage 2 the frozen modules and a fine-tuned
    feature extractor run in eval mode: their BatchNorm layers normalise with (and keep) the running
    statistics the walk is trained and served on."""
    model.train()
    if stage == 2:
        _, fine_tuned, frozen = _stage_modules(model, stage, freeze_confidence, features_lr > 0)
        for module in fine_tuned + frozen:
            module.eval()


def _checkpoint(setup: "_Setup", stage: "_Stage", epoch: int, progress: "_Progress",
                partial: dict | None = None) -> dict:
    """What ``last.pt`` and the best models hold. ``epoch``: the last completed epoch of ``stage``;
    the stage's ``best``: its selection score so far (val L0 in stage 1, val RMSE(R) in stage 2);
    the progress's ``best_rmse``: the lowest val RMSE(R) of the whole run (selects best.pt across
    stages), ``train_seconds``: wall time spent in training and validation epochs so far, over all
    sessions; the setup's ``lineage``: the chain of warm starts before this run
    (:class:`vrnet_ext.learning.lineage.Lineage`); ``partial``: ``{"epoch", "batches", "totals"}`` of
    an epoch in progress (mid-epoch checkpoints only)."""
    return {"model": setup.model.state_dict(), "optimizer": stage.optimizer.state_dict(),
            "scheduler": stage.scheduler.state_dict(), "config": json.loads(json.dumps(setup.cfg.to_dict())),
            "stage": stage.number, "epoch": epoch, "step": progress.step, "best": stage.best,
            "best_rmse": progress.best_rmse, "train_seconds": progress.train_seconds,
            "lineage": setup.lineage.to_dict(), "partial": partial}


def _save(checkpoint: dict, path: Path) -> None:
    """Writes ``path`` atomically (a run stopped mid-write leaves the previous file intact)."""
    save_atomically(checkpoint, path)


def _run_lineage(cfg: TrainConfig, state: dict | None) -> Lineage:
    """The chain of warm starts before this run: as recorded in the checkpoint resumed from, else
    read from ``--features-from`` (else ``--walk-from``) now."""
    if state is not None and "lineage" in state:
        return Lineage.from_dict(state["lineage"], cfg.start.resume)
    return lineage_before(cfg.start.features_from or cfg.start.walk_from, "features_from / walk_from")


def _resolved_precision(precision: str, device: torch.device, state: dict | None) -> str:
    """The autocast precision a run trains in, ``"bf16"`` or ``"fp32"``: ``"auto"`` keeps what the
    resumed checkpoint's run trained in (so ``--resume`` continues bit-exactly), else takes bf16
    where ``device`` multiplies bfloat16 in hardware and fp32 elsewhere. An explicit bf16 on a CPU
    that only emulates it is kept, with a warning (it runs several times slower than fp32)."""
    if precision == "auto":
        saved = state["config"].get("precision") if state is not None else None
        if saved in ("bf16", "fp32"):
            return saved
        return "bf16" if device_has_native_bf16(device) else "fp32"
    if precision == "bf16" and device.type == "cpu" and not device_has_native_bf16(device):
        warnings.warn("precision bf16: this CPU has no bfloat16 matrix products (AVX512-BF16 / AMX); bfloat16 "
                      "autocast is emulated and several times slower than fp32 (--precision auto picks fp32 here)")
    return precision


def _check_resumable(state: dict, model_cfg: VRNetConfig, path: str) -> None:
    """A run resumes only the model it was training (the file's config, not silently this run's),
    from a training checkpoint (not shipped weights or a scene model)."""
    if "step" not in state or "optimizer" not in state or not isinstance(state["config"].get("model"), dict):
        raise ValueError(f"resume: {path} is not a checkpoint of `vrnet train` (shipped weights and scene models "
                         f"hold no training state; start a run from one with features_from / walk_from)")
    saved = validate_model_config(model_values(state["config"], path), path).to_dict()
    wanted = model_cfg.to_dict()
    saved["backend"] = wanted["backend"]  # the kernels used do not change the model
    differing = sorted(k for k in wanted if saved.get(k) != wanted[k])
    if differing:
        raise ValueError(f"resume: {path} holds a model with other {', '.join(differing)} "
                         f"({', '.join(f'{k}={saved.get(k)!r}' for k in differing)}) than this run "
                         f"({', '.join(f'{k}={wanted[k]!r}' for k in differing)}); pass the same preset and options")


class _StopRequest:
    """SIGINT / SIGTERM (Ctrl-C, ``kill``, a scheduler's stop) ask for a stop after the current
    batch instead of killing the run: it then writes a mid-epoch ``last.pt`` and returns, and
    ``--resume last.pt`` continues with the next batch. Single-process runs only (``torchrun``
    handles the signals of DDP workers itself)."""

    def __init__(self, enabled: bool) -> None:
        self.requested = False
        self.signal = 0
        self._previous = {}
        if enabled and threading.current_thread() is threading.main_thread():
            for number in (signal.SIGINT, signal.SIGTERM):
                self._previous[number] = signal.signal(number, self._request)

    def _request(self, number, frame) -> None:
        self.requested = True
        self.signal = number

    def restore(self) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)


OUTPUTS = ("last.pt", "best.pt", "best_stage1.pt", "best_stage2.pt", "metrics.jsonl", "metrics.csv")


def _write_metrics(out_dir: Path, records: list[dict]) -> None:
    """metrics.jsonl and metrics.csv (over the union of the records' keys), each written atomically."""
    write_json_lines(out_dir / "metrics.jsonl", records)
    columns = list(dict.fromkeys(key for r in records for key in r))
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(records)
    write_text_atomically(out_dir / "metrics.csv", text.getvalue())


def _log(out_dir: Path, record: dict) -> None:
    """Adds the epoch's row to the metrics files."""
    _write_metrics(out_dir, read_json_lines(out_dir / "metrics.jsonl") + [record])


def _tidy(out_dir: Path, state: dict | None) -> None:
    """Before a run writes: the temporary files a killed run's writers left in ``out_dir`` go, and
    the metrics keep only the rows up to the epoch it resumes after (rows written before a kill
    stopped ``last.pt`` are done again; a run that does not resume starts its own metrics)."""
    for name in OUTPUTS:
        remove_leftovers(out_dir / name)
    if (out_dir / "metrics.jsonl").exists():
        done = (state["stage"], state["epoch"] + 1) if state is not None else (0, 0)
        rows = read_json_lines(out_dir / "metrics.jsonl")
        _write_metrics(out_dir, [row for row in rows if (row.get("stage", 0), row.get("epoch", 0)) <= done])


def _replica_spread(model: VRNet, run: _Run) -> float:
    """Max |difference| between this rank's weights and any other rank's (0 when identical)."""
    if run.world == 1:
        return 0.0
    flat = torch.cat([p.detach().flatten().cpu().double() for p in model.parameters()])
    gathered = [torch.empty_like(flat) for _ in range(run.world)]
    dist.all_gather(gathered, flat)
    return float(max((g - flat).abs().max() for g in gathered))


def train(cfg: TrainConfig, datasets: tuple[Dataset, Dataset] | None = None) -> dict:
    """Trains per ``cfg``; returns the last epoch's record (rank 0 writes files).

    ``datasets``: (training, validation) pair providers to use instead of ModelNet40 per ``cfg``: any
    map-style datasets whose items hold the protocol's fields (``src`` (N, 3), ``tgt`` (M, 3),
    ``rotation`` (3, 3), ``translation`` (3,), ``gt_idx`` (N,): :func:`vrnet_ext.data.make_pair`);
    a ``set_epoch(epoch)`` method, when present, is called before each epoch.
    """
    run = _Run(cfg.runtime.device)
    if cfg.runtime.flush_denormal:
        set_flush_denormal(True)
    state = read_checkpoint(cfg.start.resume, run.device) if cfg.start.resume else None
    cfg = replace(cfg, runtime=replace(cfg.runtime, precision=_resolved_precision(cfg.runtime.precision, run.device,
                                                                                   state)))
    out_dir = Path(cfg.runtime.out_dir)
    if run.main:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "config.json").write_text(json.dumps(cfg.to_dict(), indent=1))
        _tidy(out_dir, state)
    torch.manual_seed(cfg.data.seed)
    model_cfg = VRNetConfig.from_dict(dict(model_values(cfg.to_dict()), backend=cfg.runtime.backend))
    model = VRNet(model_cfg).to(run.device)
    train_set, val_set = datasets if datasets is not None else _datasets(cfg)
    sampler = DistributedSampler(train_set, num_replicas=run.world, rank=run.rank, shuffle=True, seed=cfg.data.seed,
                                 drop_last=True)
    if len(sampler) < cfg.schedule.batch_size:
        raise ValueError(f"batch_size {cfg.schedule.batch_size} x {run.world} process(es) exceeds the "
                         f"{len(train_set)} training pairs")
    if cfg.start.features_from and not cfg.start.resume:
        init_features_from(model, cfg.start.features_from)
    if cfg.start.walk_from and not cfg.start.resume:
        init_walk_from(model, cfg.start.walk_from)
    if state is not None:
        _check_resumable(state, model_cfg, cfg.start.resume)
        model.load_state_dict(state["model"])
    loss_weights = HybridLossWeights(l4=cfg.loss.loss_l4, l4_form=cfg.loss.loss_l4_form, motion=cfg.loss.loss_motion,
                                     motion_translation=cfg.loss.loss_motion_translation)
    progress = _Progress()
    if state:
        progress = _Progress(state["step"], state.get("best_rmse", float("inf")), state.get("train_seconds", 0.0))
    autocast = torch.autocast(run.device.type, dtype=torch.bfloat16, enabled=cfg.runtime.precision == "bf16")
    stop = _StopRequest(enabled=run.world == 1)
    setup = _Setup(cfg, run, model, train_set, val_set, sampler, loss_weights, autocast, stop, out_dir,
                   _run_lineage(cfg, state))
    try:
        return _train_stages(setup, state, progress)
    finally:
        stop.restore()
        run.close()


@dataclass
class _Setup:
    """What :func:`train` prepares for its loops: the options, the process group, the model, the data
    and the loss, the precision, the stop request, the output folder and the chain of warm starts
    before the run."""

    cfg: TrainConfig
    run: _Run
    model: VRNet
    train_set: Dataset
    val_set: Dataset
    sampler: DistributedSampler
    loss_weights: HybridLossWeights
    autocast: torch.autocast
    stop: _StopRequest
    out_dir: Path
    lineage: Lineage


@dataclass
class _Progress:
    """What the loops advance and checkpoint: optimiser steps, the best validation RMSE(R) so far and
    the training time."""

    step: int = 0
    best_rmse: float = float("inf")
    train_seconds: float = 0.0


@dataclass
class _Stage:
    """One stage's optimiser, schedule and selection score, and where it starts: ``first_epoch``
    (0 unless resumed), ``partial`` (a resumed epoch's batches done and loss totals, or None)."""

    number: int
    epochs: int
    features_lr: float
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.MultiStepLR
    first_epoch: int = 0
    best: float = float("inf")
    partial: dict | None = None


def _train_stages(setup: _Setup, state: dict | None, progress: _Progress) -> dict:
    """The stage and epoch loops of :func:`train` (``state``: the checkpoint resumed from, or None)."""
    run = setup.run
    record: dict = {}
    for number in (1, 2):
        stage = _start_stage(setup, number, state)
        if stage is None:
            continue  # this stage is already complete in the checkpoint
        state = None  # resumed: later stages start afresh
        wrapped = DistributedDataParallel(setup.model) if run.world > 1 else setup.model
        for epoch in range(stage.first_epoch, stage.epochs):
            done = _train_epoch(setup, stage, epoch, wrapped, progress)
            if done.get("stopped"):
                return done
            record = _end_epoch(setup, stage, epoch, done, progress)
            run.barrier()
    if run.main and record:
        plot_metrics(setup.out_dir)
    return record


def _start_stage(setup: _Setup, number: int, state: dict | None) -> _Stage | None:
    """Stage ``number``'s trainable parameters, optimiser and schedule, resumed from ``state`` when it
    holds this stage; None when ``state`` holds this stage complete or a later one."""
    cfg, schedule = setup.cfg, setup.cfg.schedule
    epochs, lr = ((schedule.stage1_epochs, schedule.lr_stage1) if number == 1
                  else (schedule.stage2_epochs, schedule.lr_stage2))
    if state is not None and (state["stage"] > number or (state["stage"] == number and state["epoch"] + 1 >= epochs)):
        return None
    features_lr = schedule.lr_features_stage2 if number == 2 else 0.0
    groups = set_stage(setup.model, number, cfg.start.freeze_confidence, features_lr)
    optimizer = torch.optim.Adam(groups, lr=lr, weight_decay=schedule.weight_decay)
    stage = _Stage(number, epochs, features_lr, optimizer,
                   torch.optim.lr_scheduler.MultiStepLR(optimizer, schedule.lr_milestones, schedule.lr_gamma))
    if state is not None and state["stage"] == number:
        if len(state["optimizer"]["param_groups"]) != len(groups):
            saved = state["config"].get("lr_features_stage2", 0.0)
            raise ValueError(f"resume: {cfg.start.resume} was trained with lr_features_stage2 {saved}, this run "
                             f"with {schedule.lr_features_stage2}: pass the same value (zero or not) to continue "
                             f"it")
        optimizer.load_state_dict(state["optimizer"])
        stage.scheduler.load_state_dict(state["scheduler"])
        # This run's schedule, not the saved one: extending a run (a larger --stage2-epochs)
        # may add a milestone after the epochs already done.
        stage.scheduler.milestones, stage.scheduler.gamma = Counter(cfg.schedule.lr_milestones), cfg.schedule.lr_gamma
        stage.first_epoch, stage.best, stage.partial = state["epoch"] + 1, state["best"], state.get("partial")
    return stage


def _train_epoch(setup: _Setup, stage: _Stage, epoch: int, wrapped, progress: _Progress) -> dict:
    """One epoch's batches (after those a resumed mid-epoch checkpoint did), with a mid-epoch
    ``last.pt`` every ``checkpoint_minutes`` and on a stop request -> ``{"totals", "batches",
    "epoch_started", "started"}``, or the record of a stopped run (``"stopped": True``)."""
    cfg, run, model = setup.cfg, setup.run, setup.model
    global_epoch = epoch if stage.number == 1 else cfg.schedule.stage1_epochs + epoch
    if hasattr(setup.train_set, "set_epoch"):
        setup.train_set.set_epoch(global_epoch)
    setup.sampler.set_epoch(global_epoch)
    stage_train_mode(model, stage.number, cfg.start.freeze_confidence, stage.features_lr)
    epoch_started = started = saved_at = time.time()
    totals, batches = {}, 0
    if stage.partial is not None and stage.partial["epoch"] == epoch:
        totals, batches = dict(stage.partial["totals"]), stage.partial["batches"]
    stage.partial = None
    indices = list(setup.sampler)[batches * cfg.schedule.batch_size:]  # the same order as before the checkpoint
    loader = DataLoader(setup.train_set, batch_size=cfg.schedule.batch_size, sampler=indices,
                        num_workers=cfg.runtime.num_workers, drop_last=True)
    bar = tqdm(loader, desc=f"stage {stage.number} epoch {epoch + 1}/{stage.epochs}", initial=batches,
               total=batches + len(loader), disable=not (cfg.runtime.progress and run.main))
    for batch in bar:
        parts = _step(setup, stage.number, stage.optimizer, to_device(batch, run.device), wrapped, progress)
        batches += 1
        for k, v in parts.items():
            totals[k] = totals.get(k, 0.0) + v
        bar.set_postfix(loss=f"{parts['loss']:.4f}")
        if run.main and (setup.stop.requested or time.time() - saved_at > 60 * cfg.runtime.checkpoint_minutes):
            now = time.time()
            progress.train_seconds += now - started
            started = saved_at = now
            partial = {"epoch": epoch, "batches": batches, "totals": dict(totals)}
            _save(_checkpoint(setup, stage, epoch - 1, progress, partial), setup.out_dir / "last.pt")
        if setup.stop.requested:
            bar.close()
            print(f"vrnet train: stopped at stage {stage.number}, epoch {epoch + 1}, batch {batches}; "
                  f"continue with --resume {setup.out_dir / 'last.pt'}", flush=True)
            return {"stage": stage.number, "epoch": epoch + 1, "step": progress.step, "stopped": True,
                    "signal": setup.stop.signal}
    return {"totals": totals, "batches": batches, "epoch_started": epoch_started, "started": started}


def _step(setup: _Setup, stage: int, optimizer: torch.optim.Optimizer, batch: dict, wrapped,
          progress: _Progress) -> dict[str, float]:
    """One optimiser step of ``stage`` on ``batch`` -> the loss and its parts."""
    cfg = setup.cfg
    with setup.autocast:
        out = wrapped(batch["src"], batch["tgt"], return_matching=stage == 1)
        if stage == 1:
            loss = correspondence_loss(out.matching, batch["gt_idx"])
            parts = {"L0": float(loss.detach())}
        else:
            generator = torch.Generator().manual_seed(cfg.data.seed * 1_000_003 + progress.step)
            loss, parts = hybrid_loss(out, batch["src"], batch["rotation"], batch["translation"],
                                      setup.loss_weights, generator=generator, backend=cfg.runtime.backend)
    if not torch.isfinite(loss):
        raise FloatingPointError(f"non-finite loss at stage {stage}, step {progress.step}: {parts}")
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    progress.step += 1
    return dict(parts, loss=float(loss.detach()))


def _end_epoch(setup: _Setup, stage: _Stage, epoch: int, done: dict, progress: _Progress) -> dict:
    """The epoch's record: the learning rate, the mean losses and (rank 0) the validation pass; then
    the files, ``last.pt`` last: the best models and the metrics row come first, so that a run killed
    between them resumes from the previous ``last.pt``, redoes the epoch and writes them again (a
    resume drops the rows after its checkpoint: :func:`_tidy`)."""
    cfg, run, model, out_dir = setup.cfg, setup.run, setup.model, setup.out_dir
    epoch_lr = stage.optimizer.param_groups[0]["lr"]
    stage.scheduler.step()
    record = {"stage": stage.number, "epoch": epoch + 1, "step": progress.step, "lr": epoch_lr,
              "epoch_seconds": round(time.time() - done["epoch_started"], 2), "world_size": run.world}
    record.update({f"train_{k}": v / max(done["batches"], 1) for k, v in done["totals"].items()})
    record["replica_max_abs_diff"] = _replica_spread(model, run)
    if not run.main:
        return record
    val = evaluate(model, setup.val_set, batch_size=cfg.schedule.batch_size, device=run.device,
                   progress=cfg.runtime.progress, use_rcp=stage.number == 2)
    record.update({f"val_{k}": v for k, v in val.items()})
    score = val["L0"] if stage.number == 1 else val["RMSE(R)"]
    improved, improved_rmse = score < stage.best, val["RMSE(R)"] < progress.best_rmse
    stage.best, progress.best_rmse = min(stage.best, score), min(progress.best_rmse, val["RMSE(R)"])
    progress.train_seconds += time.time() - done["started"]
    record["train_seconds"] = round(progress.train_seconds, 1)
    checkpoint = _checkpoint(setup, stage, epoch, progress)
    if improved:
        _save(checkpoint, out_dir / f"best_stage{stage.number}.pt")
    if improved_rmse:
        _save(checkpoint, out_dir / "best.pt")
    _log(out_dir, record)
    _save(checkpoint, out_dir / "last.pt")
    return record
