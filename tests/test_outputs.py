"""Outputs never replace what they were not asked to write: devices and FIFOs are written into,
symlinks followed, loops refused with a message; ``--json -`` prints the record alone."""
import json
import os
import stat
import threading
from pathlib import Path

import numpy as np
import pytest

from vrnet_ext.cli import main
from vrnet_ext.geometry.atomic import OutputError, atomic_output, write_text_atomically
from vrnet_ext.geometry.io import write_ply


def test_a_device_is_written_into_and_never_replaced():
    """/dev/null is a character device: the block must be handed the device itself. On code that
    hands out a temporary file instead, the block raises, so nothing is renamed over /dev/null."""
    before = os.stat("/dev/null")
    with atomic_output("/dev/null") as path:
        if path != Path("/dev/null"):
            raise AssertionError(f"atomic_output('/dev/null') yielded {path}, which it would rename over the device")
        path.write_text("{}")
    after = os.stat("/dev/null")
    assert stat.S_ISCHR(after.st_mode) and after.st_rdev == before.st_rdev


def test_a_fifo_receives_the_output_and_stays_a_fifo(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    received = []
    reader = threading.Thread(target=lambda: received.append(fifo.read_text()), daemon=True)
    reader.start()
    write_text_atomically(fifo, "hello")
    reader.join(timeout=60)
    assert received == ["hello"] and stat.S_ISFIFO(os.stat(fifo).st_mode)


def test_a_symlink_is_followed_and_kept_and_a_loop_is_refused(tmp_path):
    target = tmp_path / "real.ply"
    link = tmp_path / "link.ply"
    link.symlink_to(target)
    write_ply(link, np.zeros((4, 3)))
    assert link.is_symlink() and target.is_file() and target.stat().st_size > 0
    loop = tmp_path / "loop.json"
    loop.symlink_to(loop)
    with pytest.raises(OutputError, match="loop.json"):
        write_text_atomically(loop, "{}")
    assert loop.is_symlink()
    with pytest.raises(OutputError, match="is a folder"):
        write_text_atomically(tmp_path, "{}")


def test_json_to_standard_output_is_the_record_alone(tmp_path, capsys):
    assert main(["demo", "--pairs", "1", "--out", str(tmp_path / "demo.png"), "--json", "-"]) == 0
    captured = capsys.readouterr()
    record = json.loads(captured.out)
    assert record["pairs"] and "mean rotation error" in captured.err
    assert not (Path.cwd() / "-").exists()


def test_a_picture_without_a_format_is_refused_before_any_work(tmp_path, capsys):
    for argv in (["demo", "--out", str(tmp_path / "picture")],
                 ["register", "a.ply", "b.ply", "--plot", str(tmp_path / "views.txt")]):
        with pytest.raises(SystemExit):
            main(argv)
        assert "give a picture file name ending in .png" in capsys.readouterr().err


def test_an_output_that_cannot_be_written_is_refused_before_any_work(tmp_path, capsys):
    """A symlink loop, and (where the machine has one) a pseudo file system that takes no new file:
    refused when the arguments are read, naming the path, with no traceback."""
    loop = tmp_path / "loop.json"
    loop.symlink_to(loop)
    cases = [(str(loop), "cannot be followed to a file")]
    if Path("/sys/kernel").is_dir():
        cases.append(("/sys/kernel/result.json", "cannot be written"))
    for target, message in cases:
        with pytest.raises(SystemExit):
            main(["register", "a.ply", "b.ply", "--json", target])
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, err
    assert loop.is_symlink() and not [p for p in tmp_path.iterdir() if p.name.endswith(".probe")]
