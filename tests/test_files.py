"""write_json_atomically: the file whole or untouched, with a plain file's mode, and no temporary left behind."""

from __future__ import annotations

import json
import os

import pytest

from lerobot_bcrl.files import write_json_atomically


def test_writes_json_with_the_umask_mode_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "nested" / "result.json"
    write_json_atomically(path, {"return": 1.5})
    assert json.loads(path.read_text()) == {"return": 1.5}
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask
    assert [p.name for p in path.parent.iterdir()] == ["result.json"]


def test_a_payload_that_fails_to_serialise_keeps_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "result.json"
    write_json_atomically(path, {"return": 1.5})
    with pytest.raises(TypeError):
        write_json_atomically(path, {"return": object()})
    assert json.loads(path.read_text()) == {"return": 1.5}
    assert [p.name for p in tmp_path.iterdir()] == ["result.json"]
