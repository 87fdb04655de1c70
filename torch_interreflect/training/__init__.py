"""Synthetic data and colour-constancy training with exact interreflection.

- Data: :class:`GeneratorConfig` (:mod:`.config`), :func:`render_sample` (:mod:`.sample`), the files and their
  formats (:mod:`.storage`: :func:`read_png` reads the 16-bit PNGs bit-exactly), :func:`generate` (:mod:`.generator`,
  ``interreflect generate``); random scenes, reflectances, illuminants, lights and views in :mod:`.random_scenes`.
- Datasets: :class:`GeneratedDataset` (a generated folder), :class:`RenderedDataset` (on the fly),
  :func:`collate`, :func:`split_indices`.
- Metrics: :func:`angular_error`, :func:`angular_loss`, :func:`summarize` (mean, median, tri-mean, best/worst 25 %).
- Baselines: :func:`grey_world`, :func:`white_patch`, :func:`grey_edge`.
- Models: :class:`FC4Net`, :class:`PhysicsInformedNet`, :func:`physics_loss`.
- Inference: :func:`load_estimator` → :class:`IlluminantEstimator` (``predict(image, geometry=None)``),
  :func:`save_estimator`; with geometry, :func:`refine_illuminant` (analysis by synthesis through the
  interreflection model, :mod:`.refine`). Representation floors of the illuminant model: :mod:`.floors`.
- Recipe: :func:`run_train_cc` / :class:`TrainConfig` (``interreflect train-cc``).
- Commands: :mod:`.commands` (``generate``, ``train-cc``; one-line errors, exit status 2 for usage errors).
"""

from .baselines import BASELINES, grey_edge, grey_world, white_patch
from .commands import add_generate_parser, add_train_parser, main_generate, main_train
from .config import GeneratorConfig, shard_indices
from .datasets import GeneratedDataset, RenderedDataset, collate, split_indices
from .estimator import CheckpointError, IlluminantEstimator, load_estimator, make_network, save_estimator
from .generator import GenerateResult, generate
from .metrics import angular_error, angular_loss, format_table, summarize
from .models import FC4Net, PhysicsInformedNet, physics_loss
from .random_scenes import (
    ILLUMINANT_KINDS,
    SCENE_KINDS,
    random_illuminant,
    random_light,
    random_reflectances,
    random_scene,
    random_view,
)
from .refine import RefinedIlluminant, refine_illuminant
from .sample import Sample, render_sample
from .storage import is_complete, load_geometry, read_png
from .train import TrainConfig, evaluate, run_train_cc, train_model

__all__ = [
    "BASELINES",
    "ILLUMINANT_KINDS",
    "SCENE_KINDS",
    "CheckpointError",
    "FC4Net",
    "GenerateResult",
    "GeneratedDataset",
    "GeneratorConfig",
    "IlluminantEstimator",
    "PhysicsInformedNet",
    "RefinedIlluminant",
    "RenderedDataset",
    "Sample",
    "TrainConfig",
    "add_generate_parser",
    "add_train_parser",
    "angular_error",
    "angular_loss",
    "collate",
    "evaluate",
    "format_table",
    "generate",
    "grey_edge",
    "grey_world",
    "is_complete",
    "load_estimator",
    "load_geometry",
    "main_generate",
    "main_train",
    "make_network",
    "physics_loss",
    "random_illuminant",
    "random_light",
    "random_reflectances",
    "random_scene",
    "random_view",
    "read_png",
    "refine_illuminant",
    "render_sample",
    "run_train_cc",
    "save_estimator",
    "shard_indices",
    "split_indices",
    "summarize",
    "train_model",
    "white_patch",
]
