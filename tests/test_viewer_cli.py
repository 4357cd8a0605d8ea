"""``clsplat view`` (clsplat/viewer/cli.py): one-line errors with exit status 2 for a file that is
not a scene, a checkpoint of an unknown family, a port in use and a missing ``view`` extra; and a
served scene stops cleanly on Ctrl-C."""
import os
import queue
import signal
import socket
import subprocess
import sys
import threading

import pytest
import torch

from clsplat.cli import main

pytest.importorskip("viser", reason="the view extra (pip install 'clsplat[view]') is not installed")


def _one_line_error(capsys, prog="clsplat view"):
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"{prog}:"), err
    return err


def test_not_a_scene(tmp_path, capsys):
    f = tmp_path / "notes.txt"
    f.write_text("hello")
    assert main(["view", str(f), "--port", "0"]) == 2
    assert "is not a scene" in _one_line_error(capsys)
    bad_ply = tmp_path / "bad.ply"
    bad_ply.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    assert main(["view", str(bad_ply), "--port", "0"]) == 2
    err = _one_line_error(capsys)
    assert "bad.ply" in err and "not a Gaussian scene" in err
    assert main(["view", str(tmp_path / "missing.ply"), "--port", "0"]) == 2
    assert "no such file" in _one_line_error(capsys)
    assert main(["view", str(tmp_path), "--port", "0"]) == 2
    assert "without checkpoint.pt" in _one_line_error(capsys)


def test_not_a_scene_names_the_file(tmp_path, capsys):
    f = tmp_path / "notes.txt"
    f.write_text("hello")
    assert main(["view", str(f), "--port", "0"]) == 2
    err = _one_line_error(capsys)
    assert "notes.txt" in err and "not a scene" in err


def test_checkpoint_of_an_unknown_family(tmp_path, capsys):
    from clsplat.models.common.train import CHECKPOINT_FORMAT
    ck = tmp_path / "checkpoint.pt"
    torch.save({"format": CHECKPOINT_FORMAT, "family": "nerf", "model": {}, "preset": {"name": "x"}}, ck)
    for path in (ck, tmp_path):   # the file and its run folder
        assert main(["view", str(path), "--port", "0"]) == 2
        err = _one_line_error(capsys)
        assert "unknown model family 'nerf'" in err and "drivingforward" in err


def test_port_in_use(two_colour_ply, capsys):
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen(1)
    port = s.getsockname()[1]
    try:
        assert main(["view", str(two_colour_ply[0]), "--port", str(port)]) == 2
        err = _one_line_error(capsys)
        assert f"--port {port}" in err and "in use" in err
    finally:
        s.close()


def test_missing_view_extra_is_named(two_colour_ply, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "viser", None)   # import viser -> ModuleNotFoundError
    with pytest.raises(SystemExit) as e:
        main(["view", str(two_colour_ply[0]), "--port", "0"])
    assert "clsplat[view]" in str(e.value) and "'viser'" in str(e.value)


@pytest.mark.slow   # spawns clsplat view
def test_serves_and_stops_cleanly_on_ctrl_c(two_colour_ply, tmp_path):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    p = subprocess.Popen([sys.executable, "-c", "import sys; from clsplat.cli import main; sys.exit(main())",
                          "view", str(two_colour_ply[0]), "--port", "0"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=env)
    lines: queue.Queue = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(x) for x in p.stdout], daemon=True)
    reader.start()
    try:
        line = lines.get(timeout=120)
        assert "open http://127.0.0.1:" in line, line
        url = line.split("open ")[1].split()[0]
        import urllib.request
        page = urllib.request.urlopen(url, timeout=30).read()
        assert b"<html" in page.lower() or b"<!doctype html" in page.lower()   # viser's client page
        p.send_signal(signal.SIGINT)
        p.wait(timeout=30)
        reader.join(timeout=5)
        err = p.stderr.read()
        out = "".join(lines.get(timeout=5) for _ in range(lines.qsize()))
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 0, err
    assert "stopped" in out and "Traceback" not in err
