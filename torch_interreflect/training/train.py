"""``interreflect train-cc``: colour constancy on generated data, with and without interreflection.

The recipe (:func:`run_train_cc`):

1. make sure the data exist (``interreflect generate`` with the run's ``--count``, ``--seed``, ``--size``;
   skipped when the folder is complete; under ``torchrun`` every rank generates its own shard);
2. split the indices: the last ``--test-fraction`` are held-out scenes (every index is its own random scene);
3. evaluate Grey-World, White-Patch and Grey-Edge on the held-out ∞-bounce images;
4. train the FC4-style CNN (:class:`~.models.FC4Net`) on direct-only images (``_b1``), on 2-bounce images
   (``_b2``; each when the data has them), and on ∞-bounce images; train the physics-informed model
   (:class:`~.models.PhysicsInformedNet`, angular + reconstruction loss through the interreflection solve) on
   ∞-bounce images with their geometry;
5. test all of them on the held-out ∞-bounce images and write one table (``results.md``, ``results.json``) and the
   checkpoints (:func:`~.estimator.save_estimator`: configuration, library version and weights; load them with
   :func:`~.estimator.load_estimator`) to ``--out``.

Distributed: run the same command under ``torchrun --nproc-per-node N -m torch_interreflect.cli train-cc …``;
the script reads ``RANK`` / ``WORLD_SIZE`` (set by torchrun, SLURM wrappers, ...), joins a ``gloo`` process group
(CPU; ``nccl`` when CUDA is used), wraps the models in ``DistributedDataParallel`` and shards the training set with a
``DistributedSampler``. Evaluation and writing happen on rank 0.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset

from .._deprecation import moved_attribute
from ..errors import AccuracyWarning, collect_warnings
from .baselines import BASELINES
from .datasets import GeneratedDataset, collate, split_indices
from .estimator import make_network, save_estimator
from .generator import GeneratorConfig, generate, is_complete, read_config
from .metrics import angular_error, format_table, summarize
from .models import physics_loss

__all__ = ["WEIGHT_FILES", "TrainConfig", "evaluate", "run_train_cc", "train_model"]

_MOVED = {name: "torch_interreflect.training.commands" for name in ("add_train_parser", "main_train")}


def __getattr__(name: str) -> object:
    return moved_attribute(__name__, name, _MOVED)


#: What :func:`run_train_cc` writes to its ``out`` folder (refused when present, unless ``overwrite``).
WEIGHT_FILES = ("fc4_direct.pt", "fc4_b2.pt", "fc4_inf.pt", "physics.pt", "results.md", "results.json")


@dataclasses.dataclass
class TrainConfig:
    """Configuration of :func:`run_train_cc` (defaults: the ≤ 10-minute CPU run).

    Attributes:
        data: Folder of generated data (generated there when incomplete).
        out: Folder for results and weights (default ``<data>/train-cc``).
        count: Samples to use (a folder with fewer is grown to this many; samples do not depend on the count).
        seed: Generator seed of new data (existing data keep theirs), and the seed of the training.
        size: Image ``(height, width)``; ``None``: the existing data's size, or 64 × 64 for new data. A size that
            differs from the existing data's is an error (the images would not be what was asked for).
        test_fraction: Fraction of the indices held out (the last ones).
        epochs: Epochs of each CNN.
        physics_epochs: Epochs of the physics-informed model (each step solves one interreflection per image).
        batch_size: Batch size per process.
        lr: Adam learning rate (cosine-decayed to 5 % of it).
        width: Backbone width of the networks.
        reconstruction_weight: Weight of the reconstruction term of the physics-informed loss.
        threads: Torch threads of this process (default 1: the tensors are small, and intra-op threads that spin on
            a busy machine cost more than they bring; scale out with processes, ``torchrun``). ``None``: torch's
            choice.
        progress: Show progress bars.
        overwrite: Replace results and weights already in ``out`` (otherwise their presence is an error, raised
            before anything is generated or trained).

    Raises:
        ValueError: a field out of range (the message names it).
    """

    data: str = "out/cc-data"
    out: str | None = None
    count: int = 500
    seed: int = 0
    size: tuple[int, int] | None = None
    test_fraction: float = 0.2
    epochs: int = 100
    physics_epochs: int = 30
    batch_size: int = 16
    lr: float = 3e-3
    width: int = 16
    reconstruction_weight: float = 10.0
    threads: int | None = 1
    progress: bool = True
    overwrite: bool = False

    def __post_init__(self) -> None:
        checks = {"count": (self.count, 2), "epochs": (self.epochs, 0), "physics_epochs": (self.physics_epochs, 0),
                  "batch_size": (self.batch_size, 1), "width": (self.width, 1)}
        for name, (v, low) in checks.items():
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ValueError(f"{name} must be an integer >= {low}; got {v!r}")
        if self.size is not None:
            self.size = tuple(int(v) for v in self.size)  # type: ignore[assignment]
            if len(self.size) != 2 or min(self.size) < 1:
                raise ValueError(f"size must be two positive integers (height, width); got {self.size!r}")
        if not 0.0 < self.test_fraction < 1.0:
            raise ValueError(f"test_fraction must lie in (0, 1); got {self.test_fraction!r}")
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise ValueError(f"lr must be a finite number > 0; got {self.lr!r}")

    @property
    def out_dir(self) -> Path:
        """Where results and weights go: ``out``, or ``<data>/train-cc``."""
        return Path(self.out) if self.out else Path(self.data) / "train-cc"


# ------------------------------------------------------------------------------------------------ distributed
@dataclasses.dataclass
class _Dist:
    rank: int = 0
    world: int = 1
    started_here: bool = False

    @property
    def main(self) -> bool:
        return self.rank == 0

    def barrier(self) -> None:
        if self.world > 1:
            torch.distributed.barrier()


def _init_distributed() -> _Dist:
    """Join a process group when ``WORLD_SIZE > 1`` (torchrun, SLURM with the env vars set)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    if world <= 1:
        return _Dist()
    import torch.distributed as dist

    if dist.is_initialized():
        return _Dist(dist.get_rank(), dist.get_world_size(), False)
    os.environ.setdefault("MASTER_ADDR", "127.0.0.1")
    os.environ.setdefault("MASTER_PORT", "29500")
    dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo", rank=rank, world_size=world)
    return _Dist(rank, world, True)


