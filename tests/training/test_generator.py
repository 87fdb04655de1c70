"""The synthetic data generator: determinism, resumability, shards, file formats, sidecars."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.training import generator as g
from torch_interreflect.training import storage
from torch_interreflect.training.commands import main_generate
from torch_interreflect.training.storage import read_png, write_png16

CFG = g.GeneratorConfig(count=5, seed=7, scenes=("v_groove", "box_corner", "cornell", "mesh"), size=(12, 16))


@pytest.fixture
def no_hang():
    """Tests that start worker processes: a hang ends the test process with tracebacks after 180 s, not the suite."""
    import faulthandler

    faulthandler.dump_traceback_later(180, exit=True)
    yield
    faulthandler.cancel_dump_traceback_later()


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _samples(root: Path) -> dict[str, bytes]:
    return {k: v for k, v in _files(root).items() if not k.startswith(g.MANIFEST_DIR)}


@pytest.fixture(scope="module")
def full_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("full")
    res = g.generate(out, CFG, progress=False)
    assert res.written == list(range(CFG.count)) and res.skipped == []
    return out


def test_same_seed_gives_identical_files(full_run: Path, tmp_path: Path) -> None:
    res = g.generate(tmp_path, CFG, progress=False)
    assert len(res.written) == CFG.count
    a, b = _files(full_run), _files(tmp_path)
    assert a.keys() == b.keys()
    assert all(a[k] == b[k] for k in a)
    names = set(a)
    for i in range(CFG.count):
        assert set(g.sample_files(CFG, i)) <= names
    # another seed gives other images
    other = g.render_sample(g.GeneratorConfig(**{**CFG.__dict__, "seed": 8}), 0)
    assert not np.array_equal(other.images[None], np.load(full_run / "000000.npy"))


def test_interrupted_run_resumes_to_the_same_result(full_run: Path, tmp_path: Path) -> None:
    first = g.generate(tmp_path, CFG, progress=False, limit=2)
    assert first.written == [0, 1]
    manifest = json.loads((tmp_path / g.MANIFEST_DIR / "shard-0000-of-0001.json").read_text())
    assert manifest["done"] == [0, 1] and not manifest["complete"]
    # a half-written sample: files present but no sidecar, plus the temporary files a killed process left (the
    # names of this version and of the earlier one); resuming removes them, so the folder equals a clean run's
    (tmp_path / "000002.npy").write_bytes(b"garbage")
    (tmp_path / ".000002.png.tmp123").write_bytes(b"garbage")
    (tmp_path / ".000002_geometry.tmp99999.npz").write_bytes(b"garbage")
    assert not g.is_complete(tmp_path, 2)
    second = g.generate(tmp_path, CFG, progress=False)
    assert second.skipped == [0, 1] and second.written == [2, 3, 4]
    assert sorted(p.name for p in second.removed) == [".000002.png.tmp123", ".000002_geometry.tmp99999.npz"]
    assert _files(tmp_path) == _files(full_run)
    # a sample with a missing file is redone
    (tmp_path / "000003_b1.png").unlink()
    third = g.generate(tmp_path, CFG, progress=False)
    assert third.written == [3] and _files(tmp_path) == _files(full_run)


def test_shards_partition_indices_and_reproduce_the_unsharded_run(full_run: Path, tmp_path: Path) -> None:
    for count in (0, 1, 7, 10):
        for n in (1, 2, 3, 5):
            parts = [list(g.shard_indices(count, i, n)) for i in range(n)]
            flat = sorted(k for p in parts for k in p)
            assert flat == list(range(count))  # covers everything, no index twice
    for i in (1, 0):  # any order
        g.generate(tmp_path, CFG, shard=(i, 2), progress=False)
    assert _samples(tmp_path) == _samples(full_run)
    for i, expected in ((0, [0, 2, 4]), (1, [1, 3])):
        m = json.loads((tmp_path / g.MANIFEST_DIR / f"shard-{i:04d}-of-0002.json").read_text())
        assert m["done"] == expected and m["complete"]
    with pytest.raises(ValueError, match="shard"):
        g.shard_indices(4, 2, 2)
    with pytest.raises(ValueError, match="i/n"):
        g.parse_shard("1-2")


def test_other_config_in_the_same_folder_is_refused(full_run: Path) -> None:
    with pytest.raises(ValueError, match="another configuration"):
        g.generate(full_run, g.GeneratorConfig(**{**CFG.__dict__, "seed": 99}), progress=False)


def test_sample_content(full_run: Path) -> None:
    meta = json.loads((full_run / "000001.json").read_text())
    assert meta["version"] == ti.__version__ and meta["seed"] == CFG.seed and meta["index"] == 1
    ill = meta["illuminant"]
    wl = torch.tensor(ill["wavelengths"], dtype=torch.float64)
    cam = ti.Camera.from_colour(CFG.camera, wl)
    rgb = cam(torch.tensor(ill["spd"], dtype=torch.float64)[None] / math.pi)[0]
    torch.testing.assert_close(rgb, torch.tensor(ill["rgb"], dtype=torch.float64), rtol=1e-5, atol=0)
    assert abs(np.linalg.norm(ill["rgb_normalized"]) - 1) < 1e-6
    img = np.load(full_run / "000001.npy")
    assert img.dtype == np.float32 and img.shape == (12, 16, 3)
    png = read_png(full_run / "000001.png")
    assert png.dtype == np.uint16 and png.shape == (12, 16, 3)
    np.testing.assert_array_equal(png, np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16))
    # more bounces, more light: direct ≤ 2 bounces ≤ ∞ (same exposure)
    for i in range(CFG.count):
        b1, b2, inf = (np.load(full_run / f"{i:06d}{s}.npy") for s in ("_b1", "_b2", ""))
        assert (b1 <= b2 + 1e-6).all() and (b2 <= inf + 1e-6).all() and (inf > b1 + 1e-4).any()
    geo = g.load_geometry(full_run / "000001_geometry.npz")
    assert geo["coverage"].shape == (12 * 16, meta["num_facets"])
    assert geo["reflectance"].shape == (len(meta["materials"]), wl.numel())


def test_png_files_round_trip_bit_exactly_and_ordinary_pngs_read(tmp_path: Path) -> None:
    a = np.random.default_rng(0).integers(0, 65536, (5, 7, 3)).astype(np.uint16)
    write_png16(tmp_path / "a.png", a)
    back = read_png(tmp_path / "a.png")
    assert back.dtype == np.uint16
    np.testing.assert_array_equal(back, a)  # all 16 bits, every value
    write_png16(tmp_path / "b.png", a.copy())
    assert (tmp_path / "a.png").read_bytes() == (tmp_path / "b.png").read_bytes()  # same array, same bytes
    with pytest.raises(ValueError, match="uint16"):
        write_png16(tmp_path / "c.png", a.astype(np.float32))
    # ordinary 8-bit PNGs as other programs write them (filtered rows, palettes) read too
    PIL = pytest.importorskip("PIL.Image")
    b8 = (a >> 8).astype(np.uint8)
    PIL.fromarray(b8).save(tmp_path / "rgb8.png")
    np.testing.assert_array_equal(read_png(tmp_path / "rgb8.png"), b8)
    PIL.fromarray(b8).convert("P", palette=PIL.Palette.ADAPTIVE, colors=256).convert("RGB").save(tmp_path / "q.png")
    PIL.open(tmp_path / "q.png").convert("P", palette=PIL.Palette.ADAPTIVE, colors=256).save(tmp_path / "pal.png")
    np.testing.assert_array_equal(read_png(tmp_path / "pal.png"), np.asarray(PIL.open(tmp_path / "q.png")))
    # Pillow opens the 16-bit file as 8-bit RGB, silently dropping the low byte: that is why read_png exists
    with PIL.open(tmp_path / "a.png") as im:
        assert im.mode == "RGB" and im.size == (7, 5)


def test_failed_write_leaves_no_temporary_file(full_run: Path, tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    real_replace = storage.os.replace

    def full_disk(src: object, dst: object) -> None:
        if str(dst).endswith("000001_geometry.npz"):
            raise OSError(28, "No space left on device")
        real_replace(src, dst)

    monkeypatch.setattr(storage.os, "replace", full_disk)
    with pytest.raises(OSError, match="No space"):
        g.generate(tmp_path, CFG, progress=False)
    assert [p.name for p in tmp_path.iterdir() if ".tmp" in p.name] == []
    assert g.is_complete(tmp_path, 0) and not g.is_complete(tmp_path, 1)
    monkeypatch.setattr(storage.os, "replace", real_replace)
    assert g.generate(tmp_path, CFG, progress=False).written == [1, 2, 3, 4]
    assert _samples(tmp_path) == _samples(full_run)


def test_a_folder_grows_with_a_larger_count(full_run: Path, tmp_path: Path) -> None:
    small = g.GeneratorConfig(**{**CFG.__dict__, "count": 2})
    assert g.generate(tmp_path, small, progress=False).written == [0, 1]
    grown = g.generate(tmp_path, CFG, progress=False)
    assert grown.skipped == [0, 1] and grown.written == [2, 3, 4]
    assert g.read_config(tmp_path) == CFG  # the stored count follows the largest run
    assert _samples(tmp_path) == _samples(full_run)
    assert g.generate(tmp_path, small, progress=False).written == []  # a smaller count: nothing to do
    assert g.read_config(tmp_path).count == CFG.count  # and never shrinks what is listed


def test_render_sample_on_a_device_matches_the_cpu(device: torch.device) -> None:
    cfg = g.GeneratorConfig(count=1, seed=3, scenes=("cornell",), size=(10, 12))
    cpu = g.render_sample(cfg, 0)
    dev = g.render_sample(cfg, 0, device=device)
    for b in cfg.bounces:
        np.testing.assert_allclose(dev.images[b], cpu.images[b], rtol=1e-6, atol=1e-7)
        if device.type == "cpu":
            np.testing.assert_array_equal(dev.images[b], cpu.images[b])
    assert dev.metadata == cpu.metadata


def test_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--out", str(tmp_path), "--count", "2", "--seed", "3", "--scenes", "v_groove", "--size", "8x10",
            "--bounces", "inf", "1", "--no-geometry", "--no-progress", "--shard", "1/2"]
    assert main_generate(argv) == 0
    assert "samples/s" in capsys.readouterr().out
    assert sorted(p.name for p in tmp_path.iterdir() if p.is_file()) == [
        "000001.json", "000001.npy", "000001.png", "000001_b1.npy", "000001_b1.png", "dataset.json"]


@pytest.mark.parametrize("bad, says", [
    (["--count", "-1"], "argument --count: expected an integer >= 0; got '-1'"),
    (["--count", "2", "--size", "0x64"], "argument --size: expected HxW with positive integers"),
    (["--count", "2", "--size", "8by10"], "argument --size: expected HxW"),
    (["--count", "2", "--bounces", "0"], "argument --bounces: expected 'inf' or an integer >= 1; got '0'"),
    (["--count", "2", "--supersample", "0"], "argument --supersample: expected an integer >= 1"),
    (["--count", "2", "--shading", "smooth"], "argument --shading: invalid choice: 'smooth'"),
    (["--count", "2", "--shard", "2/2"], "shard must satisfy 0 <= shard < num_shards"),
    (["--count", "2", "--camera", "Nikon 510O"], "unknown camera 'Nikon 510O'"),
    (["--count", "2", "--workers", "0"], "argument --workers: expected 'auto' or an integer >= 1; got '0'"),
    (["--count", "2", "--workers", "many"], "argument --workers: expected 'auto' or an integer >= 1; got 'many'"),
])
def test_cli_usage_errors_are_one_line_exit_2_and_write_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], bad: list[str], says: str
) -> None:
    out = tmp_path / "data"
    with pytest.raises(SystemExit) as exc:  # argparse exits; errors found later return the status
        raise SystemExit(main_generate(["--out", str(out), "--no-progress", *bad]))
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and says in err and "Traceback" not in err
    assert not out.exists()  # a failed start writes nothing


def test_cli_corrected_run_after_a_typo_and_debug_traceback(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    base = ["--out", str(tmp_path / "d"), "--count", "1", "--scenes", "v_groove", "--size", "6x6", "--no-progress"]
    assert main_generate([*base, "--camera", "Nikkon"]) == 2
    assert main_generate(base) == 0  # not blocked by the failed run
    with pytest.raises(ValueError, match="another configuration"):
        main_generate([*base[:-1], "--size", "6x7", "--debug", "--no-progress"])
    capsys.readouterr()


def test_bad_configs() -> None:
    with pytest.raises(ValueError, match="scenes"):
        g.GeneratorConfig(scenes=("sphere",))
    with pytest.raises(ValueError, match="bounces"):
        g.GeneratorConfig(bounces=(1, 2))
    with pytest.raises(ValueError, match="count"):
        g.GeneratorConfig(count=-1)
    with pytest.raises(ValueError, match="shading must be one of"):
        g.GeneratorConfig(shading="smooth")
    with pytest.raises(ValueError, match="split_contacts"):
        g.GeneratorConfig(split_contacts=1)
    with pytest.raises(ValueError, match="visibility_samples"):
        g.GeneratorConfig(visibility_samples=0)


@pytest.mark.parametrize("index", range(6))
def test_gathered_samples_agree_with_flat_ones_on_average(index: int) -> None:
    """Gather and flat shading light the same facets. On scenes whose facets the camera sees whole (grooves, box
    corners, W folds) image means (exposure removed) agree to within 0.3 % (measured on these six samples, the
    flat coverage from 16 × 16 rays per pixel: 0.9982–1.0013, the same from 32 × 32; from 2 × 2 rays, against the
    gather's edge rays, 0.984 on one), for every variant. (On meshes and boxes with blocks the visible parts of a
    facet need not have its mean irradiance: up to 4 % apart at 64 × 64.)"""
    cfg = g.GeneratorConfig(count=6, seed=7, scenes=("v_groove", "box_corner", "w_shape"), size=(32, 32))
    gathered = g.render_sample(cfg, index)
    # flat coverage with uniform 16 × 16 rays: the pixel integral that the gather's edge pixels resolve
    flat = g.render_sample(g.GeneratorConfig(**{**cfg.__dict__, "shading": "flat", "supersample": 16}), index)
    assert gathered.metadata["num_facets"] == flat.metadata["num_facets"]
    for b in cfg.bounces:
        mg = gathered.images[b].mean() / gathered.metadata["exposure"]
        mf = flat.images[b].mean() / flat.metadata["exposure"]
        assert mg == pytest.approx(mf, rel=3e-3), (b, mg, mf)
    # per pixel they differ: the gather varies inside facets
    assert not np.allclose(gathered.images[None], flat.images[None], rtol=1e-3)


def test_gathered_variants_gather_one_bounce_less() -> None:
    """The n-bounce image gathers the (n - 1)-bounce facet irradiance: the 1-bounce image is direct light only,
    so it is darker than the 2-bounce one everywhere, which is darker than infinite bounces."""
    s = g.render_sample(g.GeneratorConfig(count=1, seed=3, scenes=("box_corner",), size=(12, 12)), 0)
    b1, b2, inf = s.images[1], s.images[2], s.images[None]
    lit = inf > 0.05 * inf.max()
    assert np.all(b1[lit] < b2[lit]) and np.all(b2[lit] <= inf[lit] * (1 + 1e-6))


def test_configs_of_earlier_versions_read_back_as_flat_unsplit(tmp_path: Path) -> None:
    """A dataset.json written before ``shading`` existed made flat, unsplit samples: it reads back so, and the new
    defaults are another configuration (the folder is not mixed)."""
    old = CFG.to_json()
    for k in ("shading", "split_contacts", "visibility_samples"):
        del old[k]
    cfg = g.GeneratorConfig.from_json(old)
    assert (cfg.shading, cfg.split_contacts) == ("flat", False)
    assert not cfg.same_samples(CFG)
    assert g.GeneratorConfig.from_json(CFG.to_json()) == CFG
    # the gather's settings do not change flat samples: a flat folder grows whatever they say
    flat = g.GeneratorConfig(**{**CFG.__dict__, "shading": "flat"})
    assert flat.same_samples(g.GeneratorConfig(**{**flat.__dict__, "visibility_samples": 3, "gather_stride": 2,
                                                   "edge_supersample": 4}))
    assert not CFG.same_samples(g.GeneratorConfig(**{**CFG.__dict__, "visibility_samples": 3}))


def test_gathered_folders_before_edge_rays_keep_uniform_rays() -> None:
    """A gathered folder written before ``edge_supersample`` (0.2.0) had uniform rays: it reads back with none, so
    growing it adds samples of the same kind; an edge supersample not above the supersample is uniform too."""
    old = CFG.to_json()
    del old["edge_supersample"]
    cfg = g.GeneratorConfig.from_json(old)
    assert cfg.shading == "gather" and cfg.edge_supersample is None and not cfg.same_samples(CFG)
    assert CFG.edge_supersample == 8
    assert g.GeneratorConfig(**{**CFG.__dict__, "edge_supersample": 2}).same_samples(cfg)
    with pytest.raises(ValueError, match="edge_supersample must be an integer >= 1; got 0"):
        g.GeneratorConfig(edge_supersample=0)


def test_split_contacts_splits_the_floor_under_the_blocks() -> None:
    cfg = g.GeneratorConfig(count=1, seed=3, scenes=("cornell",), size=(8, 8), shading="flat")
    split = g.render_sample(cfg, 0).metadata["num_facets"]
    whole = g.render_sample(g.GeneratorConfig(**{**cfg.__dict__, "split_contacts": False}), 0).metadata["num_facets"]
    assert split > whole


def test_gathered_samples_carry_their_per_pixel_model_and_refine_uses_it():
    """A gathered sample's geometry stores the facets, view, light mix and rays; refine_illuminant rebuilds the
    gather from them, so at the true illuminant its re-render explains the image to 0.17 % (measured) where the
    flat model leaves 12 % (a concave mesh, only parts of its facets seen), and the sample's model with uniform
    2 × 2 rays (``edge_supersample=1``) 5.5 %."""
    from torch_interreflect.training import refine_illuminant

    cfg = g.GeneratorConfig(size=(32, 32))
    s = g.render_sample(cfg, 0)
    assert s.metadata["scene"]["kind"] == "mesh"
    geo = g.load_geometry(s.geometry)
    assert "shading" in geo and "shading" not in g.load_geometry(
        g.render_sample(g.GeneratorConfig(size=(8, 8), shading="flat"), 0).geometry)
    image = torch.from_numpy(s.images[None]).permute(2, 0, 1).double()
    truth = torch.tensor(s.metadata["illuminant"]["rgb_normalized"], dtype=torch.float64)
    est = {"camera": cfg.camera, "wavelengths": cfg.wavelengths}
    gathered = refine_illuminant(est, image, geo, truth, steps=3)
    flat = refine_illuminant(est, image, {k: v for k, v in geo.items() if k != "shading"}, truth, steps=3)
    assert gathered.start_residual < 3e-3 < 0.05 < flat.start_residual
    assert geo["shading"]["edge_supersample"] == 8
    uniform = refine_illuminant(est, image, geo, truth, steps=3, edge_supersample=1)
    assert uniform.start_residual > 0.03


def test_solver_accuracy_warnings_come_once_per_run(tmp_path: Path) -> None:
    """Bright rooms make the solve warn that its error bound (the form factors' closure error, amplified) is above
    its tolerance: one warning per run names the samples, instead of one or more per sample."""
    import warnings

    from torch_interreflect.errors import AccuracyWarning

    cfg = g.GeneratorConfig(count=5, seed=0, scenes=("cornell",), size=(8, 8), bounces=(None,))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = g.generate(tmp_path / "d", cfg, progress=False)
    assert res.inaccurate == [3, 4] and res.written == [0, 1, 2, 3, 4]
    accuracy = [w for w in caught if issubclass(w.category, AccuracyWarning)]
    assert len(accuracy) == 1
    assert "the solves of 2 of 5 samples warned" in str(accuracy[0].message)
    assert "closure error" in str(accuracy[0].message)
    # refining one of them: one warning for all the fit's solves
    from torch_interreflect.training import refine_illuminant

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", AccuracyWarning)
        s = g.render_sample(cfg, 3)
    image = torch.from_numpy(s.images[None]).permute(2, 0, 1).double()
    truth = torch.tensor(s.metadata["illuminant"]["rgb_normalized"], dtype=torch.float64)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        refine_illuminant({"camera": cfg.camera, "wavelengths": cfg.wavelengths}, image,
                          g.load_geometry(s.geometry), truth, steps=3)
    accuracy = [str(w.message) for w in caught if issubclass(w.category, AccuracyWarning)]
    assert len(accuracy) == 1 and accuracy[0].startswith("refine_illuminant: ") and "of the fit's solves" in accuracy[0]


def test_worker_processes_write_the_same_bytes_and_resume(full_run: Path, tmp_path: Path, no_hang: None) -> None:
    """Two processes (this one and a spawned one) write the files one process writes, the manifest included; a run
    interrupted by ``limit`` resumes with workers; inaccurate solves are reported from either process."""
    first = g.generate(tmp_path, CFG, progress=False, limit=1, workers=2)
    assert first.written == [0] and first.workers == 1  # one sample: rendered here, no process started
    second = g.generate(tmp_path, CFG, progress=False, limit=3, workers=2)  # interrupted with two processes
    assert second.written == [1, 2, 3] and second.skipped == [0] and second.workers == 2
    manifest = json.loads((tmp_path / g.MANIFEST_DIR / "shard-0000-of-0001.json").read_text())
    assert manifest["done"] == [0, 1, 2, 3] and not manifest["complete"]
    res = g.generate(tmp_path, CFG, progress=False, workers=2)
    assert res.written == [4] and res.skipped == [0, 1, 2, 3] and res.workers == 1
    assert _files(tmp_path) == _files(full_run)
    from torch_interreflect.errors import AccuracyWarning
    from torch_interreflect.training.workers import render_indices

    cfg = g.GeneratorConfig(count=5, seed=0, scenes=("cornell",), size=(8, 8), bounces=(None,))
    with pytest.warns(AccuracyWarning, match="the solves of 2 of 5 samples warned.*sample 3: "):
        res = g.generate(tmp_path / "d", cfg, progress=False, workers=2)
    assert res.inaccurate == [3, 4]  # as in one process (test_solver_accuracy_warnings_come_once_per_run)
    # the spawned process takes the first indices (3 and 4 here), this one the last: warnings come back from it
    (tmp_path / "e").mkdir()
    got = dict(render_indices(tmp_path / "e", cfg, [3, 4, 0, 1, 2], workers=2))
    assert sorted(got) == [0, 1, 2, 3, 4]
    assert [k for k, w in sorted(got.items()) if w is not None] == [3, 4] and "closure error" in got[3]
    assert _samples(tmp_path / "e") == {k: v for k, v in _samples(tmp_path / "d").items() if k != "dataset.json"}


def test_auto_workers_start_one_process_per_32_samples_up_to_the_cores(monkeypatch: pytest.MonkeyPatch,
                                                                       tmp_path: Path) -> None:
    from torch_interreflect.training import workers

    monkeypatch.setattr(workers, "usable_cores", lambda: 4)
    assert [workers.auto_workers(n) for n in (0, 31, 32, 95, 96, 1000)] == [1, 1, 1, 2, 3, 4]
    res = g.generate(tmp_path, g.GeneratorConfig(**{**CFG.__dict__, "count": 2}), progress=False, workers="auto")
    assert res.workers == 1 and res.written == [0, 1]
    assert workers.auto_workers(1000, threads=2) == 2 and workers.auto_workers(1000, threads=8) == 1
    for bad in (0, -1, 1.5, "all", True):
        with pytest.raises(ValueError, match="workers must be a positive int or 'auto'"):
            g.generate(tmp_path / "never", CFG, progress=False, workers=bad)
    with pytest.raises(ValueError, match="limit must be None or an integer >= 0; got -1"):
        g.generate(tmp_path / "never", CFG, progress=False, limit=-1)
    assert not (tmp_path / "never").exists()
    for bad in (0, 1.5, "auto"):
        with pytest.raises(ValueError, match="workers must be a positive int; got"):
            next(workers.render_indices(tmp_path, CFG, [0], workers=bad))
    assert [workers.processes(w, n) for w, n in ((4, 2), (2, 0), (2, 1), (3, 10))] == [2, 1, 1, 3]


def test_an_error_in_a_worker_process_stops_the_run_and_is_raised(tmp_path: Path, no_hang: None) -> None:
    """A sample that cannot be written (its sidecar's name taken by a folder) fails in the spawned process that takes
    it: the run raises that error, does not hang, and marks nothing of it complete."""
    cfg = g.GeneratorConfig(count=5, seed=7, scenes=("v_groove",), size=(8, 8), bounces=(None,))
    g.generate(tmp_path, g.GeneratorConfig(**{**cfg.__dict__, "count": 0}), progress=False)  # the folder, config
    (tmp_path / "000000.json").mkdir()  # index 0 goes to the spawned process (it takes the first indices)
    with pytest.raises(OSError, match=r"000000\.json"):
        g.generate(tmp_path, cfg, progress=False, workers=2)
    assert (tmp_path / "000000.json").is_dir()  # untouched
    assert not list(tmp_path.glob(".*tmp*"))  # the failed write left no temporary file


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc (Linux)")
def test_workers_exit_when_their_parent_is_killed(tmp_path: Path, no_hang: None) -> None:
    """A parent killed by SIGKILL runs no shutdown: its spawned workers notice and exit instead of waiting forever."""
    import os
    import signal
    import subprocess
    import sys
    import time

    code = ("import sys; from torch_interreflect.training import generator as g; "
            "g.generate(sys.argv[1], g.GeneratorConfig(count=60, seed=7, scenes=('v_groove',), size=(8, 8), "
            "bounces=(None,)), progress=False, workers=2)")
    p = subprocess.Popen([sys.executable, "-c", code, str(tmp_path / "d")])
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and len(list((tmp_path / "d").glob("*.json"))) < 6:
        time.sleep(0.2)  # until both processes write samples
    children = [c for c in os.listdir("/proc") if c.isdigit() and _proc_field(c, "PPid:") == str(p.pid)]
    assert children, "no worker process was started"
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    deadline = time.monotonic() + 30
    alive = children
    while alive and time.monotonic() < deadline:
        time.sleep(0.2)
        alive = [c for c in alive if "zombie" not in _proc_field(c, "State:").lower()]
    assert not alive, f"workers {alive} outlived their killed parent"


def _proc_field(pid: str, field: str) -> str:
    """A field of ``/proc/<pid>/status`` (``"zombie"`` once the process is gone)."""
    try:
        return Path(f"/proc/{pid}/status").read_text().split(field)[1].split("\n")[0].strip()
    except (OSError, IndexError):
        return "zombie"


class _WarningConfig(g.GeneratorConfig):
    """A configuration that warns, with the process id, each time a sample reads its camera (pickled by reference:
    spawned workers import it from this module)."""

    def __getattribute__(self, name: str):
        if name == "camera":
            import os
            import warnings

            warnings.warn(f"camera read in process {os.getpid()}", UserWarning, stacklevel=2)
        return super().__getattribute__(name)


def test_warnings_raised_in_worker_processes_are_raised_again_in_the_parent(tmp_path: Path, no_hang: None) -> None:
    import os
    import warnings

    from torch_interreflect.training.workers import render_indices

    cfg = _WarningConfig(count=3, seed=7, scenes=("v_groove",), size=(8, 8), bounces=(None,))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        done = dict(render_indices(tmp_path, cfg, [0, 1, 2], workers=2))
    assert sorted(done) == [0, 1, 2]
    pids = {str(w.message).rsplit(" ", 1)[1] for w in caught if issubclass(w.category, UserWarning)}
    assert str(os.getpid()) in pids  # index 2, rendered here
    assert pids - {str(os.getpid())}, "no warning came back from the spawned process (indices 0 and 1)"
