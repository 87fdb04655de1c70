"""Shared fixtures: ``dtype`` (float32 and float64), ``device`` (CPU, and CUDA when present or asked for with
``--device``), and the oracle builders of :mod:`tests.oracles`."""

from __future__ import annotations

import os

import pytest
import torch

from tests import oracles

# Under pytest-xdist every worker is its own process: one torch thread each keeps 2 cores from being
# oversubscribed (spinning intra-op threads make small-tensor code many times slower). Tests of behaviour under
# several threads set the count themselves (tests/solver/test_threads.py).
if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--device",
        action="append",
        default=None,
        help="device(s) for the `device` fixture (default: cpu, plus cuda when available); repeatable",
    )


def _devices(config: pytest.Config) -> list[str]:
    asked = config.getoption("--device")
    if asked:
        return list(asked)
    return ["cpu", "cuda"]  # cuda is skipped where there is none


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if "device" in metafunc.fixturenames:
        metafunc.parametrize("device", _devices(metafunc.config), indirect=True)


@pytest.fixture
def device(request: pytest.FixtureRequest) -> torch.device:
    """A device to run on; CUDA cases skip on machines without a GPU."""
    dev = torch.device(request.param)
    if dev.type == "cuda" and not torch.cuda.is_available():
        pytest.skip("needs CUDA")
    return dev


@pytest.fixture(params=[torch.float32, torch.float64], ids=["float32", "float64"])
def dtype(request: pytest.FixtureRequest) -> torch.dtype:
    """Both floating dtypes the library supports."""
    return request.param


@pytest.fixture
def random_reciprocal():
    """The builder :func:`tests.oracles.random_reciprocal` (random reciprocal form factors)."""
    return oracles.random_reciprocal