# ------------------------------------------------------------------------------------------------ data
class _InMemory(Dataset):
    """Loads every item of a dataset once (the default data are a few tens of MB)."""

    def __init__(self, ds: Dataset) -> None:
        self.items = [ds[k] for k in range(len(ds))]  # type: ignore[arg-type]

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, k: int) -> dict[str, Any]:
        return self.items[k]


def _check_out(cfg: TrainConfig) -> None:
    present = [n for n in WEIGHT_FILES if (cfg.out_dir / n).exists()]
    if present and not cfg.overwrite:
        raise FileExistsError(
            f"{cfg.out_dir} already holds {', '.join(present)} from an earlier run; pass --overwrite to replace "
            "them, or --out to write elsewhere"
        )


def _data_config(cfg: TrainConfig) -> GeneratorConfig:
    """The generator config to use: the folder's (grown to ``cfg.count``), or a new one; checks the size."""
    old = read_config(cfg.data)
    if old is None:
        return GeneratorConfig(count=cfg.count, seed=cfg.seed, size=cfg.size or (64, 64))
    if cfg.size is not None and tuple(cfg.size) != old.size:
        h, w = old.size
        raise ValueError(f"{cfg.data} holds {h}x{w} images but --size is {cfg.size[0]}x{cfg.size[1]}; drop --size "
                         f"(or pass --size {h}x{w}) to use these data, or use another --data folder")
    return dataclasses.replace(old, count=max(old.count, cfg.count))


def _ensure_data(cfg: TrainConfig, dist: _Dist) -> GeneratorConfig:
    gen = _data_config(cfg)
    if not all(is_complete(cfg.data, i) for i in range(cfg.count)):
        # one process: render on every core (generate's workers); under DDP the ranks already share the work
        generate(cfg.data, gen, shard=(dist.rank, dist.world), progress=cfg.progress and dist.main,
                 workers="auto" if dist.world == 1 else 1)
    dist.barrier()
    return gen


