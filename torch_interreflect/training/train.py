"""``interreflect train-cc``: colour constancy on generated data, with and without interreflection.

The recipe (:func:`run_train_cc`):

1. make sure the data exist (``interreflect generate`` with the run's ``--count``, ``--seed``, ``--size``;
   skipped when the folder is complete; under ``torchrun`` every rank generates its own shard);
2. split the indices: the last ``--test-fraction`` are held-out scenes (every index is its own random scene);
3. evaluate Grey-World, White-Patch and Grey-Edge on the held-out ∞-bounce images;
4. train the FC4-style CNN (:class:`~.models.FC4Net`) on direct-only images (``_b1``), and again on ∞-bounce
   images; train the physics-informed model (:class:`~.models.PhysicsInformedNet`, angular + reconstruction
   loss through the interreflection solve) on ∞-bounce images with their geometry;
5. test all of them on the held-out ∞-bounce images and write one table (``results.md``, ``results.json``) and the
   model weights to ``--out``.

Distributed: run the same command under ``torchrun --nproc-per-node N``; the script reads ``RANK`` /
``WORLD_SIZE`` (set by torchrun, SLURM wrappers, ...), joins a ``gloo`` process group (CPU; ``nccl`` when CUDA
is used), wraps the models in ``DistributedDataParallel`` and shards the training set with a
``DistributedSampler``. Evaluation and writing happen on rank 0.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset

from .. import spectral
from .baselines import BASELINES
from .datasets import GeneratedDataset, collate, split_indices
from .generator import CONFIG_FILE, GeneratorConfig, generate, is_complete
from .metrics import angular_error, format_table, summarize
from .models import FC4Net, PhysicsInformedNet, physics_loss

__all__ = ["TrainConfig", "add_train_parser", "evaluate", "main_train", "run_train_cc", "train_model"]


@dataclasses.dataclass
class TrainConfig:
    """Configuration of :func:`run_train_cc` (defaults: the ≤ 10-minute CPU run).

    Attributes:
        data: Folder of generated data (generated there when incomplete).
        out: Folder for results and weights (default ``<data>/train-cc``).
        count: Samples to generate / use.
        seed: Generator seed, and the seed of the training.
        size: Image ``(height, width)``.
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
    """

    data: str = "out/cc-data"
    out: str | None = None
    count: int = 500
    seed: int = 0
    size: tuple[int, int] = (64, 64)
    test_fraction: float = 0.2
    epochs: int = 100
    physics_epochs: int = 30
    batch_size: int = 16
    lr: float = 3e-3
    width: int = 16
    reconstruction_weight: float = 10.0
    threads: int | None = 1
    progress: bool = True


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


def _ensure_data(cfg: TrainConfig, dist: _Dist) -> GeneratorConfig:
    root = Path(cfg.data)
    if (root / CONFIG_FILE).is_file():
        gen = GeneratorConfig.from_json(json.loads((root / CONFIG_FILE).read_text())["generator"])
        if gen.count < cfg.count:
            raise ValueError(f"{root} holds a data set of {gen.count} samples but --count is {cfg.count}; use "
                             "another --data folder or a smaller --count")
    else:
        gen = GeneratorConfig(count=cfg.count, seed=cfg.seed, size=tuple(cfg.size))  # type: ignore[arg-type]
    if not all(is_complete(root, i) for i in range(cfg.count)):
        generate(root, gen, shard=(dist.rank, dist.world), progress=cfg.progress and dist.main)
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
    for epoch in bar:
        if sampler is not None:
            sampler.set_epoch(epoch)
        sums: dict[str, float] = {}
        n = 0
        for batch in loader:
            loss, logs = loss_fn(model, batch)
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


def run_train_cc(cfg: TrainConfig) -> dict[str, Any]:
    """Generate (if needed), train, evaluate and write the results table (see the module docstring).

    Returns:
        ``{"table": markdown, "summaries": {method: summary}, "seconds": {...}, "history": {...}}`` on rank 0
        (other ranks get the same keys with empty values).
    """
    t_start = time.perf_counter()
    old_threads = torch.get_num_threads()
    if cfg.threads is not None:
        torch.set_num_threads(int(cfg.threads))
    dist = _init_distributed()
    try:
        gen = _ensure_data(cfg, dist)
        t_data = time.perf_counter() - t_start
        train_idx, test_idx = split_indices(cfg.count, cfg.test_fraction)
        root = cfg.data
        out = Path(cfg.out or Path(cfg.data) / "train-cc")
        test = _InMemory(GeneratedDataset(root, None, test_idx))
        wl = spectral.wavelengths(*gen.wavelengths)
        summaries: dict[str, dict[str, float]] = {}
        seconds: dict[str, float] = {"data": t_data}
        history: dict[str, list[dict[str, float]]] = {}
        if dist.main:
            for name, fn in BASELINES.items():
                summaries[name] = summarize(evaluate(fn, test))

        runs: list[tuple[str, str, Callable[[], nn.Module], Any, int]] = []
        if 1 in gen.bounces:
            runs.append(("FC4-style CNN, trained on direct-only", "fc4_direct", lambda: FC4Net(cfg.width), 1,
                         cfg.epochs))
        runs.append(("FC4-style CNN, trained on ∞-bounce", "fc4_inf", lambda: FC4Net(cfg.width), None, cfg.epochs))
        if gen.geometry and cfg.physics_epochs > 0:
            runs.append(("Physics-informed (∞-bounce + re-rendering)", "physics",
                         lambda: PhysicsInformedNet(wl, gen.camera, width=cfg.width), "physics", cfg.physics_epochs))
        for label, key, make, variant, epochs in runs:
            torch.manual_seed(cfg.seed)  # DistributedDataParallel broadcasts rank 0's initial weights anyway
            model = make()
            physics = variant == "physics"
            ds = GeneratedDataset(root, None if physics else variant, train_idx, geometry=physics)
            t0 = time.perf_counter()
            loss_fn = _physics_loss(cfg.reconstruction_weight) if physics else _cnn_loss
            local = _InMemory(ds)
            history[key] = train_model(model, local, loss_fn, epochs=epochs, batch_size=cfg.batch_size, lr=cfg.lr,
                                       seed=cfg.seed, dist=dist, progress=cfg.progress, desc=key)
            seconds[key] = time.perf_counter() - t0
            if dist.main:
                summaries[label] = summarize(evaluate(_net_estimator(model), test))
                out.mkdir(parents=True, exist_ok=True)
                torch.save(model.state_dict(), out / f"{key}.pt")
            dist.barrier()
        seconds["total"] = time.perf_counter() - t_start
        if not dist.main:
            return {"table": "", "summaries": {}, "seconds": seconds, "history": history}
        table = format_table(summaries)
        n_train, n_test = len(train_idx), len(test_idx)
        header = (f"Recovery angular error (degrees) on {n_test} held-out ∞-bounce images "
                  f"({gen.size[0]}×{gen.size[1]}, camera {gen.camera}); training on {n_train} scenes; "
                  f"{dist.world} process(es); wall time {seconds['total']:.0f} s.\n\n")
        (out / "results.md").write_text(header + table + "\n")
        (out / "results.json").write_text(json.dumps(
            {"config": {**dataclasses.asdict(cfg), "size": list(cfg.size)}, "generator": gen.to_json(),
             "summaries": summaries, "seconds": seconds, "history": history}, indent=1) + "\n")
        return {"table": header + table, "summaries": summaries, "seconds": seconds, "history": history}
    finally:
        torch.set_num_threads(old_threads)
        if dist.started_here:
            torch.distributed.destroy_process_group()


# ------------------------------------------------------------------------------------------------ CLI
def add_train_parser(sub: Any) -> argparse.ArgumentParser:
    """Add the ``train-cc`` sub-command to an ``argparse`` sub-parsers object."""
    from .generator import _size

    d = TrainConfig()
    p = sub.add_parser("train-cc", help="colour constancy on generated data: baselines, CNNs, physics-informed model",
                       description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--data", default=d.data, help=f"generated data folder, created if needed (default {d.data})")
    p.add_argument("--out", default=None, help="results and weights (default <data>/train-cc)")
    p.add_argument("--count", type=int, default=d.count, help=f"samples (default {d.count})")
    p.add_argument("--seed", type=int, default=d.seed, help="seed of the data and the training (default 0)")
    p.add_argument("--size", type=_size, default=d.size, help="image size HxW (default 64x64)")
    p.add_argument("--test-fraction", type=float, default=d.test_fraction, help="held-out fraction (default 0.2)")
    p.add_argument("--epochs", type=int, default=d.epochs, help=f"epochs of each CNN (default {d.epochs})")
    p.add_argument("--physics-epochs", type=int, default=d.physics_epochs,
                   help=f"epochs of the physics-informed model, 0 to skip (default {d.physics_epochs})")
    p.add_argument("--batch-size", type=int, default=d.batch_size, help=f"per process (default {d.batch_size})")
    p.add_argument("--lr", type=float, default=d.lr, help=f"Adam learning rate (default {d.lr})")
    p.add_argument("--width", type=int, default=d.width, help=f"network width (default {d.width})")
    p.add_argument("--reconstruction-weight", type=float, default=d.reconstruction_weight,
                   help=f"weight of the re-rendering loss (default {d.reconstruction_weight})")
    p.add_argument("--threads", type=int, default=d.threads,
                   help="torch threads per process (default 1; 0 = torch's choice)")
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    p.set_defaults(func=_run_train)
    return p


def _run_train(args: argparse.Namespace) -> int:
    cfg = TrainConfig(
        data=args.data, out=args.out, count=args.count, seed=args.seed, size=args.size,
        test_fraction=args.test_fraction, epochs=args.epochs, physics_epochs=args.physics_epochs,
        batch_size=args.batch_size, lr=args.lr, width=args.width, reconstruction_weight=args.reconstruction_weight,
        threads=args.threads or None, progress=not args.no_progress,
    )
    res = run_train_cc(cfg)
    if res["table"]:
        print(res["table"])
        print("\nSeconds: " + ", ".join(f"{k} {v:.0f}" for k, v in res["seconds"].items()))
        print(f"Wrote {Path(cfg.out or Path(cfg.data) / 'train-cc')}/results.md, results.json and the weights.")
    return 0


def main_train(argv: Sequence[str] | None = None) -> int:
    """``interreflect train-cc`` as a stand-alone entry point (``python -m torch_interreflect.training.train``)."""
    parser = argparse.ArgumentParser(prog="interreflect")
    sub = parser.add_subparsers(dest="command", required=True)
    add_train_parser(sub)
    args = parser.parse_args(["train-cc", *(argv if argv is not None else sys.argv[1:])])
    return int(args.func(args))


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main_train())
