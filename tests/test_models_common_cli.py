"""models/common/cli.py: `clsplat train|eval FAMILY` dispatch and the shared arguments."""
from __future__ import annotations

import argparse

import pytest

from clsplat.cli import main
from clsplat.models.common.cli import add_common_args, add_lpips_args, lpips_from_args


def test_unknown_family_and_help(capsys):
    assert main(["train", "nerf"]) == 2
    assert "unknown model family 'nerf'" in capsys.readouterr().err
    assert main(["eval"]) == 2
    assert main(["train", "--help"]) == 0
    assert "drivingforward" in capsys.readouterr().out


def test_common_arguments():
    p = argparse.ArgumentParser()
    add_common_args(p)
    a = p.parse_args(["--out", "x", "--steps", "3", "--data", "pandaset:/d", "--resume"])
    assert (a.out, a.steps, a.data, a.resume, a.preset) == ("x", 3, "pandaset:/d", True, "small")
    with pytest.raises(SystemExit):
        p.parse_args(["--out", "x", "--steps", "0"])


def test_lpips_arguments_are_off_by_default_and_need_both_files(capsys, tmp_path):
    p = argparse.ArgumentParser()
    add_lpips_args(p)
    assert lpips_from_args(p.parse_args([])) is None
    assert "LPIPS off" in capsys.readouterr().out
    with pytest.raises(ValueError, match="lin_weights: LPIPS needs both"):
        lpips_from_args(p.parse_args(["--lpips-vgg", str(tmp_path / "vgg.pth")]))