# ------------------------------------------------------------------------------------------------ training
def train_model(
    model: nn.Module,
    dataset: Dataset,
    loss_fn: Callable[[nn.Module, dict[str, Any]], tuple[Tensor, dict[str, float]]],
    *,
    epochs: int,
    batch_size: int,
    lr: float,
    seed: int = 0,
    dist: _Dist | None = None,
    progress: bool = True,
    desc: str = "train",
) -> list[dict[str, float]]:
    """Train ``model`` with Adam and a cosine schedule; DistributedDataParallel when a process group is up.

    Args:
        model: The network.
        dataset: Items as :func:`~.datasets.collate` batches them.
        loss_fn: ``(model, batch) → (loss, logs)``.
        epochs: Passes over the (local shard of the) data.
        batch_size: Per-process batch size.
        lr: Initial learning rate.
        seed: Seed of the shuffling.
        dist: Distributed context (default: single process).
        progress: Show a tqdm bar (rank 0).
        desc: Bar label.

    Returns:
        Per epoch, the mean of each logged value (this process's shard).
    """
    from tqdm.auto import tqdm

    dist = dist or _Dist()
    sampler = None
    if dist.world > 1:
        from torch.nn.parallel import DistributedDataParallel
        from torch.utils.data.distributed import DistributedSampler

        sampler = DistributedSampler(dataset, num_replicas=dist.world, rank=dist.rank, shuffle=True, seed=seed)  # type: ignore[arg-type]
        model = DistributedDataParallel(model)
    gen = torch.Generator().manual_seed(seed)
    loader = DataLoader(
        dataset, batch_size=batch_size, shuffle=sampler is None, sampler=sampler, collate_fn=collate,
        generator=gen if sampler is None else None, drop_last=len(dataset) > batch_size,  # type: ignore[arg-type]
    )
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    steps = max(1, epochs * len(loader))
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * s / steps)))
    history: list[dict[str, float]] = []
    flush = torch.set_flush_denormal(True)  # subnormal floats make CPU convolutions several times slower
    bar = tqdm(range(epochs), desc=desc, unit="epoch", disable=not (progress and dist.main))
    model.train()
    warned, last = 0, ""
    for epoch in bar:
        if sampler is not None:
            sampler.set_epoch(epoch)
        sums: dict[str, float] = {}
        n = 0
        for batch in loader:
            with collect_warnings(AccuracyWarning) as got:  # a re-render's solves: one summary after training
                loss, logs = loss_fn(model, batch)
            warned, last = warned + len(got), (got[-1] if got else last)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            for k, v in {"loss": float(loss.detach()), **logs}.items():
                sums[k] = sums.get(k, 0.0) + v
            n += 1
        history.append({k: v / max(n, 1) for k, v in sums.items()})
        bar.set_postfix({k: f"{v:.3g}" for k, v in history[-1].items()})
    model.eval()
    if flush:
        torch.set_flush_denormal(False)
    if warned:
        warnings.warn(f"{desc}: {warned} of the training's solves warned (the last: {last})",
                      AccuracyWarning, stacklevel=2)
    return history


def _cnn_loss(model: nn.Module, batch: dict[str, Any]) -> tuple[Tensor, dict[str, float]]:
    ang = angular_error(model(batch["image"]), batch["illuminant"]).mean()
    return ang, {"angular": float(ang.detach())}


def _physics_loss(weight: float) -> Callable[[nn.Module, dict[str, Any]], tuple[Tensor, dict[str, float]]]:
    def fn(model: nn.Module, batch: dict[str, Any]) -> tuple[Tensor, dict[str, float]]:
        return physics_loss(model, model(batch["image"]), batch, weight=weight)

    return fn


@torch.no_grad()
def evaluate(estimator: Callable[[Tensor, Tensor], Tensor], dataset: Dataset, batch_size: int = 64) -> Tensor:
    """Angular errors (degrees, ``[N]``) of ``estimator(image [B, 3, H, W], mask [B, H, W]) → rgb [B, 3]``."""
    errs = []
    for batch in DataLoader(dataset, batch_size=batch_size, collate_fn=collate):  # type: ignore[arg-type]
        est = estimator(batch["image"], batch["mask"])
        errs.append(angular_error(est.float(), batch["illuminant"]))
    return torch.cat(errs)


def _net_estimator(model: nn.Module) -> Callable[[Tensor, Tensor], Tensor]:
    def fn(image: Tensor, mask: Tensor) -> Tensor:
        out = model(image)
        return out["rgb"] if isinstance(out, dict) else out

    return fn


def _runs(cfg: TrainConfig, gen: GeneratorConfig) -> list[tuple[str, str, dict[str, Any], Any, int]]:
    """``(label, key, network config, variant, epochs)`` of each model to train (:func:`~.estimator.make_network`)."""
    common = {"width": cfg.width, "camera": gen.camera, "wavelengths": list(gen.wavelengths), "percentile": 99.0}
    fc4 = {"kind": "fc4", **common}
    runs: list[tuple[str, str, dict[str, Any], Any, int]] = []
    if 1 in gen.bounces:
        runs.append(("FC4-style CNN, trained on direct-only", "fc4_direct", {**fc4, "trained_on": "direct-only"}, 1,
                     cfg.epochs))
    if 2 in gen.bounces:
        runs.append(("FC4-style CNN, trained on 2-bounce", "fc4_b2", {**fc4, "trained_on": "2-bounce"}, 2, cfg.epochs))
    runs.append(("FC4-style CNN, trained on ∞-bounce", "fc4_inf", {**fc4, "trained_on": "inf"}, None, cfg.epochs))
    if gen.geometry and cfg.physics_epochs > 0:
        phys = {"kind": "physics", **common, "illuminant_components": 12, "reflectance_components": 3,
                "trained_on": "inf + re-rendering"}
        runs.append(("Physics-informed (∞-bounce + re-rendering)", "physics", phys, "physics", cfg.physics_epochs))
    return runs


