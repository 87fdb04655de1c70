"""Cores the generator's workers may use: the affinity mask, and a container's CPU quota (cgroup v2 and v1)."""

from pathlib import Path

import pytest

from torch_interreflect.training import workers


def _files(tmp_path: Path, v2: str | None = None, v1: tuple[str, str] | None = None):
    paths = (tmp_path / "cpu.max", (tmp_path / "cfs_quota_us", tmp_path / "cfs_period_us"))
    if v2 is not None:
        paths[0].write_text(v2)
    if v1 is not None:
        paths[1][0].write_text(v1[0])
        paths[1][1].write_text(v1[1])
    return paths


@pytest.mark.parametrize(("v2", "v1", "cores"), [
    ("200000 100000\n", None, 2),  # docker --cpus=2
    ("150000 100000\n", None, 2),  # 1.5 cores: a second process still has half a core
    ("50000 100000\n", None, 1),
    ("max 100000\n", None, None),  # no quota
    (None, ("400000", "100000"), 4),  # cgroup v1
    (None, ("-1", "100000"), None),
    (None, None, None),  # no cgroup files (macOS, Windows, no container)
    ("garbage", ("300000", "100000"), 3),  # an unreadable v2 file falls back to v1
])
def test_cpu_quota(tmp_path, v2, v1, cores):
    assert workers.cpu_quota(_files(tmp_path, v2, v1)) == cores


def test_usable_cores_capped_by_the_quota(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(workers.os, "sched_getaffinity", lambda pid: set(range(64)), raising=False)
    monkeypatch.setattr(workers, "CGROUP_QUOTA", _files(tmp_path, "200000 100000"))
    assert workers.usable_cores() == 2
    assert workers.auto_workers(10_000) == 2
    none = tmp_path / "none"
    none.mkdir()
    monkeypatch.setattr(workers, "CGROUP_QUOTA", _files(none))
    assert workers.usable_cores() == 64
