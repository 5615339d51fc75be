"""scripts/average_checkpoints.py: the mean of several runs' weights, written as a loadable pretrained_model."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "average_checkpoints.py"


def load_script():
    spec = importlib.util.spec_from_file_location("average_checkpoints", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_floats_are_averaged_and_integers_come_from_the_last_state():
    average = load_script().average_state_dicts
    states = [{"w": torch.tensor([1.0, 3.0]), "n": torch.tensor([1])},
              {"w": torch.tensor([2.0, 5.0]), "n": torch.tensor([2])},
              {"w": torch.tensor([6.0, 1.0]), "n": torch.tensor([7])}]
    averaged = average(states)
    torch.testing.assert_close(averaged["w"], torch.tensor([3.0, 3.0]))
    assert averaged["n"].tolist() == [7]
    with pytest.raises(ValueError, match="checkpoint 0 has other tensors"):
        average([{"v": torch.zeros(1)}, {"w": torch.zeros(1)}])


def test_the_cli_writes_a_whole_folder_and_names_a_missing_weights_file(tmp_path):
    folders = []
    for i, value in enumerate([0.0, 4.0]):
        folder = tmp_path / f"{i}" / "pretrained_model"
        folder.mkdir(parents=True)
        save_file({"w": torch.full((2, 2), value)}, str(folder / "model.safetensors"))
        (folder / "config.json").write_text(f'{{"step": {i}}}')
        folders.append(folder)
    out = tmp_path / "avg"
    subprocess.run([sys.executable, str(SCRIPT), "--output", str(out), *map(str, folders)], check=True)
    torch.testing.assert_close(load_file(str(out / "model.safetensors"))["w"], torch.full((2, 2), 2.0))
    assert (out / "config.json").read_text() == '{"step": 1}'  # the last checkpoint's config and processors
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporary folder left
    missing = subprocess.run([sys.executable, str(SCRIPT), "--output", str(out), str(tmp_path)],
                             capture_output=True, text=True)
    assert missing.returncode != 0 and f"{tmp_path / 'model.safetensors'} does not exist" in missing.stderr