def _train_all(cfg: TrainConfig, gen: GeneratorConfig, dist: _Dist, train_idx: list[int], test: Dataset,
               summaries: dict, seconds: dict) -> dict[str, list[dict[str, float]]]:
    history: dict[str, list[dict[str, float]]] = {}
    out = cfg.out_dir
    for label, key, net_config, variant, epochs in _runs(cfg, gen):
        torch.manual_seed(cfg.seed)  # DistributedDataParallel broadcasts rank 0's initial weights anyway
        model = make_network(net_config)
        physics = variant == "physics"
        local = _InMemory(GeneratedDataset(cfg.data, None if physics else variant, train_idx, geometry=physics))
        t0 = time.perf_counter()
        loss_fn = _physics_loss(cfg.reconstruction_weight) if physics else _cnn_loss
        history[key] = train_model(model, local, loss_fn, epochs=epochs, batch_size=cfg.batch_size, lr=cfg.lr,
                                   seed=cfg.seed, dist=dist, progress=cfg.progress, desc=key)
        seconds[key] = time.perf_counter() - t0
        if dist.main:
            summaries[label] = summarize(evaluate(_net_estimator(model), test))
            out.mkdir(parents=True, exist_ok=True)
            save_estimator(model, {**net_config, "seed": cfg.seed, "generator": gen.to_json()}, out / f"{key}.pt")
        dist.barrier()
    return history


def _write_results(cfg: TrainConfig, gen: GeneratorConfig, dist: _Dist, n: tuple[int, int], summaries: dict,
                   seconds: dict, history: dict) -> str:
    table = format_table(summaries)
    header = (f"Recovery angular error (degrees) on {n[1]} held-out ∞-bounce images "
              f"({gen.size[0]}×{gen.size[1]}, camera {gen.camera}); training on {n[0]} scenes; "
              f"{dist.world} process(es); wall time {seconds['total']:.0f} s.\n\n")
    out = cfg.out_dir
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.md").write_text(header + table + "\n")
    config = {**dataclasses.asdict(cfg), "size": list(gen.size)}
    (out / "results.json").write_text(json.dumps(
        {"config": config, "generator": gen.to_json(), "summaries": summaries, "seconds": seconds,
         "history": history}, indent=1) + "\n")
    return header + table


def run_train_cc(cfg: TrainConfig) -> dict[str, Any]:
    """Generate (if needed), train, evaluate and write the results table (see the module docstring).

    Returns:
        ``{"table": markdown, "summaries": {method: summary}, "seconds": {...}, "history": {...}}`` on rank 0
        (other ranks get the same keys with empty values).

    Raises:
        FileExistsError: results or weights already in the output folder and ``cfg.overwrite`` not set.
        ValueError: ``cfg.size`` differs from the existing data's size, or the data folder holds another
            generator configuration. Both are raised before anything is written.
    """
    t_start = time.perf_counter()
    _check_out(cfg)
    old_threads = torch.get_num_threads()
    if cfg.threads is not None:
        torch.set_num_threads(int(cfg.threads))
    dist = _init_distributed()
    try:
        gen = _ensure_data(cfg, dist)
        seconds: dict[str, float] = {"data": time.perf_counter() - t_start}
        train_idx, test_idx = split_indices(cfg.count, cfg.test_fraction)
        test = _InMemory(GeneratedDataset(cfg.data, None, test_idx))
        summaries: dict[str, dict[str, float]] = {}
        if dist.main:
            for name, fn in BASELINES.items():
                summaries[name] = summarize(evaluate(fn, test))
        history = _train_all(cfg, gen, dist, train_idx, test, summaries, seconds)
        seconds["total"] = time.perf_counter() - t_start
        if not dist.main:
            return {"table": "", "summaries": {}, "seconds": seconds, "history": history}
        table = _write_results(cfg, gen, dist, (len(train_idx), len(test_idx)), summaries, seconds, history)
        return {"table": table, "summaries": summaries, "seconds": seconds, "history": history}
    finally:
        torch.set_num_threads(old_threads)
        if dist.started_here:
            torch.distributed.destroy_process_group()
