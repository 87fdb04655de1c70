import json

import torch_interreflect as ti
from torch_interreflect.cli import main
from torch_interreflect.cli.demo import DemoConfig, run_demo


def test_demo_writes_its_outputs_and_the_numbers_make_sense(tmp_path):
    run_demo(tmp_path, DemoConfig(angles=(45.0,), divisions=4), progress=False)
    for name in ("form_factors.png", "images_45deg_D50.png", "images_45deg_A.png", "difference_vs_distance.png",
                 "table9.md", "results.json"):
        assert (tmp_path / name).stat().st_size > 0
    table = json.loads((tmp_path / "results.json").read_text())["table"]["45"]["D50"]
    for patch, by_b in table.items():
        worst = {b: max(v["hinge_column_%"]) for b, v in by_b.items()}
        overall = {b: max(v["overall_%"]) for b, v in by_b.items()}
        # more bounces, closer to infinity; the hinge column is where the error lives
        assert worst["2"] > worst["3"] > worst["4"] > 0, patch
        assert worst["2"] > overall["2"], patch
    # a bright patch needs the extra bounces more than a dark one
    assert max(table["red"]["2"]["hinge_column_%"]) > max(table["blue"]["2"]["hinge_column_%"])


def test_cli_demo(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--angles", "60", "--divisions", "3", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "table9.md" in out and "Done in" in out
    assert ti.__version__
