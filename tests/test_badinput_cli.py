"""Bad input to the ``clsplat`` command: ``fit`` and ``demo`` name the argument or file that is
wrong, a diverging fit names ``lr``, and a failed write (full disk) leaves the previous run's
outputs whole."""
import errno

import numpy as np
import pytest

from clsplat import fit_image
from clsplat.cli import main
from clsplat.io.images import write_image

TINY = ["--gaussians", "8", "--iterations", "2", "--no-progress"]


@pytest.fixture(scope="module")
def target(tmp_path_factory):
    img = np.random.default_rng(0).random((12, 16, 3)).astype(np.float32)
    return write_image(tmp_path_factory.mktemp("t") / "target.png", img)


def test_diverging_learning_rate_names_lr(tmp_path, target):
    with pytest.raises(ValueError, match=r"^lr: the fit diverged at iteration \d+ with lr=1e\+12"):
        main(["fit", "--out", str(tmp_path / "o"), "--target", str(target), "--lr", "1e12",
              "--gaussians", "8", "--iterations", "6", "--no-progress"])


@pytest.mark.parametrize("args,what", [(["--lr", "nan"], "^lr must be"), (["--lr", "-1"], "^lr must be"),
                                       (["--gaussians", "0"], "^n_gaussians must be"),
                                       (["--iterations", "0"], "^iterations must be")])
def test_fit_arguments_named(tmp_path, target, args, what):
    with pytest.raises(ValueError, match=what):
        main(["fit", "--out", str(tmp_path / "o"), "--target", str(target), *TINY, *args])


def test_fit_target_missing_or_corrupt(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"nope\.png"):
        main(["fit", "--out", str(tmp_path / "o"), "--target", str(tmp_path / "nope.png"), *TINY])
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(ValueError, match=r"bad\.png"):
        main(["fit", "--out", str(tmp_path / "o"), "--target", str(tmp_path / "bad.png"), *TINY])


def test_fit_out_dir_that_is_a_file(tmp_path, target):
    (tmp_path / "f").write_text("x")
    with pytest.raises(ValueError, match="^out_dir: .* is not a folder"):
        main(["fit", "--out", str(tmp_path / "f"), "--target", str(target), *TINY])


def test_demo_out_dir_that_is_a_file(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(ValueError, match="^out_dir: .* is not a folder"):
        main(["demo", "--out", str(tmp_path / "f")])


def test_huge_procedural_target_refused_before_allocation():
    with pytest.raises(ValueError, match="^height, width: at most"):
        fit_image.procedural_target(100000, 100000)


def test_fit_on_a_full_disk_keeps_the_previous_run(tmp_path, target, monkeypatch):
    out = tmp_path / "o"
    main(["fit", "--out", str(out), "--target", str(target), *TINY])
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert sorted(before) == ["fit.png", "loss_curve.png", "target.png"]

    def full(path, losses):  # the last of the three files runs out of space half way
        path.write_bytes(b"\x89PNG partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(fit_image, "_save_loss_curve", full)
    with pytest.raises(OSError, match=r"loss_curve\.png.*No space left.*other files are unchanged") as e:
        main(["fit", "--out", str(out), "--target", str(target), *TINY, "--seed", "1"])
    assert e.value.errno == errno.ENOSPC
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # no temp files, nothing replaced


@pytest.mark.parametrize("argv,named", [(["fit"], "--out"),
                                        (["fit", "--out", "o", "--gaussians", "many"], "--gaussians"),
                                        (["demo", "--seed", "x"], "--seed"),
                                        (["nope"], "'nope'")])
def test_argparse_errors_name_the_argument(argv, named, capsys):
    """Each mistake is one line naming the argument that is wrong (each case its own), exit 2."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("clsplat") and named in err[0], err


def test_missing_optional_package_names_the_extra(tmp_path, monkeypatch):
    import sys
    monkeypatch.setitem(sys.modules, "OpenImageIO", None)  # as if the io extra were not installed
    monkeypatch.delitem(sys.modules, "clsplat.io.images", raising=False)
    monkeypatch.delitem(sys.modules, "clsplat.io", raising=False)
    with pytest.raises(SystemExit, match=r"needs the optional package 'OpenImageIO'.*clsplat\[io\]"):
        main(["fit", "--out", str(tmp_path / "o"), *TINY])


def test_the_console_entry_point_prints_one_line_and_an_exit_status(tmp_path, target, monkeypatch, capsys):
    from clsplat.cli import console

    assert console(["fit", "--out", str(tmp_path / "o"), "--target", str(target), *TINY, "--lr", "nan"]) == 2
    assert capsys.readouterr().err.splitlines() == ["clsplat fit: lr must be a finite number > 0, got nan"]
    assert console(["fit", "--out", str(tmp_path / "o"), "--target", str(tmp_path / "nope.png"), *TINY]) == 2
    assert "nope.png" in capsys.readouterr().err

    def full(path, losses):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(fit_image, "_save_loss_curve", full)
    assert console(["fit", "--out", str(tmp_path / "o"), "--target", str(target), *TINY]) == 1
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("clsplat fit: writing ") and "loss_curve.png" in err[0]
    assert "No space left on device" in err[0] and "[Errno" not in err[0]
