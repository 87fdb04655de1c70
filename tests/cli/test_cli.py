"""How ``interreflect`` fails: one-line usage errors with exit status 2, nothing written by a failed start, growing
data sets, sizes that must match, weights that are not overwritten silently, Ctrl-C."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from torch_interreflect.cli import main
from torch_interreflect.training.commands import run_command


def _fails(argv: list[str], capsys: pytest.CaptureFixture[str], status: int = 2) -> str:
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's own errors exit
        code = exc.code
    assert code == status
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("argv, says", [
    (["train-cc", "--count", "-1"], "argument --count: expected an integer >= 1; got '-1'"),
    (["train-cc", "--size", "0x64"], "argument --size: expected HxW with positive integers"),
    (["train-cc", "--test-fraction", "1.5"], "argument --test-fraction: expected a number in (0, 1)"),
    (["train-cc", "--lr", "nan"], "argument --lr: expected a finite number > 0"),
    (["demo", "--divisions", "0"], "argument --divisions: expected an integer >= 1"),
    (["demo", "--angles", "190"], "argument --angles: expected a groove angle in (0, 180)"),
    (["generate", "--out", "x", "--count", "2", "--bounces", "0"], "argument --bounces"),
    (["nosuchcommand"], "invalid choice"),
])
def test_usage_errors_are_one_line_with_status_2(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                 monkeypatch: pytest.MonkeyPatch, argv: list[str], says: str) -> None:
    monkeypatch.chdir(tmp_path)
    assert says in _fails(argv, capsys)
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_train_cc_size_mismatch_and_overwrite(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data, out = str(tmp_path / "d"), str(tmp_path / "r")
    gen = ["generate", "--out", data, "--count", "3", "--scenes", "v_groove", "--size", "8x8", "--bounces", "inf",
           "--no-geometry", "--no-progress"]
    assert main(gen) == 0
    train = ["train-cc", "--data", data, "--out", out, "--count", "3", "--test-fraction", "0.34", "--epochs", "1",
             "--physics-epochs", "0", "--batch-size", "2", "--width", "2", "--no-progress"]
    err = _fails([*train, "--size", "16x16"], capsys)
    assert "holds 8x8 images but --size is 16x16" in err and not Path(out).exists()
    assert main([*train, "--size", "8x8"]) == 0
    capsys.readouterr()
    weights = (Path(out) / "fc4_inf.pt").read_bytes()
    assert "--overwrite" in _fails(train, capsys)
    assert (Path(out) / "fc4_inf.pt").read_bytes() == weights
    assert main([*train, "--overwrite", "--epochs", "2"]) == 0
    # the data set grows: 3 samples, then 5 (the first 3 are kept, not redone)
    first = (Path(data) / "000000.npy").stat().st_mtime_ns
    assert main([*gen[:4], "5", *gen[5:]]) == 0
    assert "wrote 2 samples, skipped 3" in capsys.readouterr().out
    assert (Path(data) / "000000.npy").stat().st_mtime_ns == first


def test_other_errors_are_one_line_with_status_1_and_debug_shows_the_traceback(capsys) -> None:
    from torch_interreflect.training.commands import ArgumentParser

    def boom(args: object) -> int:
        raise RuntimeError("disk on fire")

    def interrupted(args: object) -> int:
        raise KeyboardInterrupt

    parser = ArgumentParser(prog="interreflect")
    parser.add_argument("--debug", action="store_true")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("boom").set_defaults(func=boom)
    sub.add_parser("int").set_defaults(func=interrupted)
    assert run_command(parser, ["boom"]) == 1
    assert capsys.readouterr().err.strip() == (
        "interreflect: error (RuntimeError): disk on fire (run with --debug for the traceback)")
    assert run_command(parser, ["int"]) == 130
    assert capsys.readouterr().err.strip() == "interreflect: interrupted"
    with pytest.raises(RuntimeError, match="disk on fire"):
        run_command(parser, ["--debug", "boom"])


def test_ctrl_c_exits_130_with_one_line(tmp_path: Path) -> None:
    out = tmp_path / "d"
    proc = subprocess.Popen(
        [sys.executable, "-m", "torch_interreflect.cli", "generate", "--out", str(out), "--count", "1000",
         "--scenes", "v_groove", "--size", "8x8", "--no-progress"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        # a shell's background job (e.g. a CI script run with `&`) ignores SIGINT, and a child inherits that
        # (Python then installs no KeyboardInterrupt handler): give the command the default, as a terminal does
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + 120
    while not (out / "000000.json").exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert err.strip() == "interreflect: interrupted"
    assert [p.name for p in out.iterdir() if ".tmp" in p.name] == []  # the write in flight cleaned up after itself
