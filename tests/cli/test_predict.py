"""``interreflect predict``: JSON and previews from a checkpoint, with and without geometry; one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from torch_interreflect.cli import main
from torch_interreflect.training import GeneratorConfig, generate, load_estimator, make_network, save_estimator
from torch_interreflect.training.storage import read_png

CFG = GeneratorConfig(count=2, seed=3, scenes=("box_corner",), size=(12, 12))


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("pred")
    generate(root / "data", CFG, progress=False)
    torch.manual_seed(0)
    conf = {"kind": "physics", "width": 4, "camera": CFG.camera, "wavelengths": list(CFG.wavelengths)}
    (root / "model").mkdir()
    save_estimator(make_network(conf), conf, root / "model" / "physics.pt")
    return root / "data", root / "model"


def test_predict_end_to_end(setup: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data, model = setup
    images = [str(data / "000000.png"), str(data / "000001.npy")]
    assert main(["predict", *images, "--model", str(model), "--out", str(tmp_path / "p"), "--geometry"]) == 0
    doc = json.loads((tmp_path / "p" / "predictions.json").read_text())
    assert [r["image"] for r in doc["predictions"]] == images and doc["camera"] == CFG.camera
    est = load_estimator(model)
    for r in doc["predictions"]:
        assert r["geometry"] is True
        assert abs(sum(v * v for v in r["rgb"]) - 1.0) < 1e-5
        preview = read_png(r["preview"])
        assert preview.shape == (12, 12, 3) and preview.dtype.name == "uint8"
    # without --geometry the network alone answers: the same numbers as the Python API
    assert main(["predict", images[1], "--model", str(model), "--out", str(tmp_path / "q")]) == 0
    row = json.loads((tmp_path / "q" / "predictions.json").read_text())["predictions"][0]
    import numpy as np

    img = torch.from_numpy(np.load(images[1])).permute(2, 0, 1)
    torch.testing.assert_close(torch.tensor(row["rgb"]), est.predict(img)[0].float(), atol=1e-6, rtol=0)
    assert "illuminant RGB" in capsys.readouterr().out


def test_predict_errors_are_one_line(setup: tuple[Path, Path], tmp_path: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    data, model = setup
    assert main(["predict", str(data / "000000.json"), "--model", str(model), "--out", str(tmp_path / "o")]) == 2
    assert "expected a .png or .npy image" in capsys.readouterr().err
    assert main(["predict", str(data / "000000.png"), "--model", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "holds none of" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()
